"""Camera calibration from board views: intrinsics per camera, then the rig by one bundle adjustment
on GTSAM, with a quality report; and refinement of a rig from the animal's keypoints.

The front door::

    board = parse_board("checkerboard:9x6:0.031")
    views = [load_views(src, board) for src in sources]            # detections JSON, image folder or video
    cam = calibrate_intrinsics(views[0], board, model="fisheye")    # IntrinsicsResult
    rig = calibrate_extrinsics(views, board)                        # RigResult (.calibration: graph.camera.Calibration)

Modules: :mod:`.board` (specs, corner geometry), :mod:`.views` (the detections JSON), :mod:`.detect`
(finding boards in images and videos, cached), :mod:`.model` (projection with Jacobians),
:mod:`.bundle` (the GTSAM bundle adjustment), :mod:`.poses` (PnP and robust starts),
:mod:`.intrinsics`, :mod:`.extrinsics`, :mod:`.refine` (from keypoints), :mod:`.report` (JSON and
figures), :mod:`.simulate` (synthetic rigs and board images with a known truth), :mod:`.cli`.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Board": "graph.calibrate.board", "parse_board": "graph.calibrate.board",
    "BoardViews": "graph.calibrate.views", "read_detections": "graph.calibrate.views",
    "load_views": "graph.calibrate.detect",
    "IntrinsicsResult": "graph.calibrate.intrinsics", "calibrate_intrinsics": "graph.calibrate.intrinsics",
    "RigResult": "graph.calibrate.extrinsics", "calibrate_extrinsics": "graph.calibrate.extrinsics",
}
_RENAMED = {"load_views": "detect_views"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    """The front door's names, imported when first used (so ``acinoset calibrate --help`` loads no
    solver)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'graph.calibrate' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), _RENAMED.get(name, name))
