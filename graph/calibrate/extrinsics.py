"""Extrinsic calibration of a rig from board views seen by several cameras at the same instants.

1. Views are matched across cameras by frame (:func:`graph.calibrate.views.frame_key`). Cameras that
   saw the board in the same frame are linked; the number of such frames weighs the link. A graph in
   pieces is refused, naming its groups of cameras.
2. A start: the board's pose in every camera by PnP; along the maximum spanning tree of the graph
   from camera 1, each camera's pose relative to its parent is the robust middle (medoid) of the
   relative poses its shared frames give; each board view's pose comes from the camera that saw it
   best.
3. One bundle adjustment (:mod:`graph.calibrate.bundle`) over the camera poses (camera 1 fixed) and
   the board poses, with the board's known geometry and Huber's loss; views that stand out are
   dropped and the rest solved again. Intrinsics are held, or refined under the prior their own
   calibration gave them (never free: the board alone cannot hold a focal length that trades
   against distance when the views are few and far).
4. The world frame: camera 1 (``X_w = X_c1``), or the board of one frame (origin at its first corner,
   x along its rows, z up, to the side of the cameras). Metres.
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from graph.calibrate import bundle
from graph.calibrate.board import Board
from graph.calibrate.intrinsics import MIN_CORNERS, IntrinsicsResult, calibrate_intrinsics, observations, outlier_views
from graph.calibrate.model import LENSES, camera_with, intrinsics_of, lens_with_intrinsics
from graph.calibrate.poses import board_in_camera, compose, inverse, medoid
from graph.calibrate.views import BoardViews, frame_key
from graph.camera import FISHEYE, Calibration, Camera
from graph.errors import InputError

MAX_ROUNDS = 5  # solve, drop outlier views, solve again: at most this many times


@dataclass
class CameraReport:
    name: str
    rms_px: float
    views_used: int
    views_dropped: list[dict]
    position_std_mm: list[float]
    rotation_std_deg: list[float]
    intrinsics_change: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class RigResult:
    """A calibrated rig and how well it fits."""

    calibration: Calibration
    rms_px: float
    sigma_px: float
    cameras: list[CameraReport]
    overlap: list[dict]
    baselines_m: dict[str, float]
    frames_used: list[str]
    board_poses: dict[str, np.ndarray]  # frame -> 4x4 board-to-world
    residuals: list[np.ndarray]  # per camera (n, 2) pixels
    corners_used: list[np.ndarray]  # per camera (n, 2) pixels: the detections the solve kept
    iterations: int
    seconds: float
    origin: str
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"rms_px": self.rms_px, "sigma_px": self.sigma_px, "origin": self.origin,
                "cameras": [c.to_dict() for c in self.cameras], "overlap": self.overlap,
                "baselines_m": self.baselines_m, "frames_used": len(self.frames_used),
                "iterations": self.iterations, "seconds": self.seconds, "warnings": self.warnings,
                "units": "m"}


def overlap_graph(views: list[BoardViews]) -> dict[tuple[int, int], list[str]]:
    """Shared frames of each pair of cameras (i < j)."""
    keys = [{frame_key(f) for f in v.frames} for v in views]
    return {(i, j): sorted(keys[i] & keys[j]) for i, j in itertools.combinations(range(len(views)), 2)}


def connected_groups(n: int, edges: list[tuple[int, int]]) -> list[list[int]]:
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        parent[find(a)] = find(b)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


def spanning_tree(n: int, weights: dict[tuple[int, int], int], root: int = 0) -> list[tuple[int, int]]:
    """Prim's maximum spanning tree from ``root``: (parent, child) edges in the order they are added."""
    inside = {root}
    edges = []
    while len(inside) < n:
        best = max(((w, a, b) for (a, b), w in weights.items() if w > 0 and ((a in inside) ^ (b in inside))),
                   default=None)
        if best is None:
            break
        _, a, b = best
        parent, child = (a, b) if a in inside else (b, a)
        edges.append((parent, child))
        inside.add(child)
    return edges


