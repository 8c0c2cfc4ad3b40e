"""Synthetic groups: several animals crossing paths and touching in a rig, seen through a multi-animal
2D tracker whose identities swap now and then (the bench and tests of :mod:`graph.solve.identity`).

The animals. Animal ``a`` (of ``A``) is a rigid-ish body of :data:`BODY` markers (metres along and
across its heading, and up), scaled by ``U(0.9, 1.1)``. Its centre runs round the rig's centre on a
circle of radius ``r_a = R (1 + 0.15 (a - (A - 1) / 2))`` whose radius also wobbles by 10 %, at an
angular speed ``w_a = s_a v / R`` with ``s_a`` alternating in sign and ``|s_a|`` in 0.7-1.3, so
that neighbours meet head-on about once a lap and pass within ``0.15 R`` of each other: for the
default ``R`` = 0.8 m and bodies 0.6 m long they touch. Each marker also moves by a few centimetres
(a gait-like sinusoid), and the body faces along its velocity.

The 2D tracker. Each camera sees each animal as one instance (its markers projected, with noise
``sigma_n``, a share ``outliers`` of confident 100 px outliers, a share ``missing_points`` of
points missing); an instance is missing in a share ``missing_instances`` of (camera, frame) pairs.
The instances are put in slots, the tracker's identities: slot ``k`` of camera ``c`` at frame ``t``
holds animal ``owner[c, t, k]``. At the start the slots are the animals; in every frame, with
probability ``swap_rate`` per camera, two slots trade animals from that frame on (a persistent
identity switch, as trackers make them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.camera import Calibration
from graph.io.keypoint_types import Tracks

# marker: (along the heading, across it to the left, up), metres, for a body 0.6 m long
BODY: dict[str, tuple[float, float, float]] = {
    "nose": (0.30, 0.0, 0.28), "l_ear": (0.22, 0.05, 0.33), "r_ear": (0.22, -0.05, 0.33),
    "neck": (0.14, 0.0, 0.30), "spine": (0.0, 0.0, 0.30), "hip": (-0.14, 0.0, 0.28),
    "tail_base": (-0.20, 0.0, 0.27), "tail_tip": (-0.36, 0.0, 0.18),
    "l_front": (0.12, 0.07, 0.02), "r_front": (0.12, -0.07, 0.02),
    "l_back": (-0.14, 0.07, 0.02), "r_back": (-0.14, -0.07, 0.02),
}


@dataclass
class GroupRun:
    """A simulated group: A animals, N frames, M markers, C cameras, K = A slots a camera."""

    markers: list[str]
    positions: np.ndarray  # (N, A, M, 3) true marker positions, metres
    tracks: list[Tracks]  # one a camera: the tracker's slots
    owner: np.ndarray  # (C, N, K) the animal slot k of camera c holds at frame t
    calibration: Calibration
    fps: float
    seed: int

    @property
    def animals(self) -> int:
        return self.positions.shape[1]

    @property
    def frames(self) -> int:
        return self.positions.shape[0]

    def true_tracks(self) -> list[Tracks]:
        """The same detections with every slot its own animal throughout (the oracle's input)."""
        out = []
        for c, t in enumerate(self.tracks):
            order = np.argsort(self.owner[c], axis=1)  # (N, K): the slot holding animal a
            rows = np.arange(self.frames)[:, None]
            out.append(Tracks(bodyparts=list(t.bodyparts), names=list(t.names), xy=t.xy[rows, order],
                              likelihood=t.likelihood[rows, order], identified=True, scorer=t.scorer,
                              source=t.source, fps=t.fps))
        return out


def group_motion(animals: int, frames: int, fps: float, rng: np.random.Generator, radius: float = 0.8,
                 speed: float = 1.0) -> np.ndarray:
    """True marker positions (N, A, M, 3) of :data:`BODY` animals going round the origin (module docstring)."""
    t = np.arange(frames) / fps
    body = np.array(list(BODY.values()))  # (M, 3)
    out = np.empty((frames, animals, len(body), 3))
    for a in range(animals):
        r0 = radius * (1 + 0.15 * (a - (animals - 1) / 2))
        sign = 1.0 if a % 2 == 0 else -1.0
        w = sign * rng.uniform(0.7, 1.3) * speed / radius
        phase = rng.uniform(0, 2 * np.pi)
        wobble = 1 + 0.1 * np.sin(2 * np.pi * rng.uniform(0.05, 0.15) * t + rng.uniform(0, 2 * np.pi))
        ang = phase + w * t
        centre = np.stack([r0 * wobble * np.cos(ang), r0 * wobble * np.sin(ang)], axis=1)  # (N, 2)
        vel = np.gradient(centre, axis=0)
        heading = np.arctan2(vel[:, 1], vel[:, 0])
        scale = rng.uniform(0.9, 1.1)
        along, across, up = (scale * body[:, i] for i in range(3))
        gait = 0.03 * np.sin(2 * np.pi * 2.0 * t[:, None] + rng.uniform(0, 2 * np.pi, len(body)))  # (N, M)
        c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
        out[:, a, :, 0] = centre[:, :1] + c * (along + gait) - s * across
        out[:, a, :, 1] = centre[:, 1:] + s * (along + gait) + c * across
        out[:, a, :, 2] = up + 0.5 * np.abs(gait) * (up < 0.1)
    return out


def simulate_group(calibration: Calibration, animals: int = 2, frames: int = 600, fps: float = 60.0,
                   seed: int = 0, noise: float = 2.0, outliers: float = 0.02, swap_rate: float = 0.02,
                   missing_instances: float = 0.05, missing_points: float = 0.05, radius: float = 0.8,
                   speed: float = 1.0) -> GroupRun:
    """A group of ``animals`` seen by ``calibration``'s cameras through a swapping 2D tracker (module
    docstring). The floor is the rig's ``z = 0`` plane, its centre the origin."""
    if animals < 1 or frames < 1 or not fps > 0:
        raise ValueError("animals and frames must be at least 1, fps positive")
    rng = np.random.default_rng(seed)
    X = group_motion(animals, frames, fps, rng, radius, speed)
    N, A, M, _ = X.shape
    C = len(calibration)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        uv = calibration.project(X.reshape(-1, 3)).reshape(C, N, A, M, 2)
    for c, cam in enumerate(calibration.cameras):
        W, H = cam.size
        if W > 0 and H > 0:
            inside = (uv[c, ..., 0] >= 0) & (uv[c, ..., 0] < W) & (uv[c, ..., 1] >= 0) & (uv[c, ..., 1] < H)
            uv[c][~inside] = np.nan
    xy = uv + rng.normal(0.0, noise, uv.shape)
    bad = rng.random((C, N, A, M)) < outliers
    xy = xy + np.where(bad[..., None], rng.normal(0.0, 100.0, uv.shape), 0.0)
    lik = rng.uniform(0.8, 1.0, (C, N, A, M))
    gone = (rng.random((C, N, A, 1)) < missing_instances) | (rng.random((C, N, A, M)) < missing_points)
    gone = gone | ~np.isfinite(xy).all(-1)
    xy[gone] = np.nan
    lik[gone] = 0.0
    owner = np.empty((C, N, A), dtype=np.int64)
    for c in range(C):
        perm = np.arange(A)
        for n in range(N):
            if A > 1 and rng.random() < swap_rate:
                i, j = rng.choice(A, size=2, replace=False)
                perm[[i, j]] = perm[[j, i]]
            owner[c, n] = perm
    rows = np.arange(N)[:, None]
    markers = list(BODY)
    tracks = [Tracks(bodyparts=markers, names=[f"animal{k + 1}" for k in range(A)], xy=xy[c][rows, owner[c]],
                     likelihood=lik[c][rows, owner[c]], scorer="acinoset-simulated", source=calibration.names[c],
                     fps=fps) for c in range(C)]
    return GroupRun(markers=markers, positions=X, tracks=tracks, owner=owner, calibration=calibration, fps=fps,
                    seed=seed)
