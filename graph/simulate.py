"""Synthetic runs: a cheetah crossing a calibrated rig, seen through DeepLabCut-like detections.

The run (ground truth)
----------------------
The rig fixes the stage. World "up" is the mean of the cameras' image-up directions
``-R_c[1, :]`` (row 1 of ``R`` is the image y axis, which points down). For the AcinoSet 2019 rig
that is +z to within 4 degrees, so the cheetah model (z up) is simulated directly in the rig's world
frame; a rig whose up axis is further than :data:`MAX_TILT_DEG` from +z is still simulated with +z
up and the run says so in ``notes``. The rig file has no ground plane: the ground is put
:data:`CAMERA_HEIGHT` below the cameras' mean height (AcinoSet's own calibration tool places its
cameras on average 0.5 m above the ground).

The head (the root point between the eyes) follows a figure of eight centred on the middle of the
volume every camera sees, its long axis along the track: the direction through that middle along
which every camera keeps the head in view furthest both ways (for the AcinoSet rig, along its two
rows of cameras). With ``t' = t - T/2`` and ``u, w`` along
and across the track::

    u(t) = a sin(w0 t'),   w(t) = (b / 2) sin(2 w0 t'),   w0 = v / sqrt(a^2 + b^2)

so the middle frame of a run crosses the centre at speed ``v``; a run longer than one loop (about
``2 pi / w0``) goes round again and never leaves the stage. ``a`` is 75-85 % of the distance from
the centre to the edge of the commonly seen floor along the track, ``b`` 25-45 % of ``a``. The head
yaw ``psi_0 = atan2(dy, dx)`` follows the heading; its height is ``ground + h`` with ``h`` in
0.60-0.66 m plus a small bob. The legs swing periodically (a rotary gallop at ``f`` strides per
second; front knees in ``[-pi, 0]``, back knees in ``[0, pi]``), the neck, torso and tail move
slowly and smoothly, the neck yaw leans into turns. Every angle is a sum of sinusoids, so the run is
smooth (constant acceleration over a frame is a good model) and stays strictly inside the joint
bounds. Everything random comes from one ``numpy.random.Generator(seed)``, unless a ``noise_seed``
is given: then the truth still comes from ``seed`` and the detections from a generator of their own
seeded with ``(seed, noise_seed)``, so several detection sets of one run (an ensemble of pose
models, each with its own noise and outliers) share the same truth.

The observations (what a DeepLabCut network would write)
--------------------------------------------------------
Each marker is projected with each camera (``Calibration.project``), then, per coordinate,

* ``z = uv + n``, ``n ~ N(0, sigma_n^2)`` (every detection);
* with probability ``p_o`` an outlier offset ``o ~ N(0, sigma_o^2)`` is added (the paper's
  protocol). A fraction ``confident`` of outliers keep a high likelihood (DLC's confident mistakes);
  the others get a low one, ``U(0.02, 0.45)``;
* good detections get a likelihood ``U(0.8, 1.0)``;
* left/right swaps: with probability ``p_s`` per camera, frame and l_/r_ pair, the two detections of
  the pair trade places (confident);
* dropouts: ``dropouts`` stretches of ``dropout_seconds`` in which one camera sees nothing;
* a detection outside the image (``0 <= u < W``, ``0 <= v < H``) or behind the camera is missing:
  NaN with likelihood 0, as are dropped-out frames.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from graph.camera import PINHOLE, Calibration, Camera
from graph.errors import InputError, unreadable
from graph.io.calibration import default_rig_path, load_calibration, write_acinoset_json, write_anipose_toml
from graph.io.keypoints import Keypoints, write_dlc_csv
from graph.skeleton import Skeleton, left_right_pairs, load_skeleton
from graph.types import jsonable

CAMERA_HEIGHT = 0.5  # m: the cameras' mean height above the ground
MAX_TILT_DEG = 15.0  # rigs whose up axis is further than this from +z get a note
GOOD_LIKELIHOOD = (0.8, 1.0)
LOW_LIKELIHOOD = (0.02, 0.45)
CONFIDENT_OUTLIERS = 0.3  # the share of outliers that keep a high likelihood by default
BODY_STREAM = 7919  # the body proportions draw from default_rng([seed, BODY_STREAM]), apart from the run
GALLOP_PHASES = {"l_front": 0.0, "r_front": 0.12, "l_back": 0.55, "r_back": 0.65}  # in cycles


@dataclass
class Stage:
    """Where a rig looks: the middle of the commonly seen floor and the track through it."""

    up: np.ndarray  # (3,) unit world up as the cameras see it
    tilt_deg: float  # angle between ``up`` and +z
    ground_z: float  # z of the ground plane
    centre: np.ndarray  # (2,) x, y of the middle of the floor every camera sees at head height
    track: np.ndarray  # (2,) unit direction along the track
    half_length: float  # m from the centre to the edge of that floor along the track
    cameras_seeing_all: int  # how many cameras the centre region is computed for


@dataclass
class ObservationModel:
    """How detections are corrupted; see the module docstring."""

    noise_px: float = 5.0
    outlier_rate: float = 0.1
    outlier_std_px: float = 100.0
    confident_outliers: float = CONFIDENT_OUTLIERS
    swap_rate: float = 0.0
    dropouts: int = 0
    dropout_seconds: float = 0.25

    def __post_init__(self) -> None:
        if not self.noise_px >= 0:
            raise ValueError(f"noise must be >= 0 px, not {self.noise_px}")
        for name in ("outlier_rate", "confident_outliers", "swap_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name.replace('_', ' ')} must be in [0, 1], not {v}")
        if not self.outlier_std_px >= 0:
            raise ValueError(f"outlier std must be >= 0 px, not {self.outlier_std_px}")
        if self.dropouts < 0 or not self.dropout_seconds >= 0:
            raise ValueError("dropouts and their length must be >= 0")


@dataclass
class SimulatedRun:
    """A simulated run. C cameras, N frames, M markers, P pose parameters (cheetah only)."""

    skeleton: str
    markers: list[str]
    positions: np.ndarray  # (N, M, 3) true marker positions, world frame, metres
    params: np.ndarray | None  # (N, P) true pose parameters of the cheetah model
    param_names: list[str]
    keypoints: list[Keypoints]  # one per camera, in the calibration's order
    calibration: Calibration
    fps: float
    projections: np.ndarray  # (C, N, M, 2) noiseless pixels, NaN outside the image
    outlier: np.ndarray  # (C, N, M) an outlier offset was added
    swapped: np.ndarray  # (C, N, M) the detection belongs to the l_/r_ partner
    dropout: np.ndarray  # (C, N, M) the camera was blind
    observation: ObservationModel
    stage: Stage
    seed: int
    bones: list[tuple[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    noise_seed: int | None = None  # the detections' own seed, if any (module docstring)
    time_offsets: np.ndarray | None = None  # (C,) frames: camera c's frame n is the truth at n + offset
    true_lengths: dict[str, float] = field(default_factory=dict)  # the animal's length of each group (m)
    process_noise: float | None = None  # random_jerk_run: the true sd of the frame-to-frame change of acceleration
    # (C, N, M, 3) where the cameras' clocks differ: the true positions each camera saw at its frames
    seen_positions: np.ndarray | None = None

    def camera_positions(self, c: int) -> np.ndarray:
        """(N, M, 3): the true positions at camera ``c``'s frames (its own clock)."""
        return self.positions if self.seen_positions is None else self.seen_positions[c]

    @property
    def frames(self) -> int:
        return self.positions.shape[0]

    @property
    def visible(self) -> np.ndarray:
        """(C, N, M): the marker projects inside the image."""
        return np.isfinite(self.projections).all(axis=-1)


