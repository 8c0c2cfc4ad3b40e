"""Refining a rig's extrinsics from an animal's keypoints (``acinoset calibrate refine``).

1. Confident keypoints (likelihood at least ``min_likelihood``) seen by three or more cameras are
   triangulated robustly (:func:`graph.solve.triangulate.robust_points`, with the rig of step 2); at most
   :data:`MAX_POINTS` of them, spread evenly over the run, become unknowns.
2. A camera that is off, further than the adjustment could bring it back (its detections beyond the
   trimming below), is first posed again from the other cameras' points
   (:mod:`graph.calibrate.resection`): a bumped camera, or an entry copied from another camera's.
3. A bundle adjustment (:mod:`graph.calibrate.bundle`, the points as 3-dof "boards") over the camera
   poses and the 3D points, under Huber's loss: one camera is held (the first not posed again in
   step 2, or the one named), and so is its distance to the next (keypoints carry no scale); the
   intrinsics are held, or each camera's focal length and first distortion coefficient are refined
   under a prior centred on the old values (:func:`lens_prior`). Before each of :data:`ROUNDS`
   solves, the detections further than 3.03 noise sd from their prediction are left out (the noise
   measured as ``median |e| / 1.1774``), so DeepLabCut's confident mistakes neither pull the rig nor slow the
   solve to a crawl (Huber's loss alone converges linearly when many terms sit on its linear part).
   Each pose has a prior centred where step 2 left it (:func:`pose_priors`, sd ``pose_sd_deg``).
4. A camera the adjustment moves beyond :data:`MOVE_WARN_SD` sd of that prior is held where it was,
   the others adjusted again, and the report says so. Keypoints carry errors of their own that a
   rig can absorb: on SLEAP's session (a mouse seen through a curved acrylic wall) the keypoints
   turn the cameras 16-40 degrees away from the two board calibrations, which agree within 1
   degree, further the longer the solve runs and depending on where it starts; on the fly the pose
   camera C takes differs by 5 degrees between halves of the recording. Such a move fits the
   keypoints, predicts held-out frames of the same recording better (the check below cannot see it)
   and is not the rig's.
5. The check, on frames the adjustment did not use: the run is cut into :data:`BLOCKS` blocks of
   consecutive frames, and the adjustment takes its points from every other block (the first, third,
   ...); the blocks between are held out. Leave each camera out in turn, triangulate every point of
   the held-out frames from the others, reproject it into the camera left out and take the median
   error of its confident detections. The new rig replaces the old only when the mean of these
   medians falls by at least :data:`MIN_GAIN`; otherwise the old rig is kept and the report says
   why. The same score on the frames adjusted on is reported beside it: a rig can fit the frames it
   was adjusted on better and predict new ones no better (the fly: 3.64 -> 3.17 px on its own
   frames, no better on the next 250), and then it is not kept. Interleaved blocks, not a random
   half of the frames: neighbouring frames are nearly the same pose, so a random split would score
   the adjustment on frames it has all but seen. Runs shorter than :data:`MIN_SPLIT_FRAMES` frames
   are scored on the frames adjusted on, and the report says so.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from graph.calibrate import bundle
from graph.calibrate.model import HELD, camera_with, intrinsics_of
from graph.calibrate.poses import rotation_angle
from graph.calibrate.resection import errors, repose_off_cameras
from graph.camera import CALIBRATION_UNITS, Calibration, Camera
from graph.errors import InputError
from graph.io.calibration import resolve_units
from graph.solve.noise import RAYLEIGH_MEDIAN

MAX_POINTS = 20000  # 3D points in the adjustment, spread over the run. Measured on the simulated cheetah
# (AcinoSet rig, 3 px noise): the poses' error falls as 1 / sqrt(points) (600 frames from the true rig: 1500
# points 11.7 mm, all 7808 6.0 mm), and a step costs 11 ms per 1500 points
ROUNDS = 5  # triangulate, trim the detections that do not fit, solve; as the rig (and the noise) settles
MIN_GAIN = 0.01  # the new rig must predict left-out cameras at least 1 % better to replace the old one
MIN_VIEWS = 2  # detections a point keeps after the trimming, to stay in the adjustment
BLOCKS = 10  # the run cut into this many blocks of frames: adjusted on the odd ones, scored on the even
MIN_SPLIT_FRAMES = 2 * BLOCKS  # shorter runs are adjusted and scored on every frame
LENS = ("focal", "k1")  # what of a camera's intrinsics can be refined with its pose
FOCAL_SD = 0.02  # the focal scale's prior sd, relative: two board calibrations of one camera differ by up to 2 %
K1_SD = 0.02  # k1's prior sd
TOLERANCE = 1e-5  # a solve stops when a step lowers the cost by less than this fraction: with thousands of
# detections, far below what their noise resolves. Measured: 1e-9 ran every solve of the fly's near-telecentric rig
# to its 100 steps (9 s for 250 frames; 2 s here), with the same rigs on the fly, SLEAP's session and the simulation
POSE_SD_DEG = 1.0  # the poses' prior sd: a bumped camera (turned 0.3-1 degree) is within one sd
LENS_INSIST = 0.5  # a lens is refined only where the data at least halve its prior's sd (3x its information)
MOVE_WARN_SD = 3.0  # a camera moved further than this many prior sd from where it was is reported
POINT_VIEWS = 3  # cameras a point needs to enter the adjustment: with two, one confident mistake
# is indistinguishable from a good view, and the point slides along the other camera's ray


@dataclass
class RefineResult:
    calibration: Calibration  # the rig to use: the refined one, or the old one when it was not better
    refined: Calibration
    accepted: bool
    loo_old_px: list[float]  # per camera, on the held-out frames
    loo_new_px: list[float]
    changes: list[dict]
    rms_before_px: float  # over the detections the last solve kept, with the old rig
    rms_after_px: float  # ... and with the refined one
    points: int
    observations: int
    seconds: float
    notes: list[str] = field(default_factory=list)
    fit_loo_old_px: list[float] = field(default_factory=list)  # per camera, on the frames adjusted on
    fit_loo_new_px: list[float] = field(default_factory=list)
    held_out_frames: int = 0  # frames scored that the adjustment did not use (0: scored on its own)
    reposed: list[dict] = field(default_factory=list)  # cameras posed again from the others' points (resection)

    def to_dict(self) -> dict:
        return {"accepted": self.accepted, "rms_px": self.rms_after_px, "rms_before_px": self.rms_before_px,
                "leave_one_out_px": {"old": self.loo_old_px, "new": self.loo_new_px,
                                     "old_mean": float(np.nanmean(self.loo_old_px)),
                                     "new_mean": float(np.nanmean(self.loo_new_px)),
                                     "frames": "held out" if self.held_out_frames else "adjusted on",
                                     "held_out_frames": self.held_out_frames},
                "leave_one_out_adjusted_on_px": {"old": self.fit_loo_old_px, "new": self.fit_loo_new_px,
                                                 "old_mean": _mean(self.fit_loo_old_px),
                                                 "new_mean": _mean(self.fit_loo_new_px)},
                "cameras": self.changes, "points": self.points, "observations": self.observations,
                "seconds": self.seconds, "notes": self.notes}


def _mean(values: list[float]) -> float | None:
    return float(np.nanmean(values)) if values else None


def split_blocks(frames: int, blocks: int = BLOCKS) -> tuple[np.ndarray, np.ndarray]:
    """Frames to adjust on and frames held out (bool (N,) each): ``blocks`` blocks of consecutive
    frames, the first, third, ... adjusted on, the others held out; every frame both when the run is
    shorter than :data:`MIN_SPLIT_FRAMES`."""
    if frames < MIN_SPLIT_FRAMES:
        every = np.ones(frames, bool)
        return every, every
    block = (np.arange(frames) * blocks) // frames
    fit = block % 2 == 0
    return fit, ~fit


def _measurements(calibration: Calibration, keypoints, min_likelihood: float):
    """(N, C, M, 2) pixels and (N, C, M) confident, for bodyparts every file has."""
    names = [set(k.bodyparts) for k in keypoints]
    common = [b for b in keypoints[0].bodyparts if all(b in s for s in names)]
    if not common:
        raise InputError("the keypoint files share no bodypart")
    n = min(k.frames for k in keypoints)
    meas = np.stack([k.xy[:n, [k.bodyparts.index(b) for b in common]] for k in keypoints], axis=1)
    like = np.stack([k.likelihood[:n, [k.bodyparts.index(b) for b in common]] for k in keypoints], axis=1)
    valid = (like >= min_likelihood) & np.isfinite(meas).all(axis=-1)
    return meas, valid


def leave_one_out(calibration: Calibration, meas: np.ndarray, valid: np.ndarray) -> list[float]:
    """For each camera: the median error (px) of its confident detections predicted by the points the
    other cameras triangulate (two or more places of them: :func:`graph.calibrate.resection.errors`)."""
    return [float(m) for m in errors(calibration, meas, valid)[0]]


@dataclass
class _Adjusted:
    calibration: Calibration
    rms_before_px: float
    rms_after_px: float
    points: int
    observations: int
    points_xyz: np.ndarray  # (P, 3) the last round's points
    lens_sd: dict = field(default_factory=dict)  # camera -> (focal scale sd (relative), k1 sd), refined ones


def lens_prior(camera: Camera, lens: tuple[str, ...], focal_sd: float, k1_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """The prior ``(theta0, L)`` (:class:`graph.calibrate.bundle.Settings`) on a camera's intrinsics
    ``theta = [fx, fy, cx, cy, k1, ...]`` when ``lens`` (a subset of :data:`LENS`) is refined: the
    whitened rows ``L (theta - theta0)`` are

    * the focal scale ``((fx - fx0) / fx0 + (fy - fy0) / fy0) / 2`` over ``focal_sd`` ("focal" in
      ``lens``), and their ratio ``(fx - fx0) / fx0 - (fy - fy0) / fy0`` held;
    * ``(k1 - k1_0) / k1_sd`` ("k1" in ``lens``);
    * every other entry held at ``HELD`` of its scale (pixels for ``cx, cy``, 1 for coefficients).

    A held entry is a stiff prior rather than a column removed: the bundle refines a camera's whole
    ``theta`` or none of it."""
    theta0 = intrinsics_of(camera)
    n = len(theta0)
    L = np.zeros((n, n))
    L[0] = focal_scale_gradient(theta0) / (focal_sd if "focal" in lens else HELD)
    L[1, :2] = np.array([1.0 / theta0[0], -1.0 / theta0[1]]) / HELD
    for j in range(2, n):
        L[j, j] = 1.0 / (k1_sd if (j == 4 and "k1" in lens) else HELD)
    return theta0, L


def focal_scale_gradient(theta0: np.ndarray) -> np.ndarray:
    """The gradient of the focal scale ``((fx - fx0) / fx0 + (fy - fy0) / fy0) / 2`` by ``theta``."""
    grad = np.zeros(len(theta0))
    grad[:2] = 0.5 / theta0[0], 0.5 / theta0[1]
    return grad


def _points(rig: Calibration, meas: np.ndarray, valid: np.ndarray, frames: np.ndarray):
    """Step 1 with ``rig``: the points (P, 3) and their detections as :class:`bundle.Observations`
    (one 3-dof "board" per point, one view per detection the robust triangulation used)."""
    from graph.solve.triangulate import robust_points

    C = len(rig)
    X, _, ok = robust_points(rig, meas, valid)
    N, _, M, _ = meas.shape
    ok = ok.reshape(N, M, C) & valid.transpose(0, 2, 1)
    good = np.isfinite(X).all(axis=-1) & (ok.sum(axis=-1) >= POINT_VIEWS) & frames[:, None]
    idx = np.argwhere(good)
    if len(idx) < 10:
        raise InputError(f"only {len(idx)} confident keypoints are seen by three or more cameras; "
                         "lower --likelihood or give more frames")
    if len(idx) > MAX_POINTS:
        idx = idx[np.round(np.linspace(0, len(idx) - 1, MAX_POINTS)).astype(int)]
    seen = ok[idx[:, 0], idx[:, 1]]  # (P, C)
    pj, cj = np.nonzero(seen)
    uv = meas[idx[pj, 0], cj, idx[pj, 1]]
    return X[idx[:, 0], idx[:, 1]], bundle.Observations(np.arange(len(pj)), cj, pj, uv, np.zeros((len(pj), 3)))


def _bundle_rig(cal: Calibration, pts: np.ndarray) -> bundle.Rig:
    return bundle.Rig([c.model for c in cal.cameras], [intrinsics_of(c) for c in cal.cameras],
                      np.stack([c.R.T for c in cal.cameras]), np.stack([c.center for c in cal.cameras]),
                      np.broadcast_to(np.eye(3), (len(pts), 3, 3)).copy(), pts.copy())


def pose_priors(anchor: Calibration, pts: np.ndarray, sd_deg: float, gauge: int = 0) -> dict:
    """The cameras' pose priors (:attr:`graph.calibrate.bundle.Settings.pose_priors`), camera
    ``gauge``'s excepted (it is held; -1: none): centred on ``anchor``'s poses, the rotation's sd
    ``s_r = sd_deg`` and the position's ``s_t = s_r d_i``, ``d_i`` the median distance from camera i
    to the points ``pts`` (P, 3): a turn of ``s_r`` and a shift of ``s_t`` move the animal in the image alike."""
    s_r = float(np.radians(sd_deg))
    return {i: (c.R.T, c.center, s_r, s_r * float(np.median(np.linalg.norm(pts - c.center, axis=1))))
            for i, c in enumerate(anchor.cameras) if i != gauge}


def prior_moves(anchor: Calibration, moved: Calibration, pts: np.ndarray, sd_deg: float) -> np.ndarray:
    """How far each camera of ``moved`` is from ``anchor``'s, in sd of :func:`pose_priors` (C,): the
    larger of the turn over ``s_r`` and the shift over ``s_t``."""
    priors = pose_priors(anchor, pts, sd_deg, gauge=-1)
    return np.array([max(rotation_angle(R0.T @ b.R.T) / s_r, float(np.linalg.norm(t0 - b.center)) / s_t)
                     for b, (R0, t0, s_r, s_t) in zip(moved.cameras, priors.values())])


def _adjust(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, frames: np.ndarray,
            start: Calibration | None = None, rounds: int = ROUNDS, lens: tuple[str, ...] = (),
            focal_sd: float = 0.0, k1_sd: float = 0.0, anchor: Calibration | None = None,
            pose_sd_deg: float = 0.0, held: frozenset = frozenset(), gauge: tuple[int, int] = (0, 1),
            lens_held: frozenset = frozenset()) -> _Adjusted:
    """Steps 1 and 3 of the module on the frames ``frames`` (bool (N,)), from ``start`` (default the
    rig itself), in ``rounds`` rounds: triangulate with the rig so far, trim, solve. The points are
    triangulated again each round: the detections a wrong rig's triangulation rejects are the very
    ones that would mend it (a copied entry's camera, once posed again, is still a few degrees off).
    Each camera's detections are trimmed at its own noise: one camera labelled less precisely than
    the others would otherwise lose its detections that disagree most, and with them the evidence of
    its own pose. The camera ``gauge[0]`` held at the start's pose, and its distance to camera
    ``gauge[1]`` (the world frame and the scale); the lens priors centred on
    ``calibration``'s, the pose priors (:func:`pose_priors`) on ``anchor``'s; the cameras ``held``
    stay at ``anchor``'s poses."""
    rig = calibration if start is None else start
    C = len(calibration)
    if held:
        assert anchor is not None
        rig = Calibration([anchor.cameras[i] if i in held else c for i, c in enumerate(rig.cameras)],
                          source=rig.source, metadata=dict(rig.metadata))
    lens_priors = ({i: lens_prior(c, () if i in lens_held else lens, focal_sd, k1_sd)
                    for i, c in enumerate(calibration.cameras)} if lens else {})
    g, partner = gauge
    distance = float(np.linalg.norm(rig.cameras[partner].center - rig.cameras[g].center))
    rms_before = math.nan
    for r in range(rounds):
        pts, all_obs = _points(rig, meas, valid, frames)
        P, pj, cj = len(pts), all_obs.board, all_obs.cam
        state = _bundle_rig(rig, pts)
        s = np.linalg.norm(bundle.residuals(state, all_obs, jacobians=False), axis=1)
        sigma = float(np.median(s)) / RAYLEIGH_MEDIAN
        each = np.array([np.median(s[cj == c]) if (cj == c).any() else np.inf for c in range(C)]) / RAYLEIGH_MEDIAN
        keep = s <= bundle.HUBER_SIGMAS * each[cj]  # confident mistakes out before the solve, not after
        keep &= (np.bincount(pj, weights=keep, minlength=P) >= MIN_VIEWS)[pj]  # a point needs two views
        obs = all_obs.keep_views(keep)
        if r == 0:  # the old rig on the points the start triangulates
            e_old = bundle.residuals(_bundle_rig(calibration, pts), obs, jacobians=False)
            rms_before = float(np.sqrt((e_old ** 2).sum(axis=1).mean()))
        # the bundle's data terms are in pixels, not in noise sd: a prior's whitened rows are scaled by the
        # noise sd so that the posterior is the one the priors and the measured noise say
        pose = pose_priors(anchor, pts, pose_sd_deg, g) if anchor and pose_sd_deg else {}
        settings = bundle.Settings(fixed_cams=frozenset({g}) | held, huber_px=bundle.HUBER_SIGMAS * sigma, board_dof=3,
                                   fixed_distance=None if partner in held else (g, partner, distance),
                                   free_intrinsics={i: (t0, sigma * L) for i, (t0, L) in lens_priors.items()},
                                   pose_priors={i: (R0, t0, s_r / sigma, s_t / sigma)
                                                for i, (R0, t0, s_r, s_t) in pose.items()},
                                   tolerance=TOLERANCE)
        sol = bundle.solve(state, obs, settings)
        cams = []
        for i, c in enumerate(calibration.cameras):
            R = sol.rig.R_cam[i].T
            cams.append(camera_with(sol.rig.intrinsics[i], c.model, c.size, c.name, R=R, t=-R @ sol.rig.t_cam[i]))
        rig = Calibration(cams, source=calibration.source, metadata=dict(calibration.metadata))
    rms_after = float(np.sqrt((sol.residuals ** 2).sum(axis=1).mean()))
    lens_sd: dict[int, tuple[float, float]] = {}
    if lens_priors:  # the focal scale's and k1's posterior sd per camera
        cov, eq = bundle.camera_covariance(sol.rig, obs, settings, sigma)
        for i, (a, z) in eq.lens_slots.items():
            grad = focal_scale_gradient(lens_priors[i][0])
            block = cov[a:z, a:z]
            lens_sd[i] = (float(np.sqrt(max(grad @ block @ grad, 0.0))), float(np.sqrt(max(block[4, 4], 0.0))))
    return _Adjusted(rig, rms_before, rms_after, P, obs.n_views, sol.rig.t_board.copy(), lens_sd)


def refine_rig(calibration: Calibration, keypoints: list, min_likelihood: float = 0.9, lens: tuple[str, ...] = (),
               focal_sd: float = FOCAL_SD, k1_sd: float = K1_SD, pose_sd_deg: float = POSE_SD_DEG,
               hold: str | None = None) -> RefineResult:
    """See the module. Accepted on the held-out frames, the rig is adjusted once more on every frame
    (from the rig the check accepted: the held-out half of the data is not thrown away). The world
    frame and the scale are the old rig's through the camera named ``hold`` (default: the first
    camera not posed again) and its distance to the next such camera."""
    start = time.perf_counter()
    C = len(calibration)
    if len(keypoints) != C:
        raise InputError(f"{len(keypoints)} keypoint files for a calibration of {C} cameras")
    meas, valid = _measurements(calibration, keypoints, min_likelihood)
    fit, held = split_blocks(len(meas))
    if hold is not None and hold not in calibration.names:
        raise InputError(f"--hold: no camera {hold!r} in the calibration (its cameras: {', '.join(calibration.names)})")
    start_rig, reposed = repose_off_cameras(calibration, meas, valid, fit, held, MIN_GAIN)
    steady = [i for i in range(C) if i not in {r["camera"] for r in reposed}] or list(range(C))
    g = calibration.names.index(hold) if hold is not None else steady[0]
    gauge = (g, next((i for i in steady if i != g), (g + 1) % C))
    adjust = partial(_adjust, lens=lens, focal_sd=focal_sd, k1_sd=k1_sd, anchor=start_rig, pose_sd_deg=pose_sd_deg,
                     gauge=gauge)
    holding: frozenset = frozenset()
    moves: dict[int, float] = {}
    while True:  # a camera the data move beyond MOVE_WARN_SD sd of the prior is held where it was
        adjusted = adjust(calibration, meas, valid, fit, start=start_rig, held=holding)
        if not pose_sd_deg:
            break
        far = prior_moves(start_rig, adjusted.calibration, adjusted.points_xyz, pose_sd_deg)
        more = {i for i, sds in enumerate(far) if sds > MOVE_WARN_SD and i != g} - holding
        if not more:
            break
        moves.update({i: float(far[i]) for i in more})
        holding |= more
    loose = {i: sd for i, sd in adjusted.lens_sd.items()
             if ("focal" in lens and sd[0] > LENS_INSIST * focal_sd) or ("k1" in lens and sd[1] > LENS_INSIST * k1_sd)}
    if loose:  # the keypoints do not determine these cameras' lenses: held at the calibration's
        adjust = partial(adjust, lens_held=frozenset(loose))
        adjusted = adjust(calibration, meas, valid, fit, start=start_rig, held=holding)
    refined = adjusted.calibration
    loo_old = leave_one_out(calibration, meas[held], valid[held])
    loo_new = leave_one_out(refined, meas[held], valid[held])
    split = not fit.all()
    fit_old = leave_one_out(calibration, meas[fit], valid[fit]) if split else loo_old
    fit_new = leave_one_out(refined, meas[fit], valid[fit]) if split else loo_new
    accepted = bool(np.nanmean(loo_new) <= (1 - MIN_GAIN) * np.nanmean(loo_old))
    rms_before = adjusted.rms_before_px  # the old rig on the points it triangulates itself
    if accepted and split:
        # one round: the start has settled, the trimming only has the new frames' mistakes to find
        adjusted = adjust(calibration, meas, valid, np.ones(len(meas), bool), start=refined, rounds=1, held=holding)
        refined = adjusted.calibration
    cams = refined.cameras
    again = {r["camera"]: r for r in reposed}
    units, units_note = resolve_units(calibration, "auto")  # the rig's own units: metres or millimetres
    mm_per_unit = CALIBRATION_UNITS[units] * 1000.0
    changes = [{"name": name, "position_change_mm": float(np.linalg.norm(a.center - b.center) * mm_per_unit),
                "rotation_change_deg": float(np.degrees(rotation_angle(a.R @ b.R.T))),
                "focal_change_percent": float((b.K[0, 0] / a.K[0, 0] - 1) * 100),
                "k1_change": float(b.dist[0] - a.dist[0]),
                "focal_sd_percent": (adjusted.lens_sd[i][0] * 100 if i in adjusted.lens_sd and i not in loose
                                     else None),
                "leave_one_out_old_px": lo, "leave_one_out_new_px": ln, "re_posed": i in again,
                "held": i in holding, "lens_held": i in loose}
               for i, (name, a, b, lo, ln) in enumerate(zip(calibration.names, calibration.cameras, cams, loo_old,
                                                            loo_new))]
    notes = [units_note] if units_note else []
    for i, r in again.items():
        notes.append(f"{calibration.names[i]} was off: its detections sat {r['old_px']:.1f} px (median) from the "
                     f"other cameras' points on the held-out frames; posed again from those points ({r['new_px']:.1f} "
                     "px) before the adjustment")
    if holding:
        names = ", ".join(calibration.names[i] for i in sorted(holding))
        sds = ", ".join(f"{moves[i]:.0f}" for i in sorted(holding))
        notes.append(f"held where they were: {names}; the keypoints would move them {sds} sd of the pose prior "
                     f"({pose_sd_deg:g} deg), more than a bumped camera moves. Errors of the keypoints themselves "
                     "(labels placed differently in each view, refraction through a wall) are fitted that way too; "
                     "if the rig was rebuilt, give a larger --pose-sd")
    if loose:
        names = ", ".join(calibration.names[i] for i in sorted(loose))
        sds = ", ".join(f"{loose[i][0] * 100:.2f} % and {loose[i][1]:.3f}" for i in sorted(loose))
        notes.append(f"lens held at the calibration's: {names}; the keypoints determine the focal length and k1 only "
                     f"to {sds} sd, against the priors' {focal_sd * 100:g} % and {k1_sd:g} (more frames, spread "
                     "over more of the images, would)")
    where = f"on {int(held.sum())} held-out frames" if split else "on the frames adjusted on (too few to hold out)"
    if accepted and split:
        notes.append(f"accepted on the {int(held.sum())} held-out frames; the rig written was then adjusted on all "
                     f"{len(meas)} frames, from the accepted one")
    if not accepted:
        notes.append(f"kept the old rig: leave-one-camera-out error {where} {np.nanmean(loo_new):.3f} px refined vs "
                     f"{np.nanmean(loo_old):.3f} px before (needs {MIN_GAIN * 100:.0f} % better)")
        if split and np.nanmean(fit_new) <= (1 - MIN_GAIN) * np.nanmean(fit_old):
            notes.append(f"the refined rig fits the frames it was adjusted on better ({np.nanmean(fit_old):.3f} -> "
                         f"{np.nanmean(fit_new):.3f} px) but predicts the others no better: the error is not the "
                         "rig's poses (a camera's labels or lens?)")
    kept = refined if accepted else calibration
    kept = Calibration(kept.cameras, source=kept.source, metadata={**calibration.metadata,
                                                                     "refined_from_keypoints": accepted})
    return RefineResult(kept, refined, accepted, loo_old, loo_new, changes, rms_before,
                        adjusted.rms_after_px, adjusted.points, adjusted.observations, time.perf_counter() - start,
                        notes, fit_old, fit_new, int(held.sum()) if split else 0, reposed)


def run(args: argparse.Namespace) -> int:
    from graph.io.calibration import load_calibration, write_anipose_toml
    from graph.io.keypoints import read_keypoints

    if not 0 < args.likelihood <= 1:
        raise InputError(f"--likelihood must be in (0, 1], got {args.likelihood}")
    lens = tuple(p.strip() for p in args.refine_intrinsics.split(",") if p.strip())
    if unknown := [p for p in lens if p not in LENS]:
        raise InputError(f"--refine-intrinsics: unknown {', '.join(unknown)} (choose from {', '.join(LENS)})")
    for name, sd in (("--focal-sd", args.focal_sd), ("--k1-sd", args.k1_sd)):
        if not (np.isfinite(sd) and 0 < sd <= 1):
            raise InputError(f"{name} must be in (0, 1], got {sd}")
    if not (np.isfinite(args.pose_sd) and 0 <= args.pose_sd <= 180):
        raise InputError(f"--pose-sd must be in [0, 180] degrees, got {args.pose_sd}")
    calibration = load_calibration(args.calibration)
    keypoints = [read_keypoints(p, individual=args.individual) for p in args.keypoints]
    result = refine_rig(calibration, keypoints, args.likelihood, lens, args.focal_sd, args.k1_sd, args.pose_sd,
                        args.hold)
    write_anipose_toml(args.out, result.calibration)
    if args.report:
        Path(args.report).write_text(json.dumps(result.to_dict(), indent=2) + "\n", encoding="utf-8")
    verdict = "refined" if result.accepted else "kept the old rig"
    where = f"{result.held_out_frames} held-out frames" if result.held_out_frames else "the frames adjusted on"
    print(f"refine: {verdict}; {result.points} points, {result.observations} detections, RMS "
          f"{result.rms_before_px:.2f} -> {result.rms_after_px:.2f} px; leave-one-camera-out on {where} "
          f"{np.nanmean(result.loo_old_px):.2f} -> {np.nanmean(result.loo_new_px):.2f} px -> {args.out}")
    for note in result.notes:
        print(f"  note: {note}")
    for ch in result.changes:
        again = (" (posed again from the others' points)" if ch["re_posed"] else
                 " (held where it was)" if ch["held"] else "")
        print(f"  {ch['name']}: moved {ch['position_change_mm']:.1f} mm, turned {ch['rotation_change_deg']:.3f} deg"
              f"{again}")
    return 0
