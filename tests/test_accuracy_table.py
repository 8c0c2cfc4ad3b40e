"""The standing accuracy table: each regime the estimator must hold, a few seconds of simulated run,
solved with ``fte``'s defaults under several tiny jitters of its detections (uniform within
``JITTER_PX``, a draw each).

For each regime the *worst* jitter's mean 3D error is held to its floor: measured as the best this
code reached (the floors below; the machine and date in :data:`MEASURED`), and more than
:data:`REGRESSION` above it fails. The spread between jitters is held too: an answer that moves with
0.001 px of jitter lands in a different basin depending on rounding, the instability the hard regime
once showed (13-48 mm over five draws). Beside the table, its oracles: the same solver given the true
body (proportions off), and ``ekf`` against ``fte`` on the drop-outs and with clocks off.

The table is printed (``pytest -s``) and is in every failure's message.
"""

from __future__ import annotations

import copy
import functools
import warnings
from dataclasses import dataclass, field

import numpy as np
import pytest

from graph.api import solve
from graph.camera import FISHEYE, Calibration
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import SimulatedRun, ring_rig, simulate_run
from graph.types import SolveOptions

JITTER_PX = 0.001
JITTERS = 3  # draws per regime: the first is the detections as simulated
REGRESSION = 0.10  # the worst jitter more than 10 % above its floor fails
MAX_SPREAD = 0.10  # (worst - best) / best over the jitters
MEASURED = "2026-12-03, 2 shared cores; the hard regime 2026-12-06 (left/right swaps decided)"


def acinoset() -> Calibration:
    return load_calibration(default_rig_path())


def fisheye_ring() -> Calibration:
    """Six fisheye cameras on a ring of 8 m, 500 px focal length (a wide rig of low resolution: each
    triangulated point some 80-100 mm off)."""
    cams = []
    for c in ring_rig(cameras=6, radius=8.0, focal_px=500.0).cameras:
        c = copy.deepcopy(c)
        c.model, c.dist = FISHEYE, np.array([0.05, -0.01, 0.0, 0.0])
        cams.append(c)
    return Calibration(cams, source="fisheye ring")


@dataclass(frozen=True)
class Regime:
    rig: str
    simulate: dict
    options: dict = field(default_factory=dict)
    floor_mm: float = 0.0  # the worst jitter's mean error, as measured (module docstring)


RIGS = {"acinoset": acinoset, "fisheye ring": fisheye_ring}
REGIMES = {
    "exact model": Regime("acinoset", dict(frames=120), dict(body="model"), 4.81),
    "proportions off": Regime("acinoset", dict(frames=120, body_scale=0.9, body_variation=0.15), {}, 4.86),
    "clocks off": Regime("acinoset", dict(frames=120, time_offsets=[0, 0.4, -0.7, 1.3, 0.2, -0.3]),
                         dict(sync="estimate"), 5.04),
    "outliers, swaps, blind cameras": Regime(
        "fisheye ring", dict(frames=240, noise=5.0, outliers=0.2, outlier_std=150.0, confident_outliers=1.0,
                             swaps=0.1, dropouts=2, speed=8.0, body_variation=0.12), {}, 14.89),
    "long and slow": Regime("acinoset", dict(frames=1200, speed=1.5), {}, 4.60),
    "camera drop-outs": Regime("acinoset", dict(frames=360, dropouts=8, dropout_seconds=1.0), {}, 5.97),
}


def jittered(run: SimulatedRun, draw: int) -> list:
    if draw == 0:
        return run.keypoints
    rng = np.random.default_rng(draw)
    out = []
    for k in run.keypoints:
        k = copy.deepcopy(k)
        k.xy = k.xy + rng.uniform(-JITTER_PX, JITTER_PX, k.xy.shape)
        out.append(k)
    return out


def error_mm(result, run: SimulatedRun) -> float:
    return float(np.nanmean(np.linalg.norm(result.positions - run.positions, axis=-1)) * 1000)


@dataclass
class Row:
    errors_mm: list[float]
    iterations: list[int]
    floor_mm: float

    @property
    def worst(self) -> float:
        return max(self.errors_mm)

    @property
    def spread(self) -> float:
        return (max(self.errors_mm) - min(self.errors_mm)) / min(self.errors_mm)


@functools.cache
def run_of(name: str) -> tuple[SimulatedRun, Calibration]:
    """The regime's simulated run (seed 0) and its rig, simulated once for all the tests here."""
    regime = REGIMES[name]
    cal = RIGS[regime.rig]()
    return simulate_run(cal, fps=120.0, seed=0, **regime.simulate), cal


@pytest.fixture(scope="module")
def table() -> dict[str, Row]:
    rows = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, regime in REGIMES.items():
            run, cal = run_of(name)
            results = [solve(jittered(run, j), cal, SolveOptions(fps=120.0, **regime.options)) for j in range(JITTERS)]
            rows[name] = Row([error_mm(r, run) for r in results], [r.report.iterations for r in results],
                             regime.floor_mm)
    print("\n" + text(rows))
    return rows