def calibrate_extrinsics(views: list[BoardViews], board: Board, intrinsics: list[Camera] | None = None,
                         model: str = FISHEYE, origin: str = "camera1", refine_intrinsics: bool = False,
                         intrinsic_results: list[IntrinsicsResult] | None = None,
                         progress=None, lens: str = "full") -> RigResult:
    """The rig (see the module). ``intrinsics``: one camera each (from ``--intrinsics`` files); when
    None, each camera's intrinsics are calibrated from its own views first, fitting ``lens``
    (:data:`graph.calibrate.model.LENSES`)."""
    n = len(views)
    if n < 2:
        raise InputError("extrinsic calibration needs at least two cameras")
    names = [v.name for v in views]
    if len(set(names)) < n:
        names = [f"cam{i + 1}" for i in range(n)]
    notes: list[str] = []
    if lens not in LENSES:
        raise InputError(f"unknown lens {lens!r} ({', '.join(LENSES)})")
    if (intrinsics is not None or intrinsic_results) and (why := lens_with_intrinsics(lens)):
        raise InputError(why)
    if board.looks_like_mm():
        notes.append(f"the board's square is {board.square:g} m: is it given in millimetres? "
                     "Board lengths are in metres")
        warnings.warn(notes[-1])
    if intrinsics is None:
        intrinsic_results = intrinsic_results or []
        if not intrinsic_results:
            for i, v in enumerate(views):
                if progress:
                    progress(f"intrinsics {names[i]}", i / (n + 1))
                intrinsic_results.append(calibrate_intrinsics(v, board, model, lens))
        intrinsics = [r.camera for r in intrinsic_results]
    if len(intrinsics) != n:
        raise InputError(f"{len(intrinsics)} intrinsics files for {n} cameras")
    for i, (v, cam) in enumerate(zip(views, intrinsics)):
        if cam.size != (0, 0) and tuple(cam.size) != tuple(v.image_size):
            raise InputError(f"{names[i]}: the images are {v.image_size[0]}x{v.image_size[1]}, the intrinsics are "
                             f"for {cam.size[0]}x{cam.size[1]} (mismatched resolutions)", v.source or None)
    # 1. the overlap graph
    for i, v in enumerate(views):
        seen: dict[str, str] = {}
        for f in v.frames:
            other = seen.setdefault(frame_key(f), f)
            if other != f:
                raise InputError(f"{names[i]}: views {other} and {f} are both frame {frame_key(f)} (frames are "
                                 "matched across cameras by the last number in their names)", v.source or None)
    shared = overlap_graph(views)
    groups = connected_groups(n, [e for e, f in shared.items() if f])
    if len(groups) > 1:
        text = "; ".join("{" + ", ".join(names[i] for i in g) + "}" for g in groups)
        raise InputError(f"the cameras fall into {len(groups)} groups that never see the board at the same "
                         f"frame: {text}; record views the groups share")
    # 2. PnP per view and the start along the spanning tree
    obj = board.object_points()
    pnp: list[dict[str, tuple]] = []
    for i, v in enumerate(views):
        d = {}
        for k, f in enumerate(v.frames):
            if np.isfinite(v.corners[k]).all(axis=1).sum() < MIN_CORNERS:
                continue
            p = board_in_camera(intrinsics[i], v.corners[k], obj)
            if p is not None:
                d[frame_key(f)] = (p, k)
        pnp.append(d)
    weights = {e: len(set(pnp[e[0]]) & set(pnp[e[1]])) for e in shared}
    tree = spanning_tree(n, weights)
    if len(tree) < n - 1:
        groups = connected_groups(n, [e for e, w in weights.items() if w])
        text = "; ".join("{" + ", ".join(names[i] for i in g) + "}" for g in groups)
        raise InputError(f"the cameras fall into {len(groups)} groups with no board pose in common: {text}")
    scale = board.square * max(board.corner_grid)
    cam_pose = {0: (np.eye(3), np.zeros(3))}  # camera -> world (camera 1's frame)
    for parent, child in tree:
        common = sorted(set(pnp[parent]) & set(pnp[child]))
        rel = [compose(pnp[parent][f][0], inverse(pnp[child][f][0])) for f in common]  # child -> parent
        cam_pose[child] = compose(cam_pose[parent], rel[medoid(rel, scale)])
    frames = sorted({f for d in pnp for f in d if sum(f in e for e in pnp) >= 2}, key=_natural)
    if not frames:
        raise InputError("no frame shows the board to two cameras")
    board_pose = [board_start(f, cam_pose, pnp, range(n), scale) for f in frames]
    which = [[pnp[i][f][1] for f in frames if f in pnp[i]] for i in range(n)]
    boards = [[b for b, f in enumerate(frames) if f in pnp[i]] for i in range(n)]
    views_frames = [[f for f in frames if f in pnp[i]] for i in range(n)]
    rig = bundle.Rig([c.model for c in intrinsics], [intrinsics_of(c) for c in intrinsics],
                     np.stack([cam_pose[i][0] for i in range(n)]), np.stack([cam_pose[i][1] for i in range(n)]),
                     np.stack([p[0] for p in board_pose]), np.stack([p[1] for p in board_pose]))
    priors = {}
    if refine_intrinsics:
        for i, cam in enumerate(intrinsics):
            prior_cov = intrinsic_results[i].covariance if intrinsic_results else None
            if prior_cov is None:
                raise InputError(f"{names[i]}: refining intrinsics needs their uncertainty (calibrate them "
                                 "here, or leave them fixed)")
            priors[i] = (intrinsics_of(cam), information_root(prior_cov))
    # 3. the bundle adjustment, dropping outlier views
    obs = observations(views, board, which, list(range(n)), boards)
    view_cam = obs.cam.copy()
    view_frame = [views_frames[i][k] for i in range(n) for k in range(len(which[i]))]
    keep = np.ones(obs.n_views, bool)
    dropped: list[list[dict]] = [[] for _ in range(n)]
    total_it, total_s = 0, 0.0
    for round_ in range(MAX_ROUNDS):
        views_left = np.bincount(view_cam[keep], minlength=n)
        if (views_left == 0).any():
            i = int(np.flatnonzero(views_left == 0)[0])
            raise InputError(f"{names[i]}: every board view of this camera was dropped as an outlier; its pose "
                             "is not determined")
        cur = obs.keep_views(keep)
        if progress:
            progress("bundle adjustment", (n + round_ / MAX_ROUNDS) / (n + 1))
        sigma = bundle.noise_sigma(bundle.residuals(rig, cur, jacobians=False))
        # the data terms are pixels, the priors' rows noise sd: scaled by the noise, the posterior is the
        # one the intrinsic calibrations' covariances and this noise say
        settings = bundle.Settings(fixed_cams=frozenset({0}), huber_px=bundle.HUBER_SIGMAS * sigma,
                                   free_intrinsics={i: (t0, sigma * L) for i, (t0, L) in priors.items()})
        sol = bundle.solve(rig, cur, settings)
        total_it += sol.iterations
        total_s += sol.seconds
        rig = sol.rig
        sigma = bundle.noise_sigma(sol.residuals)
        rms = bundle.view_rms(sol.residuals, cur)
        bad = worst_per_frame(outliers_within_cameras(rms, cur.cam), rms, [view_frame[g] for g in np.flatnonzero(keep)])
        if not bad.any():
            break
        if round_ == MAX_ROUNDS - 1:  # a view dropped after the last solve would not be solved: kept, and said
            notes.append(f"{int(bad.sum())} view(s) still stand out after {MAX_ROUNDS} rounds of dropping outliers "
                         "and are kept: " + ", ".join(f"{names[view_cam[g]]} {view_frame[g]}"
                                                     for g in np.flatnonzero(keep)[bad]))
            warnings.warn(notes[-1])
            break
        idx = np.flatnonzero(keep)
        for worst_view in np.flatnonzero(bad):
            g = idx[worst_view]
            dropped[view_cam[g]].append({"frame": view_frame[g], "reason": f"outlier: {rms[worst_view]:.2f} px RMS, "
                                         f"median view {np.median(rms):.2f} px"})
            keep[g] = False
            # the frame's board pose again, from the views left (it may have followed the wrong one)
            b = frames.index(view_frame[g])
            left = [int(view_cam[h]) for h in np.flatnonzero(keep) if view_frame[h] == view_frame[g]]
            poses = {i: (rig.R_cam[i], rig.t_cam[i]) for i in range(n)}
            rig.R_board[b], rig.t_board[b] = board_start(view_frame[g], poses, pnp, left, scale)
    e = sol.residuals  # the last round dropped nothing: its views ``cur`` are the ones kept
    # 4. uncertainty and the world frame
    full, eq = bundle.camera_covariance(rig, cur, settings, sigma)
    cov = {i: full[a:z, a:z] for i, (a, z) in eq.cam_slots.items()}
    to_world = _origin_transform(origin, frames, rig, views)
    cams, reports, residuals, corners_used = [], [], [], []
    c_of = cur.cam[cur.view]
    for i in range(n):
        Rw, tw = compose(to_world, (rig.R_cam[i], rig.t_cam[i]))
        cam = camera_with(rig.intrinsics[i], rig.models[i], views[i].image_size, names[i], R=Rw.T, t=-Rw.T @ tw)
        cams.append(cam)
        ei = e[c_of == i]
        residuals.append(ei)
        corners_used.append(cur.uv[c_of == i])
        if i == 0:
            pos, rot = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        else:
            C = cov[i]
            Rc = to_world[0] @ rig.R_cam[i]
            pos = (np.sqrt(np.diag(Rc @ C[3:, 3:] @ Rc.T)) * 1000).tolist()
            rot = np.degrees(np.sqrt(np.diag(C[:3, :3]))).tolist()
        change = {}
        if i in priors:
            th0, th = intrinsics_of(intrinsics[i]), rig.intrinsics[i]
            change = {"fx": th[0] - th0[0], "fy": th[1] - th0[1], "cx": th[2] - th0[2], "cy": th[3] - th0[3]}
        reports.append(CameraReport(names[i], float(np.sqrt((ei * ei).sum(axis=1).mean())) if len(ei) else math.nan,
                                    int((cur.cam == i).sum()), dropped[i], pos, rot, change))
    centres = [c.center for c in cams]
    baselines = {f"{names[a]}-{names[b]}": float(np.linalg.norm(centres[a] - centres[b]))
                 for a, b in itertools.combinations(range(n), 2)}
    overlap = [{"cameras": [names[a], names[b]], "shared_views": w} for (a, b), w in weights.items() if w]
    board_poses = {}
    for b, f in enumerate(frames):
        R, t = compose(to_world, (rig.R_board[b], rig.t_board[b]))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        board_poses[f] = T
    calibration = Calibration(cameras=cams, metadata={
        "error": float(np.sqrt((e * e).sum(axis=1).mean())), "units": "m", "origin": origin, "board": board.spec})
    return RigResult(calibration, float(np.sqrt((e * e).sum(axis=1).mean())), sigma, reports, overlap, baselines,
                     frames, board_poses, residuals, corners_used, total_it, total_s, origin, notes)


