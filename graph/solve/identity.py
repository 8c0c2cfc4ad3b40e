"""Identity across views and time: which detection in each camera is which individual.

A 2D tracker (multi-animal DeepLabCut, SLEAP) gives each camera's detections in slots, its own
identities, which it swaps now and then, independently in every camera; OpenPose gives none. Solving
each slot as an animal (what per-track triangulation does) mixes two animals whenever one camera has
swapped them. Here the 3D geometry decides, frame by frame, carried across time by a motion model:

1. **Tracks in 3D.** Each individual ``i`` keeps its last triangulated markers ``X_i`` (M, 3), the
   frame ``t_i`` they are from and its centroid's velocity ``v_i``. Its prediction at frame ``t`` is
   ``P_i = X_i + (t - t_i) v_i`` (constant velocity); a track unseen for more than :data:`MAX_GAP`
   frames is lost (it can be found again).

2. **Detections to tracks, per camera.** The cost of detection ``k`` for individual ``i`` is the
   median over the markers both have of the pixel distance between the detection and ``P_i``
   projected into the camera (at least :data:`MIN_COMMON` markers, else no match), plus a hysteresis
   ``h`` where the slot belonged to another individual in its last frame (the 2D identity is kept
   unless the geometry disagrees by more than ``h``; none for unidentified slots). The assignment
   minimising the summed cost is found by the Hungarian method
   (``scipy.optimize.linear_sum_assignment``); a pair costing more than the gate ``g`` is not
   matched. ``g`` and ``h`` scale with the detection's size ``s`` (the diagonal of its confident
   markers' bounding box, at least :data:`MIN_SIZE_PX`): ``g = GATE s``, ``h = HYSTERESIS s``.
   ``h`` only breaks near ties: measured on simulated groups of 2 and 3 (``bench/bench_group.py``'s
   runs, seeds 0-6), detections given to the wrong animal were 0.16 % with ``h = 0.1 s`` (two animals
   overlapping in one camera, 17-31 px apart there, kept the tracker's swap for 25 frames), none
   or 0.001 % with 0.02 and 0.

3. **New and lost tracks.** Detections left over, while fewer than the number of individuals are
   tracked, are grouped across cameras from scratch: the camera with most of them is the reference;
   every other camera's are matched to its by the symmetric epipolar distance of their markers
   (with ``x_a, x_b`` a marker's normalised coordinates in cameras ``a, b`` and ``E = [t]_x R`` the
   pair's essential matrix, the distance of ``x_b`` from the line ``E x_a``, in pixels of ``b``, and
   back), by the Hungarian method and the same gate. A group seen by two cameras or more is
   triangulated; members whose reprojection is beyond the gate leave it. A group becomes the lost
   track nearest in 3D, or a new one.

4. **Triangulation.** Each individual's detections of the frame are triangulated robustly (the
   compiled :func:`graph.solve.kernels.triangulate_points`, Cauchy-weighted Gauss-Newton from the best
   DLT candidate), which updates its track: ``v <- (v + d / dt) / 2``, ``d`` the median over the
   markers seen in both frames of their displacement (one marker triangulated wrong cannot throw it).

The answer: every slot of every camera and frame has an individual or none (``slot_owner``), and
each individual's detections per camera, to solve as one animal with any method. A slot whose
individual changes between its frames is counted as a 2D identity switch corrected, once a camera
and frame (a swap of two slots is one): a reassignment, so a swap next to a missing detection
counts twice, and a wrong assignment undone counts too (on the bench 5-10 % more than the swaps
simulated).

The number of individuals is given, or found (:func:`count_individuals`): per frame, the median
over the cameras that see anyone of how many detections each has; the largest count reached in at
least :data:`FOUND_SHARE` of frames.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from graph.camera import Calibration, undistort_points
from graph.errors import InputError
from graph.io.keypoint_types import Keypoints, Tracks
from graph.solve import kernels

MIN_COMMON = 2  # markers a detection and a prediction must share to be compared
MIN_POINTS = 3  # confident markers that make a detection (fewer: ignored for identity)
MIN_SIZE_PX = 20.0  # a detection's size for the gate and hysteresis, at least
GATE = 1.0  # the largest cost matched, in detection sizes
HYSTERESIS = 0.02  # the 2D identity's advantage, in detection sizes: a tie-breaker (module docstring)
MAX_GAP = 30  # frames a track may go unseen before it is lost
FOUND_SHARE = 0.05  # the share of frames a count of individuals must be seen in to be found
TRIANGULATION_PX = 5.0  # the robust triangulation's scale (its Cauchy loss), pixels
BIG = 1e12


@dataclass
class Identities:
    """Who is who: ``names`` (I,), each individual's detections per camera (``keypoints[i][c]``),
    the individual of every slot (``slot_owner`` (C, N, K), -1: none) and the switches corrected
    per camera."""

    names: list[str]
    keypoints: list[list[Keypoints]]
    slot_owner: list[np.ndarray]  # per camera (N, K_c)
    switches: list[int]
    cameras: list[str]
    found: bool  # the count was found (not given)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        frames = self.slot_owner[0].shape[0] if self.slot_owner else 0
        seen = {name: int(sum(((o == i).any(axis=1)).sum() for o in self.slot_owner))
                for i, name in enumerate(self.names)}
        return {"individuals": list(self.names), "count": "found" if self.found else "given", "frames": frames,
                "switches_corrected": dict(zip(self.cameras, self.switches)),
                "camera_frames_seen": seen, "notes": list(self.notes)}


def count_individuals(tracks: list[Tracks], likelihood_threshold: float) -> int:
    """How many individuals the cameras see (module docstring); at least 1."""
    counts = np.stack([_present(t, likelihood_threshold).sum(axis=1) for t in tracks])  # (C, N)
    seeing = np.where(counts > 0, counts, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        per_frame = np.floor(np.nanmedian(seeing, axis=0))
    per_frame = per_frame[np.isfinite(per_frame)].astype(int)
    if per_frame.size == 0:
        return 1
    for n in range(int(per_frame.max()), 0, -1):
        if (per_frame >= n).mean() >= FOUND_SHARE:
            return n
    return 1


def _present(t: Tracks, threshold: float) -> np.ndarray:
    """(N, K) the slot holds a detection: at least :data:`MIN_POINTS` confident markers (or all, if fewer)."""
    conf = (t.likelihood >= threshold) & np.isfinite(t.xy).all(-1)
    return conf.sum(axis=-1) >= min(MIN_POINTS, len(t.bodyparts))


def assign(tracks: list[Tracks], calibration: Calibration, individuals: int | None = None,
           likelihood_threshold: float = 0.5) -> Identities:
    """Each camera's slots assigned to ``individuals`` (None: :func:`count_individuals`) by geometry
    and motion (module docstring)."""
    if len(tracks) != len(calibration):
        raise InputError(f"{len(tracks)} keypoint files for {len(calibration)} cameras")
    bodyparts = tracks[0].bodyparts
    for t in tracks[1:]:
        if t.bodyparts != bodyparts:
            raise InputError("the cameras' files name different bodyparts; identities need the same ones", t.source)
    found = individuals is None
    n_ind = count_individuals(tracks, likelihood_threshold) if individuals is None else int(individuals)
    if n_ind < 1:
        raise InputError(f"--individuals must be at least 1, not {n_ind}")
    matcher = _Matcher(tracks, calibration, likelihood_threshold)
    owner = matcher.run(n_ind)  # the serial triangulation kernel: a frame's few points (graph.compiled)
    names = _names(tracks, owner, n_ind)
    order = sorted(range(n_ind), key=lambda i: _natural(names[i]))  # animal1, animal2, ..., animal10
    rank = np.argsort(order)
    owner = [np.where(o >= 0, rank[np.maximum(o, 0)], -1) for o in owner]
    names = [names[i] for i in order]
    keypoints = [[_detections(t, o, i) for t, o in zip(tracks, owner)] for i in range(n_ind)]
    switches = [_switches(o) if t.identified else 0 for t, o in zip(tracks, owner)]
    notes = []
    for i, name in enumerate(names):
        if not any((o == i).any() for o in owner):
            notes.append(f"individual {name} was never seen by two cameras at once")
    return Identities(names=names, keypoints=keypoints, slot_owner=owner, switches=switches,
                      cameras=list(calibration.names), found=found, notes=notes)


class _Matcher:
    """The frame-by-frame assignment (module docstring, steps 1-4)."""

    def __init__(self, tracks: list[Tracks], calibration: Calibration, threshold: float):
        self.tracks = tracks
        self.cal = calibration
        self.C = len(tracks)
        self.N = tracks[0].frames
        self.M = len(tracks[0].bodyparts)
        self.conf = [(t.likelihood >= threshold) & np.isfinite(t.xy).all(-1) for t in tracks]  # (N, K, M)
        self.present = [_present(t, threshold) for t in tracks]
        self.norm = [undistort_points(cam, t.xy) for cam, t in zip(calibration.cameras, tracks)]  # (N, K, M, 2)
        self.size = [self._sizes(t.xy, c) for t, c in zip(tracks, self.conf)]  # (N, K)
        self.intr, self.Rc, self.tc = calibration.packed()
        self.Pm = np.stack([np.hstack([cam.R, cam.t[:, None]]) for cam in calibration.cameras])
        self.focal = np.array([cam.K[0, 0] for cam in calibration.cameras])
        self.E = {(a, b): _essential(calibration.cameras[a], calibration.cameras[b])
                  for a in range(self.C) for b in range(self.C) if a != b}

    @staticmethod
    def _sizes(xy: np.ndarray, conf: np.ndarray) -> np.ndarray:
        pts = np.where(conf[..., None], xy, np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            span = np.nanmax(pts, axis=2) - np.nanmin(pts, axis=2)  # (N, K, 2)
        return np.maximum(np.nan_to_num(np.hypot(span[..., 0], span[..., 1])), MIN_SIZE_PX)

    def run(self, n_ind: int) -> list[np.ndarray]:
        from scipy.optimize import linear_sum_assignment

        self.hungarian = linear_sum_assignment
        owner = [np.full(t.xy.shape[:2], -1, dtype=np.int64) for t in self.tracks]
        last_owner = [np.full(t.slots, -1, dtype=np.int64) for t in self.tracks]
        X = np.full((n_ind, self.M, 3), np.nan)  # each track's last markers
        seen = np.full(n_ind, -(10**9), dtype=np.int64)  # the frame they are from
        vel = np.zeros((n_ind, 3))
        born = np.zeros(n_ind, dtype=bool)
        for t in range(self.N):
            alive = [i for i in range(n_ind) if born[i] and t - seen[i] <= MAX_GAP]
            pred = X + (t - seen)[:, None, None] * vel[:, None, :]
            taken = [np.zeros(tr.slots, dtype=bool) for tr in self.tracks]
            for c in range(self.C):
                dets = np.flatnonzero(self.present[c][t])
                if not alive or not dets.size:
                    continue
                cost = self._reprojection_cost(c, t, pred[alive], dets)
                if self.tracks[c].identified:
                    prev = last_owner[c][dets]
                    hyst = HYSTERESIS * self.size[c][t, dets]
                    cost = cost + np.where((prev[None, :] >= 0) & (prev[None, :] != np.array(alive)[:, None]),
                                           hyst[None, :], 0.0)
                for r, k in self._match(cost, GATE * self.size[c][t, dets]):
                    owner[c][t, dets[k]] = alive[r]
                    taken[c][dets[k]] = True
            free = [i for i in range(n_ind) if i not in alive]
            if free:
                for group, Xg in self._new_groups(t, taken, len(free)):
                    i = self._adopt(free, Xg, X, born)
                    free.remove(i)
                    for c, k in group:
                        owner[c][t, k] = i
            self._update(t, owner, X, seen, vel, born, n_ind)
            for c in range(self.C):
                here = owner[c][t] >= 0
                last_owner[c][here] = owner[c][t][here]
        return owner

    def _reprojection_cost(self, c: int, t: int, P: np.ndarray, dets: np.ndarray) -> np.ndarray:
        """(alive, dets): median pixel distance of each detection from each prediction projected."""
        with np.errstate(all="ignore"):
            uv = self.cal.cameras[c].project(P.reshape(-1, 3)).reshape(P.shape[0], self.M, 2)
        d = np.linalg.norm(uv[:, None] - self.tracks[c].xy[t, dets][None], axis=-1)  # (I, D, M)
        ok = self.conf[c][t, dets][None] & np.isfinite(d)
        return _median_cost(d, ok)

    def _match(self, cost: np.ndarray, gate: np.ndarray) -> list[tuple[int, int]]:
        """The Hungarian assignment of ``cost`` (rows to columns), pairs within column ``gate`` only."""
        finite = np.where(np.isfinite(cost), cost, BIG)
        rows, cols = self.hungarian(finite)
        return [(int(r), int(k)) for r, k in zip(rows, cols) if cost[r, k] <= gate[k]]

    def _new_groups(self, t: int, taken: list[np.ndarray], room: int) -> list[tuple[list[tuple[int, int]], np.ndarray]]:
        """Detections not taken, grouped across cameras by epipolar distance (module docstring, step 3):
        up to ``room`` groups of (camera, slot), each with its triangulated markers."""
        left = [np.flatnonzero(self.present[c][t] & ~taken[c]) for c in range(self.C)]
        ref = int(np.argmax([len(d) for d in left]))
        if len(left[ref]) == 0:
            return []
        groups: list[list[tuple[int, int]]] = [[(ref, int(k))] for k in left[ref]]
        for c in range(self.C):
            if c == ref or not len(left[c]):
                continue
            cost = self._epipolar_cost(ref, c, t, left[ref], left[c])
            for r, k in self._match(cost, GATE * self.size[c][t, left[c]]):
                groups[r].append((c, int(left[c][k])))
        out = []
        for g in groups:
            for _ in range(2):  # triangulate; drop members beyond the gate; once more
                if len({c for c, _ in g}) < 2:
                    break
                Xg = self._triangulate([g], t)[0]
                keep = [(c, k) for c, k in g if self._reprojection_cost(c, t, Xg[None], np.array([k]))[0, 0]
                        <= GATE * self.size[c][t, k]]
                if keep == g:
                    out.append((g, Xg))
                    break
                g = keep
        out.sort(key=lambda gx: -len(gx[0]))
        return out[:room]

    def _epipolar_cost(self, a: int, b: int, t: int, da: np.ndarray, db: np.ndarray) -> np.ndarray:
        """(len(da), len(db)): median symmetric epipolar distance (pixels) of the detections' markers."""
        xa = _homogeneous(self.norm[a][t, da])  # (A, M, 3)
        xb = _homogeneous(self.norm[b][t, db])  # (B, M, 3)
        la = xa @ self.E[(a, b)].T  # lines in b
        lb = xb @ self.E[(b, a)].T  # lines in a
        num = np.abs(np.einsum("bmk,amk->abm", xb, la))
        d_b = num / np.hypot(la[..., 0], la[..., 1])[:, None] * self.focal[b]
        d_a = num / np.hypot(lb[..., 0], lb[..., 1])[None] * self.focal[a]
        d = 0.5 * (d_a + d_b)
        ok = self.conf[a][t, da][:, None] & self.conf[b][t, db][None] & np.isfinite(d)
        return _median_cost(d, ok)

    def _triangulate(self, groups: list[list[tuple[int, int]]], t: int) -> np.ndarray:
        """(G, M, 3): each group's detections (camera, slot) of frame ``t`` triangulated."""
        G = len(groups)
        norm = np.zeros((G, self.M, self.C, 2))
        z = np.zeros((G, self.M, self.C, 2))
        ok = np.zeros((G, self.M, self.C), dtype=bool)
        for g, members in enumerate(groups):
            for c, k in members:
                norm[g, :, c] = self.norm[c][t, k]
                z[g, :, c] = self.tracks[c].xy[t, k]
                ok[g, :, c] = self.conf[c][t, k]
        ok &= np.isfinite(norm).all(-1)
        Xk, _ = kernels.triangulate_points(np.nan_to_num(norm.reshape(-1, self.C, 2)),
                                           np.nan_to_num(z.reshape(-1, self.C, 2)), ok.reshape(-1, self.C),
                                           self.intr, self.Rc, self.tc, self.Pm, TRIANGULATION_PX, 10)
        return Xk.reshape(G, self.M, 3)

    def _adopt(self, free: list[int], Xg: np.ndarray, X: np.ndarray, born: np.ndarray) -> int:
        """The free individual a new group becomes: the lost track nearest in 3D, else an unborn one."""
        lost = [i for i in free if born[i]]
        unborn = [i for i in free if not born[i]]
        if unborn and not lost:
            return unborn[0]
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            d = [float(np.nanmedian(np.linalg.norm(X[i] - Xg, axis=-1))) for i in lost]
        d = [v if np.isfinite(v) else BIG for v in d]
        return unborn[0] if unborn and min(d) == BIG else lost[int(np.argmin(d))]

    def _update(self, t: int, owner: list[np.ndarray], X: np.ndarray, seen: np.ndarray, vel: np.ndarray,
                born: np.ndarray, n_ind: int) -> None:
        """Triangulate each individual's detections of frame ``t``; update its track."""
        groups = [[(c, int(k)) for c in range(self.C) for k in np.flatnonzero(owner[c][t] == i)] for i in range(n_ind)]
        have = [g for g in range(n_ind) if len({c for c, _ in groups[g]}) >= 2]
        if not have:
            return
        Xnew = self._triangulate([groups[g] for g in have], t)
        for j, i in enumerate(have):
            Xi = Xnew[j]
            good = np.isfinite(Xi).all(-1)
            if not good.any():
                continue
            both = good & np.isfinite(X[i]).all(-1)
            if born[i] and both.any() and t > seen[i]:
                step = np.median(Xi[both] - X[i][both], axis=0) / (t - seen[i])
                vel[i] = 0.5 * (vel[i] + step) if t - seen[i] == 1 else step
            elif not born[i]:
                vel[i] = 0.0
            X[i][good] = Xi[good]
            seen[i] = t
            born[i] = True


