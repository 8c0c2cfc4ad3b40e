"""Probe: the order of the free points' motion prior on the fly (leave one camera out).

    python bench/probe_motion_order.py [--data DIR]

acinoset's smoother puts its prior on the third differences of each coordinate (constant
acceleration; graph.fte, graph.smoothing). aniposelib's ``triangulate_optim`` penalises first
differences. On the fly (bench_fly_loco.py) aniposelib given the ensemble's combined detections
scores better than acinoset's best setting. This probe asks whether the prior's order is why: it
swaps the k-th difference (k = 1, 2, 3) into the free points' smoother in this process only (the
band of the chains' solve, the evidence and the cost; the marginals keep the third difference, which
does not move the positions scored), fits the scale by the evidence as ``motion_scale="auto"`` does,
at the stiffness bound of the library and at 100x it, and scores each by
:func:`graph.metrics.leave_one_camera_out` on both members combined and on member 1. Then, on
simulated runs with a 3D truth (the cheetah solved as free points, the paper's protocol on the
AcinoSet rig: 200 frames, 2, 5 and 10 px, 10 % outliers, seeds 0 and 1), the mean 3D error of each
order.

It patches library internals on purpose: it is a question for the next design step (the order
chosen from the data), not a setting of the library.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

from bench_fly_loco import DATA, FPS, member_files
from graph import fte, smoothing
from graph.calibration import load_calibration
from graph.ensemble import combine
from graph.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out
from graph.types import SolveOptions

STENCILS = {1: np.array([-1.0, 1.0]), 2: np.array([1.0, -2.0, 1.0]), 3: np.array([-1.0, 3.0, -3.0, 1.0])}


def use_order(k: int) -> None:
    """The k-th difference in place of the third in the free points' smoother (this process only)."""
    stencil = STENCILS[k]

    def gram(N: int) -> np.ndarray:  # smoothing.third_difference_gram for the k-th difference
        T = np.zeros((4, N))
        for a in range(k + 1):
            for L in range(k + 1 - a):
                np.add.at(T[L], np.arange(max(N - k, 0)) + a, stencil[a] * stencil[a + L])
        return T

    def evidence(self, s):  # smoothing.ChainEvidence.__call__ for the k-th difference
        G, N, d = self.G, self.N, self.d
        c = 1.0 / (np.asarray(s, dtype=np.float64).reshape(G, 1) * self.sigma) ** 2
        ab = self.base + smoothing.motion_band(c, N, self.T)
        try:
            chol = cholesky_banded(ab, lower=True)
        except np.linalg.LinAlgError:
            return np.full(G, -math.inf)
        xs = cho_solve_banded((chol, True), self.rhs).reshape(G, N, d)
        dx = xs - self.x
        dk = np.diff(xs, k, axis=1)
        phi = (np.einsum("gni,gni->g", self.g, dx) + 0.5 * np.einsum("gni,gnij,gnj->g", dx, self.H, dx)
               + 0.5 * np.einsum("gi,gni->g", c, dk * dk) + 0.5 * self.w * np.sum((xs - self.x0) ** 2, axis=(1, 2)))
        logdet_k = 2.0 * np.log(chol[0]).reshape(G, N * d).sum(axis=1)
        return -phi - 0.5 * logdet_k + 0.5 * max(N - k, 0) * np.log(c).sum(axis=1)

    smoothing.third_difference_gram = gram
    smoothing.ChainEvidence.__call__ = evidence
    fte.TrajectoryProblem.motion_residual = lambda self, Q: np.diff(Q, k, axis=0) / self.sigma3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    cal = load_calibration(args.data / "calibration.toml")
    member1 = [read_keypoints(p) for p in member_files(args.data, 1)]
    ens = [combine([read_keypoints(p) for p in files]) for files in zip(*(member_files(args.data, m) for m in (1, 2)))]
    base = SolveOptions(method="fte", skeleton="points", fps=FPS, motion_scale="auto")
    bound = smoothing.MAX_STIFFNESS
    print("| order | stiffness bound | input | median px | p90 px |\n|---|---|---|---|---|")
    for k in (3, 2, 1):
        use_order(k)
        for b in (bound, 100 * bound):
            smoothing.MAX_STIFFNESS = fte.MAX_STIFFNESS = b
            for name, inputs in (("ensemble", ens), ("member 1", member1)):
                r = leave_one_camera_out(inputs, cal, replace(base), method=f"order {k}", judge=member1)
                print(f"| {k} | {b:g} | {name} | {r.median_px:.3f} | {r.p90_px:.3f} |", flush=True)
    smoothing.MAX_STIFFNESS = fte.MAX_STIFFNESS = bound
    import harness as h
    from graph.api import solve

    rig = h.rig()
    runs = [h.simulate(rig, frames=200, seed=seed, noise=noise, outliers=0.1)
            for seed in (0, 1) for noise in (2.0, 5.0, 10.0)]
    print("\n| order | simulated cheetah as free points: mean 3D error per run (mm) | mean |\n|---|---|---|")
    for k in (3, 2, 1):
        use_order(k)
        errs = []
        for run in runs:
            res = solve(run.keypoints, rig, SolveOptions(fps=run.fps, skeleton="points", motion_scale="auto"))
            errs.append(float(np.nanmean(np.linalg.norm(res.positions - run.positions, axis=-1)) * 1000))
        print(f"| {k} | {', '.join(f'{e:.2f}' for e in errs)} | {np.mean(errs):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