def text(rows: dict[str, Row]) -> str:
    lines = [f"{'regime':32s} {'worst mm':>9s} {'floor':>6s} {'spread':>7s}  each jitter (mm), iterations"]
    for name, r in rows.items():
        lines.append(f"{name:32s} {r.worst:9.2f} {r.floor_mm:6.1f} {r.spread * 100:6.1f}%  "
                     + " ".join(f"{e:.2f}" for e in r.errors_mm) + "  " + " ".join(map(str, r.iterations)))
    return "\n".join(lines)


@pytest.mark.parametrize("name", list(REGIMES))
def test_no_regime_regresses_past_its_floor(table, name):
    row = table[name]
    assert row.worst <= row.floor_mm * (1 + REGRESSION), f"{name} regressed:\n{text(table)}"


@pytest.mark.parametrize("name", list(REGIMES))
def test_no_regime_moves_with_a_thousandth_of_a_pixel(table, name):
    assert table[name].spread <= MAX_SPREAD, f"{name} depends on rounding:\n{text(table)}"


def test_proportions_off_within_1_2x_of_the_solve_given_the_true_body(table):
    """The same solver, told the animal's true lengths (the oracle), on the same detections."""
    run, cal = run_of("proportions off")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        oracle = error_mm(solve(run.keypoints, cal, SolveOptions(fps=120.0, body="given",
                                                                  body_lengths=run.true_lengths)), run)
    ours = table["proportions off"].errors_mm[0]
    assert ours <= 1.2 * oracle, f"body estimated {ours:.2f} mm, given the true body {oracle:.2f} mm"


def test_iterations_do_not_grow_with_length(table):
    """1,200 frames of a slow run take no more Levenberg-Marquardt iterations than 120 of the model's
    (they once took 10 against 5)."""
    assert max(table["long and slow"].iterations) <= max(table["exact model"].iterations) + 1, text(table)


EKF_OVER_FTE = 1.03  # measured on the drop-outs (ekf 6.14 mm, fte 5.97 mm); the target is 1.5


def test_ekf_on_the_drop_outs_does_not_fall_further_behind_fte(table):
    """ekf, a fixed-lag smoother, carries a stretch in which markers lose their second camera from one
    side for as long as its lag: with a lag of 0.25 s it was 1.84x fte here (10.98 mm: four cameras blind
    together for 65 frames), with the default 0.5 s 1.03x. Held to that ratio to fte (the smoother, both
    sides)."""
    run, cal = run_of("camera drop-outs")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ekf = error_mm(solve(run.keypoints, cal, SolveOptions(fps=120.0, method="ekf")), run)
    fte = table["camera drop-outs"].errors_mm[0]
    assert ekf <= EKF_OVER_FTE * (1 + REGRESSION) * fte, f"ekf {ekf:.2f} mm, fte {fte:.2f} mm"


EKF_CLOCKS_OVER_FTE = 1.11  # measured with clocks off (ekf 5.57 mm, fte 5.03 mm); 1.64x on the nearest frames


def test_ekf_with_clocks_off_stays_near_fte(table):
    """ekf's stream takes each camera's detections interpolated to the reference clock's frames; on the
    nearest frame instead (the offsets' sub-frame part, 0.2-0.4 of a frame here, dropped) it was 8.25 mm.
    Held to its measured ratio to fte."""
    run, cal = run_of("clocks off")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        opts = SolveOptions(fps=120.0, method="ekf", **REGIMES["clocks off"].options)
        ekf = error_mm(solve(run.keypoints, cal, opts), run)
    fte = table["clocks off"].errors_mm[0]
    assert ekf <= EKF_CLOCKS_OVER_FTE * (1 + REGRESSION) * fte, f"ekf {ekf:.2f} mm, fte {fte:.2f} mm"


EKF_HARD_FLOOR_MM = 17.53  # ekf's worst of the three jitters on the hard regime (16.98, 17.53, 16.61), 2026-12-06


def test_ekf_on_the_hard_regime_holds_its_floor_and_does_not_move_with_rounding():
    """The stream on outliers, swaps and blind cameras: its worst jitter held to its floor, and its
    spread between jitters to :data:`MAX_SPREAD` (five draws measured 16.3-17.5 mm: 7 %), as fte's rows."""
    run, cal = run_of("outliers, swaps, blind cameras")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        errors = [error_mm(solve(jittered(run, j), cal, SolveOptions(fps=120.0, method="ekf")), run)
                  for j in range(JITTERS)]
    assert max(errors) <= EKF_HARD_FLOOR_MM * (1 + REGRESSION), errors
    assert (max(errors) - min(errors)) / min(errors) <= MAX_SPREAD, errors