def information_root(cov: np.ndarray) -> np.ndarray:
    """``L`` with ``L^T L = cov^-1``, by the eigenvectors: ``L = diag(w^-1/2) V^T`` for ``cov = V diag(w)
    V^T``. Cholesky's factor of the inverse fails on a held lens's covariance (variances of 1e-12 beside
    ones of order 1), which the eigenvalues take in their stride."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.maximum(w, w.max() * 1e-30)
    return (V / np.sqrt(w)).T


def board_start(frame: str, cam_pose: dict, pnp: list[dict], cams, scale: float) -> tuple:
    """The board's pose in the world at ``frame``: the medoid of what each camera's PnP says (camera
    pose composed with the board's pose in it), so that one camera's wrong detection is outvoted."""
    cand = [compose(cam_pose[i], pnp[i][frame][0]) for i in cams if frame in pnp[i]]
    if not cand:
        return np.eye(3), np.zeros(3)
    return cand[medoid(cand, scale)]


def outliers_within_cameras(rms: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """:func:`graph.calibrate.intrinsics.outlier_views` among each camera's own views: a camera that
    fits worse than the others throughout (a softer lens, a blurrier sensor: SLEAP's side camera,
    0.53 px against 0.3-0.4) is not made of outliers. Compared over all cameras at once, every one of
    its views stood out once the other cameras' intrinsics were refined, and all were dropped in one
    round, leaving its pose to nothing."""
    bad = np.zeros(len(rms), bool)
    for i in np.unique(cam):
        mine = cam == i
        bad[mine] = outlier_views(rms[mine])
    return bad


def worst_per_frame(bad: np.ndarray, rms: np.ndarray, frames: list[str]) -> np.ndarray:
    """Of the outlier views ``bad`` of each frame, only the worst: one wrong detection spoils the
    board's pose and with it the other cameras' views of that frame, which fit again once it is gone."""
    out = np.zeros_like(bad)
    worst: dict[str, int] = {}
    for v in np.flatnonzero(bad):
        if frames[v] not in worst or rms[v] > rms[worst[frames[v]]]:
            worst[frames[v]] = int(v)
    out[list(worst.values())] = True
    return out


def _natural(s: str):
    return (0, int(s), "") if s.isdigit() else (1, 0, s)


def _origin_transform(origin: str, frames: list[str], rig: bundle.Rig, views: list[BoardViews]):
    """The transform from camera 1's frame to the world: identity for ``camera1``; for ``board:FRAME``
    the inverse of that board's pose, turned half a turn about x when the cameras sit on the board's
    -z side (so that z points up, towards them)."""
    if origin in ("camera1", "camera", "cam1"):
        return np.eye(3), np.zeros(3)
    if not origin.startswith("board:"):
        raise InputError(f"--origin: expected camera1 or board:FRAME, got {origin!r}")
    frame = origin.split(":", 1)[1]
    keys = {frame_key(frame), frame}
    match = [b for b, f in enumerate(frames) if f in keys]
    if not match:
        raise InputError(f"--origin {origin}: no frame {frame!r} among the board views the cameras share "
                         f"(e.g. {', '.join(frames[:5])})")
    b = match[0]
    T = inverse((rig.R_board[b], rig.t_board[b]))
    centres_z = [(T[0] @ rig.t_cam[i] + T[1])[2] for i in range(len(rig.t_cam))]
    if np.median(centres_z) < 0:
        flip = np.diag([1.0, -1.0, -1.0])
        T = (flip @ T[0], flip @ T[1])
    return T
