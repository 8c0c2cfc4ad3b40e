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

from graph.calibrate.board import Board, parse_board
from graph.calibrate.detect import detect_views as load_views
from graph.calibrate.extrinsics import RigResult, calibrate_extrinsics
from graph.calibrate.intrinsics import IntrinsicsResult, calibrate_intrinsics
from graph.calibrate.views import BoardViews, read_detections

__all__ = ["Board", "BoardViews", "IntrinsicsResult", "RigResult", "calibrate_extrinsics", "calibrate_intrinsics",
           "load_views", "parse_board", "read_detections"]
