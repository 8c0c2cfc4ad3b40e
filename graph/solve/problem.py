"""One estimation problem: detections of every camera stacked against one skeleton's markers.

Checks that the inputs fit together (camera count, frame counts), maps bodyparts to markers by
name (unknown bodyparts are ignored with a warning, missing markers are unobserved), applies the
likelihood threshold, and packs the cameras for the kernels.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from graph.camera import Calibration
from graph.errors import InputError
from graph.io.calibration import in_metres
from graph.io.keypoints import Keypoints, check_same_frames, match_bodyparts, no_marker_matched
from graph.skeleton import Skeleton, load_skeleton
from graph.solve.ensemble import relative_noise
from graph.solve.noise import scatter_px, triangulation_dof
from graph.solve.triangulate import triangulate
from graph.types import SolveOptions, default_motion_scale


@dataclass(frozen=True)
class Problem:
    """N frames, C cameras, M markers. Built once by :func:`build`; the solvers only read it."""

    skeleton: Skeleton
    calibration: Calibration
    options: SolveOptions
    meas: np.ndarray  # (N, C, M, 2) pixels, NaN where missing
    likelihood: np.ndarray  # (N, C, M), 0 where missing
    valid: np.ndarray  # (N, C, M) finite and at or above the likelihood threshold
    sigma_px: float = 5.0  # detection noise (px per coordinate): the option, or measured when "auto"
    warnings: list[str] = field(default_factory=list)
    # (C, M) each camera's and marker's noise relative to sigma_px, from an ensemble's spread
    # (graph.solve.ensemble.relative_noise); None: all alike
    noise_scale: np.ndarray | None = None
    # the frames [a, b) of a longer run this problem is a window of (graph.solve.windows): the checks
    # of the whole run's inputs and answer are made on the whole, not on each window
    window: tuple[int, int] | None = None
    # ekf: the poses (S, P) of its first S frames, given: a long run's window that continues the stream
    # of the window before it (graph.solve.windows) starts from that stream's poses, not afresh
    start_poses: np.ndarray | None = None

    def sigma_cm(self, sigma_px: float | None = None) -> np.ndarray:
        """The detection noise of each camera and marker (C, M), px: ``sigma_px`` (default the
        problem's) times the relative noise."""
        sigma = self.sigma_px if sigma_px is None else sigma_px
        scale = np.ones((self.cameras, len(self.markers))) if self.noise_scale is None else self.noise_scale
        return np.ascontiguousarray(sigma * scale, dtype=np.float64)

    @property
    def frames(self) -> int:
        return self.meas.shape[0]

    @property
    def cameras(self) -> int:
        return self.meas.shape[1]

    @property
    def markers(self) -> list[str]:
        return self.skeleton.markers

    @property
    def dt(self) -> float:
        return 1.0 / self.options.fps

    def packed_cameras(self):
        return self.calibration.packed()

    def views(self) -> np.ndarray:
        """Cameras that saw each marker in each frame (N, M), those at one place counted once
        (:meth:`graph.camera.Calibration.places`): two views from one centre fix no depth."""
        return self.calibration.places_seeing(self.valid)

    def unconstrained(self) -> tuple[list[str], list[int]]:
        """Markers never seen by two cameras; frames in which no marker is seen by two cameras."""
        two = self.views() >= 2
        markers = [m for j, m in enumerate(self.markers) if not two[:, j].any()]
        frames = [int(n) for n in np.flatnonzero(~two.any(axis=1))]
        return markers, frames


def build(keypoints: list[Keypoints], calibration: Calibration, options: SolveOptions) -> Problem:
    """Stack per-camera keypoints into a :class:`Problem`, or raise :class:`InputError`."""
    C = len(calibration)
    if len(keypoints) != C:
        raise InputError(f"{len(keypoints)} keypoint file(s) given for a calibration of {C} camera(s) "
                         f"({calibration.source or 'calibration'})")
    if C < 2:
        raise InputError("at least two cameras are needed for 3D")
    check_camera_order([kp.source for kp in keypoints], calibration.names)
    N = check_same_frames(keypoints)
    if N == 0:
        raise InputError("no frames", keypoints[0].source or None)

    notes: list[str] = []
    calibration, note = in_metres(calibration, options.calibration_units)
    for note in (note, calibration.same_places()):
        if note:
            notes.append(note)
            warnings.warn(note, stacklevel=2)
    skeleton = skeleton_of([kp.bodyparts for kp in keypoints], options)
    if options.motion_scale is None:  # the skeleton's and method's default, as the solvers will use it
        free_points = skeleton.kind == "points" and not skeleton.bones
        options = replace(options, motion_scale=default_motion_scale(options.method, free_points))
    if options.motion_order == "auto" and options.motion_scale != "auto":
        raise InputError("motion_order 'auto' compares the orders at their fitted scales: it needs motion_scale "
                         f"'auto', not {options.motion_scale!r}")
    meas, lik, spread, seen_any, unknown = _stack(keypoints, skeleton)
    for msg in unknown:
        notes.append(msg)
        warnings.warn(msg, stacklevel=2)
    if not seen_any.any():
        raise no_marker_matched(keypoints[0].bodyparts, skeleton.name, list(skeleton.markers))
    missing = [m for j, m in enumerate(skeleton.markers) if not seen_any[j]]
    if missing:
        notes.append(f"markers missing from every keypoint file (unobserved): {', '.join(missing)}")
    valid = np.isfinite(meas).all(axis=-1) & (lik >= options.likelihood_threshold)
    if not valid.any():
        raise InputError(f"no detection reaches the likelihood threshold {options.likelihood_threshold}")
    noise_scale = relative_noise(spread, valid) if spread is not None else None
    if noise_scale is not None and options.method == "tri":
        noise_scale = None  # triangulation weighs every view alike
    if options.measurement_std_px == "auto":
        sigma = measured_noise(calibration, meas, valid, noise_scale)  # the report says it (sigma_px)
    else:
        sigma = float(options.measurement_std_px)
    return Problem(skeleton=skeleton, calibration=calibration, options=options, meas=meas, likelihood=lik,
                   valid=valid, sigma_px=sigma, warnings=notes, noise_scale=noise_scale)


def skeleton_of(bodyparts: list[list[str]], options: SolveOptions) -> Skeleton:
    """The skeleton ``options`` name; ``"points"``: one point per bodypart of the cameras'
    ``bodyparts`` (in their order, each once)."""
    if options.skeleton != "points":
        return load_skeleton(options.skeleton)
    names: list[str] = []
    for parts in bodyparts:
        names += [b for b in parts if b not in names]
    return load_skeleton("points", bodyparts=names, bone_pairs=options.bone_lengths)


def _stack(keypoints: list[Keypoints], skeleton: Skeleton):
    """The cameras' detections against the ``skeleton``'s markers: ``meas`` (N, C, M, 2),
    ``likelihood`` (N, C, M), an ensemble's ``spread`` (N, C, M; None when no camera has one), which
    markers some camera has, and a note per camera with bodyparts not among the markers."""
    markers = skeleton.markers
    N, C, M = keypoints[0].frames, len(keypoints), len(markers)
    meas = np.full((N, C, M, 2), np.nan)
    lik = np.zeros((N, C, M))
    spread = np.full((N, C, M), np.nan) if any(kp.spread_px is not None for kp in keypoints) else None
    seen_any = np.zeros(M, dtype=bool)
    unknown = []
    for c, kp in enumerate(keypoints):
        match = match_bodyparts(kp, markers)
        if match.unknown:
            unknown.append(f"{kp.source or f'camera {c + 1}'}: bodyparts not in the {skeleton.name} skeleton "
                           f"are ignored: {', '.join(match.unknown)}")
        have = match.index >= 0
        meas[:, c, have] = kp.xy[:, match.index[have]]
        lik[:, c, have] = np.nan_to_num(kp.likelihood[:, match.index[have]], nan=0.0)
        if spread is not None and kp.spread_px is not None:
            spread[:, c, have] = kp.spread_px[:, match.index[have]]
        seen_any |= have
    return meas, lik, spread, seen_any, unknown


def confident(keypoints: list[Keypoints], skeleton: Skeleton, threshold: float) -> np.ndarray:
    """The confident detections of ``skeleton``'s markers in each frame of ``keypoints`` (N,): what
    :attr:`Problem.valid` counts."""
    meas, lik, _, _, _ = _stack(keypoints, skeleton)
    return (np.isfinite(meas).all(axis=-1) & (lik >= threshold)).sum(axis=(1, 2))


def frames_of(prob: Problem, a: int, b: int, options: SolveOptions | None = None,
              sigma_px: float | None = None) -> Problem:
    """The frames ``[a, b)`` of ``prob`` as a problem of their own, with ``options`` (default the
    problem's) and detection noise ``sigma_px`` (default the problem's)."""
    return replace(prob, meas=prob.meas[a:b], likelihood=prob.likelihood[a:b], valid=prob.valid[a:b],
                   options=options or prob.options, sigma_px=prob.sigma_px if sigma_px is None else sigma_px,
                   warnings=[], window=(a, b))


def window_of(template: Problem, keypoints: list[Keypoints], window: tuple[int, int]) -> Problem:
    """The frames ``window = [a, b)`` of a long run as a problem, from their ``keypoints`` (the run's
    cameras, sliced): ``template`` (a problem :func:`build` made of another stretch of the same run)
    gives the skeleton, calibration, options, noise and relative noise, checked there once."""
    meas, lik, _, _, _ = _stack(keypoints, template.skeleton)
    valid = np.isfinite(meas).all(axis=-1) & (lik >= template.options.likelihood_threshold)
    return replace(template, meas=meas, likelihood=lik, valid=valid, warnings=[], window=window)


def _folded(text: str) -> str:
    """``text`` lower-cased with everything but letters and digits left out: ``Cam-A`` -> ``cama``."""
    return "".join(ch for ch in text.lower() if ch.isalnum())


def camera_order_from_names(sources: list[str], names: list[str]) -> list[int] | None:
    """The calibration camera each keypoint file's name names, or None when the names do not say.

    A file names camera c when c's name, folded (:func:`_folded`), is in the folded file name
    and no other camera's is (``Cam-A`` in ``camA.rng1.csv``). The names say only when every file
    names exactly one camera and no two files the same one; names of one character (``A``, ``1``)
    are too common to say anything."""
    folded = [_folded(n) for n in names]
    if len(sources) != len(names) or any(len(f) < 2 for f in folded) or len(set(folded)) < len(folded):
        return None
    order = []
    for src in sources:
        stem = _folded(Path(src).name) if src else ""
        hits = [c for c, f in enumerate(folded) if f in stem]
        hits = [c for c in hits if not any(c != d and folded[c] in folded[d] for d in hits)]  # cam1 in cam10
        if len(hits) != 1:
            return None
        order.append(hits[0])
    return order if len(set(order)) == len(order) else None


def check_camera_order(sources: list[str], names: list[str]) -> None:
    """Raise :class:`InputError` when the keypoint files' names name the calibration's cameras in
    another order than the files were given in (a silent wrong answer otherwise: swapped cameras
    triangulate to nonsense that the robust loss half rejects)."""
    order = camera_order_from_names(sources, names)
    if order is None or order == list(range(len(order))):
        return
    wrong = next(i for i, c in enumerate(order) if c != i)
    raise InputError(f"is given as camera {wrong + 1} ({names[wrong]}) but its name says {names[order[wrong]]}: "
                     f"give the keypoint files in the calibration's camera order "
                     f"({', '.join(names)})", sources[wrong])


AUTO_START_PX = 5.0  # the triangulation's robust scale before the noise is known
AUTO_RANGE_PX = (0.05, 200.0)
AUTO_ROUNDS = 2
AUTO_CAUCHY_SCALE = 3.0  # later rounds triangulate with a Cauchy scale of this many sigmas


def measured_noise(calibration: Calibration, meas: np.ndarray, valid: np.ndarray,
                   noise_scale: np.ndarray | None = None) -> float:
    """The detection noise (px) for ``measurement_std_px="auto"``: :func:`graph.solve.noise.scatter_px` of
    the robust triangulation's residuals, each scaled for the three coordinates the point took
    (:func:`graph.solve.noise.triangulation_dof`). A Cauchy refinement whose scale is the noise itself
    pulls the points towards the views that agree and leaves residuals 10-25 % short, so after a
    first round at 5 px the points are triangulated again with a scale of 3 sigma (within 10 % of
    the simulated noise at 1-20 px with 20 % outliers). With ``noise_scale`` (C, M; an ensemble's
    relative noise) each residual is divided by its camera's and marker's, so that sigma is the
    level they are relative to. Raises :class:`InputError` when no marker is
    seen twice (nothing to measure)."""
    scale, sigma = AUTO_START_PX, float("nan")
    for _ in range(AUTO_ROUNDS):
        _, _, _, s = triangulate(calibration, meas, valid, scale)
        views = np.isfinite(s).sum(axis=1, keepdims=True)  # (N, 1, M)
        rel = 1.0 if noise_scale is None else noise_scale[None]
        sigma = scatter_px(s * scale / rel, triangulation_dof(views))
        if not np.isfinite(sigma):
            break
        scale = AUTO_CAUCHY_SCALE * float(np.clip(sigma, *AUTO_RANGE_PX))
    if not np.isfinite(sigma):
        raise InputError("measurement_std_px 'auto': too few markers seen by two cameras to measure the "
                         "detection noise; give it in pixels instead")
    return float(np.clip(sigma, *AUTO_RANGE_PX))