def _median_cost(d: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Median of ``d`` (..., M) over the markers ``ok``; inf with fewer than :data:`MIN_COMMON`."""
    ranked = np.sort(np.where(ok, d, np.inf), axis=-1)  # the markers ok first, in order
    count = ok.sum(-1)
    lo = np.take_along_axis(ranked, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(ranked, np.maximum(count // 2, 0)[..., None], axis=-1)[..., 0]
    return np.where(count >= MIN_COMMON, 0.5 * (lo + hi), np.inf)


def _homogeneous(x: np.ndarray) -> np.ndarray:
    return np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)


def _essential(a, b) -> np.ndarray:
    """The essential matrix ``E`` of cameras ``a`` to ``b``: ``x_b^T E x_a = 0`` for normalised coordinates."""
    R = b.R @ a.R.T
    tt = b.t - R @ a.t
    tx = np.array([[0, -tt[2], tt[1]], [tt[2], 0, -tt[0]], [-tt[1], tt[0], 0]])
    return tx @ R


def _names(tracks: list[Tracks], owner: list[np.ndarray], n_ind: int) -> list[str]:
    """Each individual's name: the 2D name its slots carried most often (identified slots), unique;
    else ``individual<i>``."""
    votes: list[dict[str, int]] = [{} for _ in range(n_ind)]
    for t, o in zip(tracks, owner):
        if not t.identified:
            continue
        for k, name in enumerate(t.names):
            if not name:
                continue
            ids, counts = np.unique(o[:, k][o[:, k] >= 0], return_counts=True)
            for i, n in zip(ids, counts):
                votes[int(i)][name] = votes[int(i)].get(name, 0) + int(n)
    names: list[str] = []
    for i in range(n_ind):
        ranked = sorted(votes[i].items(), key=lambda kv: -kv[1])
        pick = next((n for n, _ in ranked if n not in names), f"individual{i + 1}")
        names.append(pick if pick not in names else f"individual{i + 1}")
    return names


def _natural(name: str) -> tuple:
    """A name's sort key with its runs of digits as numbers."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name))


def _detections(t: Tracks, owner: np.ndarray, i: int) -> Keypoints:
    """Individual ``i``'s detections in one camera: the slot it owns in each frame (NaN where none)."""
    N, K = owner.shape
    xy = np.full((N, len(t.bodyparts), 2), np.nan)
    lik = np.zeros((N, len(t.bodyparts)))
    for k in range(K):
        rows = owner[:, k] == i
        xy[rows] = t.xy[rows, k]
        lik[rows] = t.likelihood[rows, k]
    return Keypoints(bodyparts=list(t.bodyparts), xy=xy, likelihood=lik, scorer=t.scorer, source=t.source, fps=t.fps)


def _switches(owner: np.ndarray) -> int:
    """Frames in which a slot's individual differs from the one it had in its last assigned frame."""
    last = np.full(owner.shape[1], -1)
    count = 0
    for row in owner:
        here = row >= 0
        count += bool(np.any(here & (last >= 0) & (row != last)))
        last = np.where(here, row, last)
    return count
