"""Pictures and the result payload scale with the animal: a fly is drawn as finely as a cheetah."""

from dataclasses import replace

import numpy as np

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run
from graph.viewer.payload import animal_size, result_payload


def test_a_fly_sized_result_keeps_its_detail_and_units(rig):
    run = simulate_run(rig, frames=30, seed=1)
    result = solve(run.keypoints, rig, SolveOptions(fps=run.fps, skeleton="points"))
    fly = replace(result, positions=result.positions * 2e-4, std=result.std * 2e-4)  # a 0.3 mm animal
    assert 1e-4 < animal_size(fly) < 1e-3 and 0.5 < animal_size(result) < 3
    payload = result_payload(fly)
    pos = np.array([[[np.nan if v is None else v for v in p] for p in fr] for fr in payload["positions"]], float)
    ok = np.isfinite(fly.positions)
    # no staircase: every coordinate within 1e-4 of the animal's size of its value
    assert np.max(np.abs(pos[ok] - fly.positions[ok])) < 1e-4 * animal_size(fly)
    assert set(payload["param_units"]) == {"m"}  # a points skeleton's parameters are positions, not angles

