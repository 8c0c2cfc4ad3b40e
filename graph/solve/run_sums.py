"""A long run's report made from its windows' kept frames as they finish, without holding the run's
arrays (a run solved streamed: :func:`graph.solve.windows.solve_streamed`; only the list of frames no
two cameras saw grows with it).

:func:`graph.solve.result.build_result` makes the report of a run held whole. Streamed, the same
figures come from sums over the cores (each :class:`graph.solve.windows.Core`):

* reprojection RMSE ``sqrt(sum |r|^2 / n)`` over the detections used (valid, not rejected), the
  rejected and valid counts per camera (the inputs' misfit check, :func:`graph.solve.result.inputs_misfit`);
* the markers seen by two cameras at least once, the frames where none was, and per marker the
  frames answered from the motion model alone;
* the measured noise, :func:`graph.solve.noise.scatter_px` of the residuals (relative to an
  ensemble's noise, when there is one) of every ``k``-th frame, ``k = ceil(N / SAMPLE_FRAMES)``: every
  frame up to :data:`SAMPLE_FRAMES` (the same figure as the whole run's), an even sample beyond;
* the motion's plausibility (:func:`graph.solve.result.implausible_motion`), judged on the settled
  stretch's positions: the stretch of the run the cameras saw best.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from graph.solve.noise import scatter_px
from graph.solve.problem import Problem
from graph.solve.result import implausible_motion, inputs_misfit, noise_mismatch
from graph.types import Result, SolveReport

SAMPLE_FRAMES = 20_000  # frames whose residuals measure the noise: at most ~20 MB for 6 cameras, 20 markers


class RunSums:
    """The sums of a run of ``frames`` frames (module docstring), added a core at a time. The noise's
    sample of residuals is kept in memory, or appended to ``sample_file`` (a run that may be resumed:
    :meth:`state`, :meth:`restore`, ``resuming``)."""

    def __init__(self, frames: int, cameras: int, markers: int, noise_scale: np.ndarray | None = None,
                 sample_file: str | Path | None = None, resuming: bool = False):
        self.frames = frames
        self.stride = max(1, math.ceil(frames / SAMPLE_FRAMES))
        self.noise_scale = noise_scale
        self.squares = 0.0
        self.used = 0
        self.valid = np.zeros(cameras, dtype=np.int64)
        self.rejected = np.zeros(cameras, dtype=np.int64)
        self.seen_twice = np.zeros(markers, dtype=bool)
        self.unseen_frames: list[int] = []
        self.alone = np.zeros(markers, dtype=np.int64)
        self.sample: list[np.ndarray] = []
        self.sample_file = None if sample_file is None else Path(sample_file)
        if self.sample_file is not None and not resuming:  # resuming: cut back to its length by restore
            self.sample_file.write_bytes(b"")

    def add(self, at: int, r: Result, valid: np.ndarray) -> None:
        """The kept frames ``r`` of a window, the run's frames from ``at``, with their confident
        detections ``valid`` (n, C, M)."""
        res, out = r.residuals, r.outlier  # (C, n, M): px, NaN where not used; rejected and valid
        used = np.isfinite(res) & ~out
        self.squares += float(np.sum(res[used] ** 2))
        self.used += int(used.sum())
        self.valid += valid.sum(axis=(0, 2))
        self.rejected += out.sum(axis=(1, 2))
        two = r.ncams >= 2
        self.seen_twice |= two.any(axis=0)
        self.unseen_frames += [at + int(n) for n in np.flatnonzero(~two.any(axis=1))]
        self.alone += ((r.ncams < 2) & np.isfinite(r.positions).all(axis=-1)).sum(axis=0)
        keep = (at + np.arange(res.shape[1])) % self.stride == 0
        rel = res[:, keep] if self.noise_scale is None else res[:, keep] / self.noise_scale[:, None, :]
        rel = np.ascontiguousarray(rel.transpose(1, 0, 2), dtype=np.float64)  # (frames, C, M): frame by frame
        if self.sample_file is None:
            self.sample.append(rel)
        else:
            with open(self.sample_file, "ab") as f:
                f.write(rel.tobytes())

    def state(self) -> dict:
        """The sums as JSON values (the sample: its file's length), for :meth:`restore`."""
        return {"squares": self.squares, "used": self.used, "valid": self.valid.tolist(),
                "rejected": self.rejected.tolist(), "seen_twice": self.seen_twice.tolist(),
                "unseen_frames": self.unseen_frames, "alone": self.alone.tolist(),
                "sample_bytes": self.sample_file.stat().st_size if self.sample_file is not None else None}

    def restore(self, state: dict) -> None:
        """The sums as :meth:`state` gave them (the sample file cut back to its length then)."""
        self.squares, self.used = float(state["squares"]), int(state["used"])
        for name in ("valid", "rejected", "alone", "seen_twice"):
            old = getattr(self, name)
            new = np.asarray(state[name], dtype=old.dtype)
            if new.shape != old.shape:
                raise ValueError(f"the saved sums' {name} has shape {new.shape}, not {old.shape}")
            setattr(self, name, new)
        self.unseen_frames = [int(n) for n in state["unseen_frames"]]
        if self.sample_file is not None:
            with open(self.sample_file, "r+b") as f:
                f.truncate(int(state["sample_bytes"]))

    def _noise_sample(self) -> np.ndarray:
        if self.sample_file is not None:
            return np.fromfile(self.sample_file, dtype=np.float64)
        return np.concatenate(self.sample) if self.sample else np.zeros(0)

    def report(self, stretch: Problem, settled: Result, sigma_px: float, seconds: dict, iterations: int, cost: float,
               bounds_active: int, notes: list[str]) -> SolveReport:
        """The run's report: ``stretch`` the settled stretch's problem (the skeleton, rig, options and
        the inputs' notes), ``settled`` its result, ``notes`` the windows' warnings (grouped)."""
        opts, names = stretch.options, stretch.calibration.names
        said = list(stretch.warnings)
        misfit = inputs_misfit(self.rejected[:, None, None], self.valid[:, None, None], names)
        noise = scatter_px(self._noise_sample())
        self.sample = []
        checks = [misfit, None if misfit else noise_mismatch(opts.method, opts.measurement_std_px, sigma_px, noise),
                  implausible_motion(settled.positions, opts.fps)]
        for note in [c for c in checks if c] + notes:
            said.append(note)
            warnings.warn(note, stacklevel=2)
        relative = None if stretch.noise_scale is None else {
            name: float(np.median(stretch.noise_scale[c])) for c, name in enumerate(names)}
        markers = stretch.markers
        return SolveReport(
            method=opts.method, skeleton=stretch.skeleton.name, frames=self.frames, cameras=stretch.cameras,
            markers=len(markers), seconds={"total": 0.0, **{k: float(v) for k, v in seconds.items()}},
            iterations=int(iterations), cost=float(cost),
            reprojection_rmse_px=math.sqrt(self.squares / self.used) if self.used else float("nan"),
            outliers=int(self.rejected.sum()), observations=int(self.valid.sum()),
            unconstrained_markers=[m for m, two in zip(markers, self.seen_twice) if not two],
            unconstrained_frames=self.unseen_frames, bounds_active=int(bounds_active), sigma_px=float(sigma_px),
            noise_px=noise, warnings=said,
            motion_only_frames={m: int(k) for m, k in zip(markers, self.alone) if k}, relative_noise=relative)
