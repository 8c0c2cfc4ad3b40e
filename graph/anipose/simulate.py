"""A simulated Anipose project in Anipose's real layout, to test and time ``acinoset anipose``::

    project/config.toml
    project/calibration/calibration.toml          found by sessions without their own
    project/<session>/calibration/calibration.toml (the first session has its own)
    project/<session>/pose-2d/<trial>_<cam>.h5     DeepLabCut H5, written by pandas/PyTables as
                                                   DeepLabCut writes it (key df_with_missing, table)

Trials are cheetah runs (:func:`graph.simulate.simulate_run`) on three cameras of the real
AcinoSet rig, named A, B, C (``cam_regex = '_([A-Z])$'``), keeping ``bodyparts`` as free points.
Needs pandas and PyTables (the ``test`` extra).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graph.camera import Calibration
from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml

BODYPARTS = ["nose", "l_eye", "r_eye", "neck_base", "spine", "tail_base", "l_shoulder", "r_shoulder"]
CONSTRAINTS = [("nose", "l_eye"), ("nose", "r_eye"), ("neck_base", "spine"), ("spine", "tail_base")]
CAMERAS = ("A", "B", "C")
SCORER = "DLC_resnet50_cheetahOct1shuffle1_100000"


def rig(cameras=(0, 1, 2)) -> Calibration:
    """Three cameras of the AcinoSet 2019 rig, named A, B, C."""
    full = load_calibration(default_rig_path())
    cams = [full.cameras[i] for i in cameras]
    for cam, name in zip(cams, CAMERAS):
        cam.name = name
    return Calibration(cameras=cams, source="acinoset_2019_rig.json")


def write_dlc_h5(path: Path, bodyparts: list[str], xy: np.ndarray, likelihood: np.ndarray) -> None:
    """DeepLabCut's H5: ``DataFrame.to_hdf(path, "df_with_missing", format="table", mode="w")`` with
    the column index (scorer, bodyparts, coords)."""
    import pandas as pd

    n, m = likelihood.shape
    columns = pd.MultiIndex.from_product([[SCORER], bodyparts, ["x", "y", "likelihood"]],
                                         names=["scorer", "bodyparts", "coords"])
    values = np.concatenate([xy, likelihood[..., None]], axis=-1).reshape(n, 3 * m)
    pd.DataFrame(values, columns=columns).to_hdf(path, key="df_with_missing", format="table", mode="w")


DEFAULT_SESSIONS = {"2026-11-30": ["run1", "run2"], "2026-12-01": ["run3"]}


def simulated_trials(sessions: dict[str, list[str]] | None = None, frames: int = 100, fps: float = 120.0,
                     seed: int = 0):
    """``(session, trial, SimulatedRun)`` for every trial, the k-th simulated with seed ``seed + k``
    (the same runs :func:`write_project` writes, with their truth)."""
    from graph.simulate import simulate_run

    cal = rig()
    k = 0
    for session, trials in (sessions or DEFAULT_SESSIONS).items():
        for trial in trials:
            yield session, trial, simulate_run(cal, frames=frames, fps=fps, seed=seed + k, bodyparts=BODYPARTS)
            k += 1


def write_project(root: str | Path, sessions: dict[str, list[str]] | None = None, frames: int = 100,
                  fps: float = 120.0, optim: bool = True, extra_config: str = "", seed: int = 0) -> Path:
    """Write the project; returns its folder. ``sessions``: session -> trial names (default two
    sessions, three trials). The first session has its own calibration, the others find the
    project's by searching upward."""
    root = Path(root)
    sessions = sessions or DEFAULT_SESSIONS
    cal = rig()
    root.mkdir(parents=True, exist_ok=True)
    constraints = ", ".join(f'["{a}", "{b}"]' for a, b in CONSTRAINTS)
    (root / "config.toml").write_text(f"""project = "cheetah-sim"
model_type = "deeplabcut"
nesting = 1
video_extension = "mp4"

[calibration]
board_type = "charuco"
board_size = [10, 7]
board_square_side_length = 25

[filter]
enabled = false

[triangulation]
cam_regex = '_([A-Z])$'
optim = {str(optim).lower()}
score_threshold = 0.5
constraints = [{constraints}]
scale_smooth = 2

[acinoset]
fps = {fps!r}
{extra_config}""", encoding="utf-8")
    (root / "calibration").mkdir(exist_ok=True)
    write_anipose_toml(root / "calibration" / "calibration.toml", cal)
    first = next(iter(sessions))
    (root / first / "calibration").mkdir(parents=True, exist_ok=True)
    write_anipose_toml(root / first / "calibration" / "calibration.toml", cal)
    for session, trial, run in simulated_trials(sessions, frames, fps, seed):
        pose = root / session / "pose-2d"
        pose.mkdir(parents=True, exist_ok=True)
        for name, kp in zip(CAMERAS, run.keypoints):
            write_dlc_h5(pose / f"{trial}_{name}.h5", kp.bodyparts, kp.xy, kp.likelihood)
    return root
