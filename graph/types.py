"""The typed data a solve takes and returns: :class:`SolveOptions`, :class:`Progress`,
:class:`SolveReport` and :class:`Result`, and their JSON form (:func:`jsonable`).

Every solver, writer and the service import these; this module imports nothing of the solvers
(:mod:`graph.api` holds :func:`~graph.api.solve` and the registry of solvers).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Literal, get_args

import numpy as np

from graph.camera import CALIBRATION_UNITS

Method = Literal["tri", "ekf", "fte"]
Body = Literal["model", "estimate", "given"]
BODIES: tuple[str, ...] = get_args(Body)
Sync = Literal["given", "estimate"]
SYNCS: tuple[str, ...] = get_args(Sync)
METHODS: tuple[str, ...] = get_args(Method)  # graph.api.SOLVERS has one solver for each

# The stages a solve reports through :class:`Progress`, in the order they come (each method skips
# some: ``tri`` triangulates, ``ekf`` filters, ``fte`` optimises).
Stage = Literal["initialise", "triangulate", "optimise", "filter", "uncertainty", "done"]
STAGES: tuple[str, ...] = get_args(Stage)


# Ranges of the options (NaN and infinity fall outside every one). A frame rate over MAX_FPS is a typo
# or a unit slip (the motion model scales with 1/fps^2: at 1e5 fps its factors are singular); one under
# MIN_FPS too (a frame every 100 s is a time-lapse, and at 1e-300 fps the motion's sds overflow).
MAX_FPS = 10000.0
MIN_FPS = 0.01
MAX_NOISE_PX = 1000.0
MAX_ITERATIONS = 10000
MAX_MOTION_SCALE = 1e6
MAX_LAG_SECONDS = 60.0
MAX_INDIVIDUALS = 64  # individuals solved from one recording (graph.io.keypoint_types.MAX_SLOTS)
MIN_WINDOW_FRAMES = 100  # a window's core: the margins are 200 frames
WINDOW_FRAMES = 2000  # fte's and ekf's windows keep this many frames each (window_frames None) ...
WINDOWED_ABOVE = 4000  # ... in runs longer than this (graph.solve.windows; bench/RESULTS.md, section 21)
WINDOWED_METHODS = ("fte", "ekf")  # the methods a long run is solved in windows by (and streamed)
MAX_MIN_VIEWS = 100


def default_motion_scale(method: str, free_points: bool) -> float | Literal["auto"]:
    """``motion_scale`` when none is given. ``fte`` on free points (no bones): ``"auto"``. Their
    process noise is a cheetah's, which fits no other animal (a fly's legs: 10^4 times too loose);
    fitted, the 3D error fell by 27-33 % in every cell of the simulated paper table solved as free
    points, the held-out error on the real fly by 8 %, at 1.6x the time (bench/RESULTS.md, sections
    12 and 12a). Otherwise 1: a kinematic skeleton's process noise is its animal's (the cheetah's,
    the paper's), and fitting it, though 12-23 % more accurate on the paper table, costs 1.7x the
    time (0.95 s for 500 frames against the 0.5 s a solve is to take); ``ekf`` fits only over its
    first seconds, when asked."""
    return "auto" if method == "fte" and free_points else 1.0


@dataclass
class SolveOptions:
    """What to solve and how. Every field has a sensible default."""

    method: Method = "fte"
    fps: float = 120.0
    skeleton: str = "cheetah"  # "cheetah", "points", or a path to a skeleton TOML file
    likelihood_threshold: float = 0.5
    measurement_std_px: float | Literal["auto"] = 5.0  # detection noise (px per coordinate); "auto": measured
    robust: bool = True  # the redescending loss; False gives plain least squares
    max_iterations: int = 50
    # multiplies every process-noise std (larger: follows the data more); "auto": fitted to the data by
    # the marginal likelihood (graph.solve.smoothing), per marker for free points, one scale for a skeleton;
    # {group: scale}: a scale per group as a report's motion_scales gives them ({marker: s} for free
    # points, {"all": s}), to solve more runs with the smoothing one run fitted;
    # None: the default for the skeleton and method (default_motion_scale)
    motion_scale: float | Literal["auto"] | dict[str, float] | None = None
    # the order k of the motion prior, white k-th differences of each parameter: 3 (constant
    # acceleration with white jerk, the paper's), 2 (white changes of velocity), 1 (a random walk of
    # positions), or "auto": chosen per group from the data (graph.solve.smoothing: the fractional Bayes
    # factor); "fte" with motion_scale "auto" only; {group: k}: per group, as a report's motion_orders
    motion_order: int | Literal["auto"] | dict[str, int] = 3
    bone_lengths: list[tuple[str, str]] | None = None  # soft bone-length terms for "points"
    individual: str | None = None  # multi-animal files: which individual, alone (its 2D identities trusted)
    # multi-animal files: how many individuals to assign the detections to by geometry and motion
    # (graph.solve.identity; api.solve_group); None: found
    individuals: int | None = None
    lag_seconds: float = 0.5  # "ekf": the fixed-lag window (0.25 s had given 1.2-1.4x fte at 10 px; RESULTS 31)
    uncertainty: bool = True  # per-marker 3D std from the marginals ("fte": about a third of the time)
    calibration_units: str = "auto"  # "m", "cm", "mm", or "auto" (a rig measured in mm is recognised)
    # the body's proportions: the skeleton's ("model"), estimated with the trajectory ("estimate"), or
    # ``body_lengths`` ("given": metres per length group, or per bone "a-b" for points, as a report has them).
    # "estimate" by default: no animal has the model's proportions (bench/RESULTS.md, section 7)
    body: Body = "estimate"
    body_lengths: dict[str, float] | None = None
    # the cameras' clocks: ``time_offsets`` (frames per camera; none: all 0) as given, or estimated
    sync: Sync = "given"
    time_offsets: list[float] | None = None
    # fte and ekf answer a marker in every frame, from the motion model where fewer than two cameras see
    # it (``ncams`` 0 or 1, a larger sd); positions seen by fewer than ``min_views`` cameras are left NaN
    # (2: only what two cameras triangulate). tri, without a motion model, needs two in any case
    min_views: int = 0
    # fte: the share of left/right marker pairs the 2D tracker swapped in a camera and frame (graph.solve.swaps):
    # "auto", estimated from the data; a number below 0.5, given; 0: every pair taken as labelled
    swap_rate: float | Literal["auto"] = "auto"
    # fte and ekf: frames kept from each window of a long run, solved in windows of bounded memory
    # (graph.solve.windows); 0: the whole run at once; None: WINDOW_FRAMES a window above WINDOWED_ABOVE
    window_frames: int | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, not {self.method!r}")
        if not (MIN_FPS <= self.fps <= MAX_FPS):
            raise ValueError(f"fps must be between {MIN_FPS:g} and {MAX_FPS:g} (frames per second), not {self.fps}")
        if not (0.0 <= self.likelihood_threshold <= 1.0):
            raise ValueError(f"likelihood_threshold must be in [0, 1], not {self.likelihood_threshold}")
        if self.measurement_std_px != "auto" and not (isinstance(self.measurement_std_px, (int, float))
                                                       and 0 < self.measurement_std_px <= MAX_NOISE_PX):
            raise ValueError(f"measurement_std_px must be a positive number of pixels or 'auto', "
                             f"not {self.measurement_std_px!r}")
        if self.individuals is not None and not (isinstance(self.individuals, int) and not isinstance(
                self.individuals, bool) and 1 <= self.individuals <= MAX_INDIVIDUALS):
            raise ValueError(f"individuals must be a whole number from 1 to {MAX_INDIVIDUALS}, "
                             f"not {self.individuals!r}")
        if self.individuals is not None and self.individual is not None:
            raise ValueError("individual names one individual to solve alone, individuals counts them: "
                             "give one of them")
        if self.calibration_units not in CALIBRATION_UNITS:
            raise ValueError(f"calibration_units must be one of {', '.join(CALIBRATION_UNITS)}")
        if not (1 <= self.max_iterations <= MAX_ITERATIONS):
            raise ValueError(f"max_iterations must be from 1 to {MAX_ITERATIONS}, not {self.max_iterations}")
        scales = self.motion_scale.values() if isinstance(self.motion_scale, dict) else [self.motion_scale]
        if self.motion_scale not in ("auto", None) and not (scales and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= MAX_MOTION_SCALE for v in scales)):
            raise ValueError(f"motion_scale must be positive and at most {MAX_MOTION_SCALE:g} (or one such per group), "
                             f"or 'auto', not {self.motion_scale!r}")
        orders = self.motion_order.values() if isinstance(self.motion_order, dict) else [self.motion_order]
        if self.motion_order != "auto" and not (orders and all(k in (1, 2, 3) and not isinstance(k, bool)
                                                               for k in orders)):
            raise ValueError(f"motion_order must be 1, 2, 3 (or one such per group) or 'auto', "
                             f"not {self.motion_order!r}")
        if self.motion_order != "auto" and set(orders) != {3} and self.method != "fte":
            why = "it has no motion model" if self.method == "tri" else "its stream is a constant-acceleration filter"
            raise ValueError(f"motion_order {self.motion_order!r} is for method 'fte' ({self.method!r}: {why})")
        if not (0 < self.lag_seconds <= MAX_LAG_SECONDS):
            raise ValueError(f"lag_seconds must be positive and at most {MAX_LAG_SECONDS:g}, not {self.lag_seconds}")
        if self.body not in BODIES:
            raise ValueError(f"body must be one of {', '.join(BODIES)}, not {self.body!r}")
        if self.body == "given" and not self.body_lengths:
            raise ValueError("body 'given' needs body_lengths (metres per length group)")
        if self.body_lengths is not None and not all(
                isinstance(v, (int, float)) and 0 < v < float("inf") for v in self.body_lengths.values()):
            raise ValueError("body_lengths must be positive lengths in metres")
        if self.sync not in SYNCS:
            raise ValueError(f"sync must be one of {', '.join(SYNCS)}, not {self.sync!r}")
        if self.time_offsets is not None and not all(
                isinstance(v, (int, float)) and abs(v) < float("inf") for v in self.time_offsets):
            raise ValueError("time_offsets must be finite numbers of frames, one per camera")
        if not (isinstance(self.min_views, int) and 0 <= self.min_views <= MAX_MIN_VIEWS):
            raise ValueError(f"min_views must be a whole number from 0 to {MAX_MIN_VIEWS}, not {self.min_views!r}")
        if self.swap_rate != "auto" and not (isinstance(self.swap_rate, (int, float)) and not isinstance(
                self.swap_rate, bool) and 0 <= self.swap_rate < 0.5):
            raise ValueError(f"swap_rate must be 'auto' or a share from 0 to below 0.5, not {self.swap_rate!r}")
        if self.window_frames is not None and not (isinstance(self.window_frames, int) and not isinstance(
                self.window_frames, bool) and (self.window_frames == 0 or MIN_WINDOW_FRAMES <= self.window_frames)):
            raise ValueError(f"window_frames must be 0 (the whole run) or a whole number of frames of at least "
                             f"{MIN_WINDOW_FRAMES}, not {self.window_frames!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Progress:
    """A progress report: ``fraction`` in [0, 1] of the whole solve (or calibration)."""

    stage: str  # a solve's: one of STAGES; a calibration's: "detect", "intrinsics <camera>", ...
    fraction: float
    iteration: int = 0
    cost: float = float("nan")
    detail: str = ""  # more for a person: which window of a long run, the time left


ProgressCallback = Callable[[Progress], None]


@dataclass
class SolveReport:
    """Numbers about the run, written to REPORT.json and shown by the service."""

    method: str
    skeleton: str
    frames: int
    cameras: int
    markers: int
    seconds: dict[str, float] = field(default_factory=lambda: {"total": 0.0, "init": 0.0, "solve": 0.0})
    iterations: int = 0
    cost: float = float("nan")
    reprojection_rmse_px: float = float("nan")
    per_frame_ms: dict[str, float] | None = None
    outliers: int = 0  # observations the robust loss gave (almost) no weight
    observations: int = 0  # observations above the likelihood threshold
    unconstrained_markers: list[str] = field(default_factory=list)  # never seen by two cameras
    unconstrained_frames: list[int] = field(default_factory=list)  # frames with no marker seen twice
    # fte and ekf: per marker, the frames answered from the motion model (fewer than two cameras saw it)
    motion_only_frames: dict[str, int] = field(default_factory=dict)
    bounds_active: int = 0
    # (camera, frame, left/right pair) taken as swapped by the 2D tracker and solved exchanged (graph.solve.swaps)
    side_swaps: int = 0
    swap_rate: float | None = None  # the share of pairs swapped, estimated (swap_rate "auto") or given
    sigma_px: float = float("nan")  # the detection noise the loss and the uncertainties assumed (px)
    noise_px: float = float("nan")  # the noise measured from the inlier residuals (px; graph.solve.noise)
    # motion_scale "auto": the scale fitted per group ({marker: scale} for free points, {"all": scale}),
    # and the order of each group's prior it was fitted for (chosen with motion_order "auto", else given);
    # give both back (SolveOptions.motion_scale / motion_order) to solve more runs with the same smoothing
    motion_scales: dict[str, float] | None = None
    motion_orders: dict[str, int] | None = None
    # ensembles: each camera's detection noise relative to sigma_px (the median over its markers)
    relative_noise: dict[str, float] | None = None
    # the body's lengths, where estimated: {group or bone: {length_m, std_m, model_m}}
    body_lengths: dict[str, dict[str, float]] | None = None
    # the cameras' offsets (frames, camera 1 = 0), where estimated or given, and their sd
    time_offsets_frames: list[float] | None = None
    time_offsets_std_frames: list[float] | None = None
    offsets_not_identified: list[str] = field(default_factory=list)  # cameras the motion did not time
    # a long run solved in windows (graph.solve.windows): their count, core and margin frames, the
    # stretch the shared unknowns were settled on and the values held; None: solved whole
    windows: dict | None = None
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return jsonable(asdict(self))


@dataclass
class Result:
    """A solved run. N frames, M markers, C cameras, P pose parameters.

    ``positions`` and ``std`` are in the calibration's world frame, metres, NaN where no estimate.
    ``reprojections`` are the estimate drawn into each camera; ``residuals`` the pixel distance
    to the detection (NaN where unobserved or below the likelihood threshold).
    """

    method: str
    skeleton: str
    markers: list[str]
    positions: np.ndarray  # (N, M, 3)
    std: np.ndarray  # (N, M, 3)
    reprojections: np.ndarray  # (C, N, M, 2)
    residuals: np.ndarray  # (C, N, M)
    ncams: np.ndarray  # (N, M) cameras that saw the marker above threshold
    score: np.ndarray  # (N, M) mean likelihood of those views
    outlier: np.ndarray  # (C, N, M) bool: the robust loss rejected this detection
    camera_names: list[str]
    fps: float
    report: SolveReport
    options: SolveOptions
    param_names: list[str] = field(default_factory=list)
    params: np.ndarray | None = None  # (N, P)
    rates: np.ndarray | None = None  # (N, P) per second
    params_std: np.ndarray | None = None  # (N, P)
    causal_positions: np.ndarray | None = None  # "ekf": the per-frame causal estimate (N, M, 3)
    bones: list[tuple[str, str]] = field(default_factory=list)  # for drawing
    camera_centers: np.ndarray | None = None  # (C, 3) world positions of the cameras, for drawing
    # the detections the solve was given, per camera frame, for drawing over the videos
    detections: np.ndarray | None = None  # (C, N, M, 2) pixels, NaN where missing
    likelihood: np.ndarray | None = None  # (C, N, M), 0 where missing

    def frames(self, a: int, b: int) -> Result:
        """The frames ``[a, b)`` of this result (its per-frame arrays sliced on their frame axis,
        :data:`FRAME_AXIS`; the report as it is)."""
        sliced = {}
        for name, axis in FRAME_AXIS.items():
            v = getattr(self, name)
            if v is not None:
                sliced[name] = v[(slice(None),) * axis + (slice(a, b),)]
        return replace(self, **sliced)

    @property
    def error(self) -> np.ndarray:
        """Mean reprojection error per frame and marker over the cameras that saw it (N, M)."""
        with np.errstate(invalid="ignore"):
            r = np.where(self.outlier, np.nan, self.residuals)
            cnt = np.isfinite(r).sum(0)
            return np.where(cnt > 0, np.nansum(r, 0) / np.maximum(cnt, 1), np.nan)


# the frame axis of each per-frame array of a Result (the rest, camera_centers, are not per frame)
FRAME_AXIS = {"positions": 0, "std": 0, "reprojections": 1, "residuals": 1, "ncams": 0, "score": 0, "outlier": 1,
              "params": 0, "rates": 0, "params_std": 0, "causal_positions": 0, "detections": 1, "likelihood": 1}


def together(group: Sequence[tuple[str, Result]]) -> Result:
    """Several individuals solved together as one :class:`Result` to draw: every one's markers side
    by side (named ``<individual> <marker>``, bones likewise), their per-marker arrays joined along
    the marker axis; no pose parameters (each individual has its own). The report is the first's."""
    first = group[0][1]

    def joined(name: str, axis: int):
        parts = [getattr(r, name) for _, r in group]
        return None if any(a is None for a in parts) else np.concatenate([np.asarray(a) for a in parts], axis=axis)

    return replace(first, markers=[f"{n} {m}" for n, r in group for m in r.markers],
                   bones=[(f"{n} {a}", f"{n} {b}") for n, r in group for a, b in r.bones],
                   positions=joined("positions", 1), std=joined("std", 1), ncams=joined("ncams", 1),
                   score=joined("score", 1), reprojections=joined("reprojections", 2),
                   residuals=joined("residuals", 2), outlier=joined("outlier", 2),
                   detections=joined("detections", 2), likelihood=joined("likelihood", 2),
                   causal_positions=joined("causal_positions", 1), param_names=[], params=None, rates=None,
                   params_std=None)


def jsonable(x):
    """``x`` as plain JSON values: dict keys as strings, tuples and arrays as lists, numpy scalars as
    Python numbers, and NaN or infinity as None (JSON has no such numbers)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x
