"""A calibration job's run, in the worker's process: :func:`run_calibration` (the API side, which
takes the uploads and queues the job, is :mod:`service.core.calibrations`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from service.store import READING, WRITING, jobfiles
from service.store.jobfiles import inside, read_manifest


def run_calibration(input_dir: Path, out_dir: Path, progress) -> dict:
    """Calibrate the rig from the job's detections (or videos) and write its files into ``out_dir``
    (:data:`service.store.jobfiles.CALIBRATION_FILES`; the scene JSON only for fisheye cameras: the format
    holds no other); returns the report (:meth:`graph.calibrate.RigResult.to_dict`) as plain JSON,
    the job's summary."""
    from graph.calibrate import calibrate_extrinsics, parse_board, read_detections
    from graph.calibrate.detect import detect_views
    from graph.calibrate.report import write_figures
    from graph.io.calibration import SCENE_JSON_MODEL, write_acinoset_json, write_anipose_toml
    from graph.io.cameras import load_camera_json
    from graph.types import Progress, jsonable

    progress.report(READING, 0.0)
    m = read_manifest(input_dir)
    if m.get("refine"):
        return run_refine(input_dir, m, out_dir, progress)
    opts = m["options"]
    board = parse_board(opts["board"])
    if m.get("videos"):  # the board found in every ``every``-th frame, the progress per video
        n = len(m["videos"])

        def detecting(i: int) -> Callable[[int, int], None]:
            return lambda done, total: progress(Progress("detect", (i + done / max(total, 1)) / n))

        views = [detect_views(inside(input_dir, rel), board, every=opts.get("every", 1), cache=False,
                              name=f"cam{i + 1}", progress=detecting(i))
                 for i, rel in enumerate(m["videos"])]
    else:
        views = [read_detections(inside(input_dir, rel), board, name=f"cam{i + 1}")
                 for i, rel in enumerate(m["detections"])]
    intrinsics = [load_camera_json(str(inside(input_dir, rel))) for rel in m.get("intrinsics", [])] or None
    result = calibrate_extrinsics(views, board, intrinsics, model=opts["model"], origin=opts["origin"],
                                  progress=lambda stage, fraction: progress(Progress(stage, fraction)),
                                  lens=opts.get("lens", "full"))  # calibrations queued before lenses: full
    progress.report(WRITING, 1.0, result.iterations)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_anipose_toml(out_dir / "calibration.toml", result.calibration)
    if opts["model"] == SCENE_JSON_MODEL:
        try:
            write_acinoset_json(out_dir / "scene.json", result.calibration)
        except ValueError:  # cameras of several resolutions: AcinoSet's scene holds one
            pass
    report = jsonable(result.to_dict())
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    write_figures(result, out_dir, board)
    return {**report, "files": jobfiles.written_outputs(out_dir)}



def run_refine(input_dir: Path, m: dict, out_dir: Path, progress) -> dict:
    """A refinement (:meth:`service.core.calibrations.CalibrationService.submit_refine`): the rig of its
    manifest refined from the keypoints (:func:`graph.calibrate.refine.refine_rig`); writes
    ``calibration.toml`` (the rig to use: the refined one, or the old when the check kept it),
    ``report.json`` and ``rig.png`` (the cameras before and after); returns the report."""
    from graph.calibrate.refine import refine_rig
    from graph.calibrate.report import refine_figure
    from graph.io.calibration import load_calibration, write_anipose_toml
    from graph.io.keypoints import read_keypoints
    from graph.types import Progress, jsonable

    r, opts = m["refine"], m["options"]
    calibration = load_calibration(inside(input_dir, r["calibration"]))
    keypoints = [read_keypoints(inside(input_dir, rel), individual=r.get("individual")) for rel in r["keypoints"]]
    progress(Progress("refine", 0.1))
    result = refine_rig(calibration, keypoints, opts["likelihood"], tuple(opts["refine_intrinsics"]),
                        opts["focal_sd"], opts["k1_sd"], opts["pose_sd"])
    progress.report(WRITING, 1.0)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_anipose_toml(out_dir / "calibration.toml", result.calibration)
    report = jsonable({**result.to_dict(), "refined_from": r["job"]})
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    refine_figure(calibration, result, out_dir / "rig.png")
    return {**report, "files": jobfiles.written_outputs(out_dir)}