# ------------------------------------------------------------------------------------------ stage


def rig_stage(calibration: Calibration, head_height: float = 0.6, grid_step: float = 0.25) -> Stage:
    """Find the up axis, the ground and the middle of the volume every camera sees.

    The floor region is found on a grid at ``ground + head_height`` over the cameras' bounding box
    grown by 5 m: a cell counts when it projects inside every image (or, if no cell does, inside
    as many as some cell does). The centre is the region's centroid. The track is the direction
    (searched every 2 degrees) along which the head stays in view of those cameras furthest from
    the centre both ways; ``half_length`` is that distance.
    """
    cams = calibration.cameras
    if len(cams) < 2:
        raise InputError("simulation needs a calibration with at least two cameras")
    up = -np.mean([c.R[1] for c in cams], axis=0)
    up /= np.linalg.norm(up)
    tilt = math.degrees(math.acos(float(np.clip(up[2], -1.0, 1.0))))
    centres = np.stack([c.center for c in cams])
    ground = float(centres[:, 2].mean() - CAMERA_HEIGHT)
    z = ground + head_height
    lo = centres[:, :2].min(0) - 5.0
    hi = centres[:, :2].max(0) + 5.0
    xs = np.arange(lo[0], hi[0] + grid_step, grid_step)
    ys = np.arange(lo[1], hi[1] + grid_step, grid_step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    P = np.stack([X, Y, np.full_like(X, z)], axis=-1)
    seen = _in_image(calibration, _project(calibration, P)).sum(axis=0)
    need = len(cams)
    while need > 1 and not (seen >= need).any():
        need -= 1
    region = seen >= need
    if not region.any():
        raise InputError("no point at animal height is seen by two cameras of this calibration")
    pts = P[region][:, :2]
    centre = pts.mean(axis=0)
    # the track: the direction through the centre along which that floor reaches furthest both ways
    steps = np.arange(grid_step / 5, 30.0, grid_step / 5)
    best = (-1.0, np.array([1.0, 0.0]))
    for ang in np.radians(np.arange(0.0, 180.0, 2.0)):
        d = np.array([math.cos(ang), math.sin(ang)])
        reach = min(_reach(calibration, centre, sign * d, z, steps, need) for sign in (1.0, -1.0))
        if reach > best[0]:
            best = (reach, d)
    half, track = best
    return Stage(up=up, tilt_deg=tilt, ground_z=ground, centre=centre, track=track,
                 half_length=float(half), cameras_seeing_all=need)


def _reach(calibration: Calibration, centre: np.ndarray, direction: np.ndarray, z: float,
           steps: np.ndarray, need: int) -> float:
    """How far from ``centre`` along ``direction`` (at height ``z``) ``need`` cameras still see."""
    P = np.concatenate([centre + steps[:, None] * direction, np.full((len(steps), 1), z)], axis=1)
    ok = _in_image(calibration, _project(calibration, P)).sum(axis=0) >= need
    return float(steps[-1]) if ok.all() else float(steps[int(np.argmin(ok))] - (steps[1] - steps[0]))


def _project(calibration: Calibration, X: np.ndarray) -> np.ndarray:
    """``calibration.project`` without warnings for points behind a camera (they come back NaN)."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return calibration.project(X)


def _in_image(calibration: Calibration, uv: np.ndarray) -> np.ndarray:
    """(C, ...) bool: finite and inside ``[0, W) x [0, H)`` (any size if the camera has none)."""
    ok = np.isfinite(uv).all(axis=-1)
    for c, cam in enumerate(calibration.cameras):
        W, H = cam.size
        if W > 0 and H > 0:
            with np.errstate(invalid="ignore"):
                ok[c] &= (uv[c, ..., 0] >= 0) & (uv[c, ..., 0] < W) & (uv[c, ..., 1] >= 0) & (uv[c, ..., 1] < H)
    return ok


# ------------------------------------------------------------------------------------ the motion


def cheetah_motion(skeleton: Skeleton, stage: Stage, frames: int, fps: float, rng: np.random.Generator,
                   speed: float = 4.0, stride_hz: float = 2.5, times: np.ndarray | None = None) -> np.ndarray:
    """True pose parameters (N, P) of a cheetah running a figure of eight (module docstring), at
    frames ``0 .. frames-1`` or at ``times`` (frames, any reals): the run is a smooth function of
    time, and the same ``rng`` state gives the same run on any clock."""
    if frames < 1:
        raise ValueError("frames must be at least 1")
    t = (np.arange(frames) if times is None else np.asarray(times, dtype=float)) / fps
    tp = t - (frames - 1) / fps / 2.0
    a = rng.uniform(0.75, 0.85) * stage.half_length
    b = rng.uniform(0.25, 0.45) * a
    v = speed * rng.uniform(0.9, 1.1)
    w0 = v / math.hypot(a, b)
    run_dir = rng.choice([-1.0, 1.0])  # which way along the track
    side = rng.choice([-1.0, 1.0])  # which way the loop bends first
    u = run_dir * a * np.sin(w0 * tp)
    w = side * 0.5 * b * np.sin(2 * w0 * tp)
    du = run_dir * a * w0 * np.cos(w0 * tp)
    dw = side * b * w0 * np.cos(2 * w0 * tp)
    ddu = -run_dir * a * w0**2 * np.sin(w0 * tp)
    ddw = -side * 2 * b * w0**2 * np.sin(2 * w0 * tp)
    tr = stage.track
    across = np.array([-tr[1], tr[0]])
    xy = stage.centre + u[:, None] * tr + w[:, None] * across
    vel = du[:, None] * tr + dw[:, None] * across
    acc = ddu[:, None] * tr + ddw[:, None] * across
    yaw = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    yaw_rate = (vel[:, 0] * acc[:, 1] - vel[:, 1] * acc[:, 0]) / np.maximum((vel**2).sum(1), 1e-9)

    f = stride_hz * rng.uniform(0.9, 1.1)
    gait = 2 * math.pi * f * t + rng.uniform(0, 2 * math.pi)
    height = rng.uniform(0.6, 0.66)

    def slow(amp: float, hz: float) -> np.ndarray:
        """A smooth small motion: two sinusoids of random phase around ``hz``."""
        p1, p2 = rng.uniform(0, 2 * math.pi, 2)
        return amp * (0.7 * np.sin(2 * math.pi * hz * t + p1) + 0.3 * np.sin(2 * math.pi * 1.7 * hz * t + p2))

    q: dict[str, np.ndarray] = {}
    q["x_0"], q["y_0"] = xy[:, 0], xy[:, 1]
    q["z_0"] = stage.ground_z + height + 0.02 * np.sin(gait + 0.5)
    q["psi_0"] = yaw
    q["phi_0"] = slow(0.04, 0.6)
    q["theta_0"] = 0.05 * np.sin(gait + 1.0) + slow(0.04, 0.5)
    q["phi_1"] = slow(0.04, 0.5)
    q["theta_1"] = 0.12 + 0.04 * np.sin(gait + 1.5)
    q["psi_1"] = np.clip(-0.12 * yaw_rate, -0.35, 0.35) + slow(0.04, 0.4)
    # the front torso's pitch (the sum of head, neck and torso pitch) stays level but for the flex
    q["theta_2"] = -(q["theta_0"] + q["theta_1"]) + 0.08 * np.sin(gait)
    q["phi_3"] = slow(0.03, 0.7)
    q["theta_3"] = 0.10 * np.sin(gait + math.pi)
    q["psi_3"] = np.clip(-0.08 * yaw_rate, -0.3, 0.3) + slow(0.03, 0.5)
    q["theta_4"] = -0.5 + 0.15 * np.sin(gait + 2.0) + slow(0.05, 0.4)
    q["psi_4"] = slow(0.25, 0.5)
    q["theta_5"] = 0.4 + 0.2 * np.sin(gait + 2.6) + slow(0.1, 0.4)
    q["psi_5"] = slow(0.35, 0.6)
    for side_name, hip, knee in (("l_front", "theta_6", "theta_7"), ("r_front", "theta_8", "theta_9")):
        ph = gait + 2 * math.pi * GALLOP_PHASES[side_name]
        q[hip] = 0.1 + 0.55 * np.sin(ph)
        q[knee] = -(0.25 + 0.55 * (1 + np.sin(ph + 1.2)))  # in [-1.35, -0.25]
    for side_name, hip, knee in (("l_back", "theta_10", "theta_11"), ("r_back", "theta_12", "theta_13")):
        ph = gait + 2 * math.pi * GALLOP_PHASES[side_name]
        q[hip] = -0.1 + 0.5 * np.sin(ph)
        q[knee] = 0.3 + 0.45 * (1 + np.sin(ph - 1.0))  # in [0.3, 1.2]
    missing = [n for n in skeleton.param_names if n not in q]
    if missing:
        raise InputError(f"the simulator drives the cheetah model; skeleton {skeleton.name!r} has "
                         f"parameters it does not know: {', '.join(missing[:5])}")
    params = np.stack([q[n] for n in skeleton.param_names], axis=1)
    margin = 1e-3
    return np.clip(params, skeleton.lower + margin, skeleton.upper - margin)


def ring_rig(cameras: int = 4, radius: float = 4.0, height: float = CAMERA_HEIGHT, focal_px: float = 1400.0,
             size: tuple[int, int] = (1920, 1080)) -> Calibration:
    """A synthetic rig: ``cameras`` pinhole cameras evenly on a circle of ``radius`` m, ``height``
    m above the ground (z = 0), each looking at the centre at that height (a lab's ring, for
    benchmarks on a rig other than the AcinoSet one)."""
    cams = []
    for k in range(cameras):
        a = 2 * math.pi * k / cameras
        C = np.array([radius * math.cos(a), radius * math.sin(a), height])
        fwd = np.array([0.0, 0.0, height]) - C
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(fwd, right), fwd])
        K = np.array([[focal_px, 0, size[0] / 2], [0, focal_px, size[1] / 2], [0, 0, 1]])
        cams.append(Camera(K=K, dist=np.zeros(5), R=R, t=-R @ C, model=PINHOLE, size=size, name=f"cam{k + 1}"))
    return Calibration(cams, source=f"ring of {cameras}")


# ---------------------------------------------------------------------------------- observations


def observe(calibration: Calibration, positions: np.ndarray, markers: list[str], fps: float,
            model: ObservationModel, rng: np.random.Generator):
    """Detections of true ``positions`` (N, M, 3), or (C, N, M, 3) when each camera sees the run on
    a clock of its own, in every camera (module docstring).

    Returns ``(keypoints, projections, outlier, swapped, dropout)``; the masks are (C, N, M).
    """
    N, M = positions.shape[-3:-1]
    if positions.ndim == 4:
        proj = np.stack([_project(Calibration([cam]), positions[c])[0] for c, cam in enumerate(calibration.cameras)])
    else:
        proj = _project(calibration, positions)  # (C, N, M, 2)
    inside = _in_image(calibration, proj)
    proj = np.where(inside[..., None], proj, np.nan)
    C = proj.shape[0]

    xy = proj + rng.normal(0.0, model.noise_px, proj.shape) if model.noise_px > 0 else proj.copy()
    lik = rng.uniform(*GOOD_LIKELIHOOD, size=(C, N, M))

    outlier = rng.random((C, N, M)) < model.outlier_rate
    xy = xy + np.where(outlier[..., None], rng.normal(0.0, model.outlier_std_px, proj.shape), 0.0)
    confident = rng.random((C, N, M)) < model.confident_outliers
    lik = np.where(outlier & ~confident, rng.uniform(*LOW_LIKELIHOOD, size=(C, N, M)), lik)

    swapped = np.zeros((C, N, M), dtype=bool)
    if model.swap_rate > 0:
        for i, j in left_right_pairs(markers):
            hit = rng.random((C, N)) < model.swap_rate
            xi, xj = xy[:, :, i].copy(), xy[:, :, j].copy()
            xy[:, :, i] = np.where(hit[..., None], xj, xi)
            xy[:, :, j] = np.where(hit[..., None], xi, xj)
            li, lj = lik[:, :, i].copy(), lik[:, :, j].copy()
            lik[:, :, i] = np.where(hit, np.maximum(lj, GOOD_LIKELIHOOD[0]), li)
            lik[:, :, j] = np.where(hit, np.maximum(li, GOOD_LIKELIHOOD[0]), lj)
            swapped[:, :, i] |= hit
            swapped[:, :, j] |= hit

    dropout = np.zeros((C, N, M), dtype=bool)
    length = max(1, int(round(model.dropout_seconds * fps)))
    for _ in range(model.dropouts):
        c = int(rng.integers(C))
        start = int(rng.integers(max(1, N - length + 1)))
        dropout[c, start:start + length] = True

    missing = dropout | ~np.isfinite(xy).all(axis=-1)
    xy[missing] = np.nan
    lik[missing] = 0.0
    keypoints = [Keypoints(bodyparts=list(markers), xy=xy[c], likelihood=lik[c], scorer="acinoset-simulated",
                           source=calibration.names[c]) for c in range(C)]
    return keypoints, proj, outlier & ~missing, swapped & ~missing, dropout


# ---------------------------------------------------------------------------------------- the run


def simulate_run(calibration: Calibration, frames: int = 200, fps: float = 120.0, noise: float = 5.0,
                 outliers: float = 0.1, outlier_std: float = 100.0, swaps: float = 0.0, dropouts: int = 0,
                 seed: int = 0, *, confident_outliers: float = CONFIDENT_OUTLIERS,
                 dropout_seconds: float = 0.25, speed: float = 4.0, bodyparts: list[str] | None = None,
                 skeleton: str | Skeleton = "cheetah", noise_seed: int | None = None, body_scale: float = 1.0,
                 body_variation: float = 0.0, time_offsets: list[float] | np.ndarray | None = None) -> SimulatedRun:
    """Simulate a cheetah run across ``calibration``'s cameras and what DeepLabCut would detect.

    ``noise`` sigma_n (px), ``outliers`` p_o, ``outlier_std`` sigma_o (px), ``swaps`` p_s,
    ``dropouts`` the number of blind-camera stretches. ``bodyparts`` keeps a subset of the
    cheetah's markers (in that order), for the ``points`` skeleton. ``noise_seed`` draws the
    detections from ``numpy.random.default_rng((seed, noise_seed))`` instead of continuing the
    truth's generator: runs with the same ``seed`` and different ``noise_seed`` have the same truth
    and independent detections.

    The animal: ``body_scale`` multiplies every length of the model, and each length group is also
    drawn within ``1 +- body_variation`` (uniform, from a generator of its own seeded with ``seed``,
    so the motion stays that of the model's run); the true lengths are ``true_lengths``. The
    clocks: camera c's frame n is the truth at time ``n + time_offsets[c]`` frames (the truth is on
    camera 1's clock: the offsets are taken relative to the first).
    """
    if frames < 1:
        raise ValueError("frames must be at least 1")
    if not fps > 0:
        raise ValueError("fps must be positive")
    model = ObservationModel(noise_px=noise, outlier_rate=outliers, outlier_std_px=outlier_std,
                             confident_outliers=confident_outliers, swap_rate=swaps, dropouts=dropouts,
                             dropout_seconds=dropout_seconds)
    sk = skeleton if isinstance(skeleton, Skeleton) else load_skeleton(skeleton)
    rng = np.random.default_rng(seed)
    stage = rig_stage(calibration)
    notes = []
    if stage.tilt_deg > MAX_TILT_DEG:
        notes.append(f"the rig's up axis is {stage.tilt_deg:.0f} degrees from +z; the run is simulated "
                     "with +z up (the cheetah model's frame)")
    if stage.cameras_seeing_all < len(calibration):
        notes.append(f"no floor is seen by all {len(calibration)} cameras; the run is centred where "
                     f"{stage.cameras_seeing_all} see it")
    if not (body_scale > 0 and 0 <= body_variation < 1):
        raise ValueError("body scale must be positive and body variation in [0, 1)")
    factors = body_scale * np.random.default_rng([seed, BODY_STREAM]).uniform(
        1 - body_variation, 1 + body_variation, len(sk.length_groups))
    true_sk = sk.scaled(factors) if sk.length_groups else sk
    motion_rng = copy.deepcopy(rng)
    params = cheetah_motion(sk, stage, frames, fps, rng, speed=speed)
    positions = true_sk.positions(params)
    offsets = np.zeros(len(calibration)) if time_offsets is None else np.asarray(time_offsets, dtype=float)
    if offsets.shape != (len(calibration),) or not np.isfinite(offsets).all():
        raise ValueError(f"time offsets: one finite number of frames per camera ({len(calibration)})")
    offsets = offsets - offsets[0]
    seen = positions
    if np.any(offsets != 0):
        seen = np.stack([positions if tau == 0 else true_sk.positions(cheetah_motion(
            sk, stage, frames, fps, copy.deepcopy(motion_rng), speed=speed, times=np.arange(frames) + tau))
            for tau in offsets])
    markers = list(sk.markers)
    bones = list(sk.bones)
    if bodyparts is not None:
        unknown = [b for b in bodyparts if b not in markers]
        if unknown:
            raise InputError(f"unknown bodyparts for the simulated cheetah: {', '.join(unknown)}")
        keep = [markers.index(b) for b in bodyparts]
        positions = positions[:, keep]
        seen = seen[..., keep, :]
        markers = list(bodyparts)
        bones = [(a, b) for a, b in bones if a in markers and b in markers]
    obs_rng = rng if noise_seed is None else np.random.default_rng((seed, noise_seed))
    kps, proj, outlier, swapped, dropout = observe(calibration, seen, markers, fps, model, obs_rng)
    return SimulatedRun(skeleton=sk.name, markers=markers, positions=positions, params=params,
                        param_names=list(sk.param_names), keypoints=kps, calibration=calibration, fps=fps,
                        projections=proj, outlier=outlier, swapped=swapped, dropout=dropout,
                        observation=model, stage=stage, seed=seed, bones=bones, notes=notes,
                        noise_seed=noise_seed, time_offsets=offsets, seen_positions=seen if seen.ndim == 4 else None,
                        true_lengths={g: float(L) for g, L in zip(true_sk.length_groups, true_sk.model_lengths)})


def random_jerk_run(calibration: Calibration, frames: int = 300, fps: float = 120.0, process_noise: float = 0.5,
                    noise: float = 2.0, markers: int = 8, spread: float = 0.15, seed: int = 0,
                    order: int = 3) -> SimulatedRun:
    """Free points that move exactly as the smoothers' motion model says, seen by ``calibration``:
    a run whose true smoothness is known, for fitting it (``motion_scale="auto"``).

    Each of ``markers`` points (named ``p1``, ``p2``, ...) starts within ``spread`` m of the stage's
    centre at head height; every coordinate's third difference over frames is white,
    ``x_{n+3} - 3 x_{n+2} + 3 x_{n+1} - x_n ~ N(0, (h^2 process_noise)^2)`` (h = 1/fps: the change of
    acceleration from frame to frame has sd ``process_noise``, m/s^2, the unit of a skeleton's process
    noise). The triple sum of those draws has its least-squares quadratic taken off, which keeps the
    points near the centre and leaves every third difference as drawn. With ``order`` k (1 or 2) the
    k-th difference is the white one instead, of sd ``h^(k-1) process_noise`` (k = 1: a random walk
    of ``process_noise`` m a frame), and the polynomial of degree below k is taken off. Detections:
    Gaussian noise of ``noise`` px, no outliers (:func:`observe`). The run's ``process_noise`` holds
    the truth."""
    if frames < 4:
        raise ValueError("frames must be at least 4")
    if order not in (1, 2, 3):
        raise ValueError(f"order must be 1, 2 or 3, not {order}")
    rng = np.random.default_rng(seed)
    stage = rig_stage(calibration)
    h = 1.0 / fps
    jerk = rng.normal(0.0, h ** (order - 1) * process_noise, (frames - order, markers, 3))
    x = np.zeros((frames, markers, 3))
    x[order:] = jerk
    for _ in range(order):  # x_n = sum of draws k times: its k-th difference is the draw
        x = np.cumsum(x, axis=0)
    t = np.arange(frames, dtype=float)
    basis = np.stack([t**j for j in range(order)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, x.reshape(frames, -1), rcond=None)
    x = x - (basis @ coef).reshape(x.shape)
    centre = np.array([*stage.centre, stage.ground_z + 0.6])
    positions = centre + rng.normal(0.0, spread, (1, markers, 3)) + x
    names = [f"p{k + 1}" for k in range(markers)]
    model = ObservationModel(noise_px=noise, outlier_rate=0.0)
    kps, proj, outlier, swapped, dropout = observe(calibration, positions, names, fps, model, rng)
    return SimulatedRun(skeleton="points", markers=names, positions=positions, params=None, param_names=[],
                        keypoints=kps, calibration=calibration, fps=fps, projections=proj, outlier=outlier,
                        swapped=swapped, dropout=dropout, observation=model, stage=stage, seed=seed,
                        process_noise=process_noise)


# ---------------------------------------------------------------------------------------- writing


def write_truth_csv(path: str | Path, markers: list[str], positions: np.ndarray,
                    ncams: np.ndarray | None = None) -> None:
    """Ground truth in Anipose's 3D CSV layout (as :func:`graph.io.results.write_anipose_csv`): per marker
    ``<m>_x, _y, _z, _error, _ncams, _score``, then ``M_00 .. M_22``, ``center_0 .. center_2`` and
    ``fnum``. Truth has error 0 and score 1; ``ncams`` is how many cameras have the marker in view."""
    N, M, _ = positions.shape
    nc = np.zeros((N, M)) if ncams is None else np.asarray(ncams, dtype=np.float64)
    cols = [f"{m}_{s}" for m in markers for s in ("x", "y", "z", "error", "ncams", "score")]
    cols += [f"M_{i}{j}" for i in range(3) for j in range(3)] + [f"center_{i}" for i in range(3)] + ["fnum"]
    const = [repr(float(v)) for v in np.eye(3).ravel()] + ["0.0"] * 3
    lines = [",".join(cols)]
    for n in range(N):
        row = []
        for m in range(M):
            x, y, z = positions[n, m]
            row += [repr(float(x)), repr(float(y)), repr(float(z)), "0.0", repr(float(nc[n, m])), "1.0"]
        lines.append(",".join(row + const + [str(n)]))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_run(run: SimulatedRun, out: str | Path, rig_path: str | Path | None = None) -> list[Path]:
    """Write a run as a user would bring it: ``cam1.csv`` ... (DeepLabCut CSV), ``calibration.toml``
    (Anipose) and the rig JSON (AcinoSet), plus the truth (``truth.csv``, ``truth.npz``) and
    ``simulation.json`` (the settings). Returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name, kp in zip(run.calibration.names, run.keypoints):
        p = out / f"{name}.csv"
        write_dlc_csv(p, kp)
        written.append(p)
    toml = out / "calibration.toml"
    write_anipose_toml(toml, run.calibration)
    written.append(toml)
    scene = out / (Path(rig_path).name if rig_path is not None else "scene.json")
    if rig_path is not None and Path(rig_path).suffix.lower() == ".json":
        shutil.copyfile(rig_path, scene)
    else:
        scene = scene.with_suffix(".json")
        write_acinoset_json(scene, run.calibration)
    written.append(scene)
    truth_csv = out / "truth.csv"
    write_truth_csv(truth_csv, run.markers, run.positions, ncams=run.visible.sum(axis=0))
    truth_npz = out / "truth.npz"
    np.savez_compressed(truth_npz, positions=run.positions, markers=np.array(run.markers),
                        params=run.params if run.params is not None else np.zeros((run.frames, 0)),
                        param_names=np.array(run.param_names), projections=run.projections,
                        outlier=run.outlier, swapped=run.swapped, dropout=run.dropout, fps=run.fps)
    written += [truth_csv, truth_npz]
    meta = out / "simulation.json"
    meta.write_text(json.dumps({
        "frames": run.frames, "fps": run.fps, "seed": run.seed, "noise_seed": run.noise_seed,
        "skeleton": run.skeleton,
        "cameras": run.calibration.names, "markers": run.markers,
        "observation": asdict(run.observation),
        "ground_z": run.stage.ground_z, "stage_centre": run.stage.centre.tolist(),
        "track": run.stage.track.tolist(), "notes": run.notes,
        "outliers": int(run.outlier.sum()), "swapped": int(run.swapped.sum()),
        "dropped": int(run.dropout.sum()), "outside_image": int((~run.visible).sum()),
        "true_lengths_m": jsonable(run.true_lengths), "time_offsets_frames": jsonable(run.time_offsets),
    }, indent=2) + "\n", encoding="utf-8")
    written.append(meta)
    return written


def load_truth(path: str | Path) -> tuple[list[str], np.ndarray]:
    """Markers and true positions (N, M, 3) from a ``truth.npz`` written by :func:`write_run`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return [str(m) for m in z["markers"]], np.asarray(z["positions"], dtype=np.float64)
    except OSError as e:
        raise unreadable(e, path, "a truth file") from None
    except (KeyError, ValueError, EOFError) as e:
        raise InputError(f"not a truth file written by 'acinoset simulate' ({type(e).__name__})", path) from None


# -------------------------------------------------------------------------------------------- CLI


def register(subparsers) -> None:
    """``acinoset simulate``: a synthetic run written as DeepLabCut CSVs plus calibration and truth."""
    p = subparsers.add_parser(
        "simulate",
        description="Simulate a cheetah running across a calibrated rig, with DeepLabCut-like noise, "
                    "outliers, left/right swaps and camera dropouts. Writes cam1.csv ... (DeepLabCut CSV), "
                    "calibration.toml (Anipose), the rig JSON (AcinoSet), truth.csv (Anipose 3D layout), "
                    "truth.npz and simulation.json.")
    p.add_argument("--rig", default=None, help="calibration file (AcinoSet JSON or Anipose TOML); "
                   "default: the AcinoSet 2019 six-camera rig")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument("--noise", type=float, default=5.0, help="Gaussian pixel noise sigma_n (px)")
    p.add_argument("--outliers", type=float, default=0.1, help="outlier probability p_o")
    p.add_argument("--outlier-std", type=float, default=100.0, help="outlier offset sigma_o (px)")
    p.add_argument("--confident", type=float, default=CONFIDENT_OUTLIERS,
                   help="share of outliers that keep a high likelihood")
    p.add_argument("--swaps", type=float, default=0.0, help="left/right swap probability p_s")
    p.add_argument("--dropouts", type=int, default=0, help="number of blind-camera stretches")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--body-scale", type=float, default=1.0,
                   help="the true animal's size against the model's (0.8: a juvenile)")
    p.add_argument("--body-variation", type=float, default=0.0,
                   help="each length group of the true animal drawn within 1 +- this (0.15: +-15 %%)")
    p.add_argument("--time-offsets", default=None, metavar="T1,T2,...",
                   help="each camera's clock in frames (camera frame n shows the truth at n + T)")
    p.add_argument("--videos", action="store_true",
                   help="also film the run: cam1.mp4 ... of the animal over a textured ground, as each camera "
                        "sees it (H.264; needs the 'video' extra)")
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_cli)


def _cli(args) -> int:
    if args.frames < 1:
        raise InputError(f"--frames must be at least 1, not {args.frames}")
    if not args.fps > 0:
        raise InputError(f"--fps must be positive, not {args.fps}")
    if not args.body_scale > 0 or not 0 <= args.body_variation < 1:
        raise InputError("--body-scale must be positive and --body-variation in [0, 1)")
    rig = Path(args.rig) if args.rig else default_rig_path()
    calibration = load_calibration(rig)
    offsets = None
    if args.time_offsets:
        try:
            offsets = [float(v) for v in args.time_offsets.split(",")]
        except ValueError:
            raise InputError(f"--time-offsets takes frames as 0,0.4,-1.2, not {args.time_offsets!r}") from None
        if len(offsets) != len(calibration):
            raise InputError(f"--time-offsets gives {len(offsets)} offsets for {len(calibration)} cameras")
    if args.videos:
        from graph.video import ffmpeg_exe

        ffmpeg_exe()  # the one-line message naming the extra, before any work
    try:
        run = simulate_run(calibration, frames=args.frames, fps=args.fps, noise=args.noise,
                           outliers=args.outliers, outlier_std=args.outlier_std, swaps=args.swaps,
                           dropouts=args.dropouts, seed=args.seed, confident_outliers=args.confident,
                           body_scale=args.body_scale, body_variation=args.body_variation, time_offsets=offsets)
    except ValueError as e:
        if isinstance(e, InputError):
            raise
        raise InputError(str(e)) from None
    written = write_run(run, args.out, rig_path=rig)
    if args.videos:
        written += _film(run, args.out)
    print(f"simulated {run.frames} frames, {len(run.calibration)} cameras, {len(run.markers)} markers: "
          f"{int(run.outlier.sum())} outliers, {int(run.swapped.sum())} swapped, "
          f"{int(run.dropout.sum())} dropped, {int((~run.visible).sum())} outside the image")
    for note in run.notes:
        print(f"note: {note}")
    print(f"wrote {len(written)} files to {args.out}")
    return 0


def _film(run: SimulatedRun, out: str | Path) -> list[Path]:
    """``--videos``: one H.264 MP4 per camera (:func:`graph.video.write_simulated_videos`), with a
    progress bar on a terminal."""
    import sys

    from graph.progress import FrameProgress
    from graph.video import write_simulated_videos

    bar = FrameProgress(sys.stderr, label="camera-frames filmed") if sys.stderr.isatty() else None
    try:
        return write_simulated_videos(run, out, progress=bar, seed=run.seed)
    except ValueError as e:
        raise InputError(str(e)) from None
    finally:
        if bar is not None:
            bar.close()
