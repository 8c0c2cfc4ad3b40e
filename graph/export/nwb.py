"""NWB (``.nwb``) with the ndx-pose extension, as neuroscience archives (DANDI) take pose data.

Layout (``pip install 'acinoset[export]'``: pynwb and ndx-pose >= 0.4)::

    general/devices/<camera>               ndx_pose.CalibratedCamera per camera: intrinsic_matrix K,
                                           rotation_matrix R, translation_vector t (X_c = R X_w + t,
                                           metres), distortion_coefficients; the model in description
    processing/behavior/Skeletons/<name>   ndx_pose.Skeleton: nodes = markers, edges = bones (indices)
    processing/behavior/PoseEstimation     ndx_pose.PoseEstimation, linked to the skeleton, with one
        <marker>                           PoseEstimationSeries per marker: data (N, 3) x, y, z in
                                           metres ("meters"), rate = fps, reference_frame the
                                           calibration's world frame; no ``confidence``
    processing/behavior/PoseEstimationSD   BehavioralTimeSeries: per marker a TimeSeries ``<marker>``
                                           (N, 3), the posterior standard deviation of x, y, z in
                                           metres. It is an sd, not a confidence in [0, 1], so it is
                                           kept beside the series and not in their ``confidence``.

Positions are stored as float64 (ndx-pose's float32 is the minimum the schema asks for).

One of several individuals solved together (its H5 names it) is one NWB file, as NWB holds one
subject a file and movement writes them: ``subject`` is a ``pynwb.file.Subject`` whose
``subject_id`` is the individual's name, and the file's ``identifier`` is that name too, which
movement's ``load_poses.from_nwb_file`` takes for the individual's (``xarray.merge`` of the files
gives the group).
"""

from __future__ import annotations

import uuid
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from graph import __version__
from graph.export.base import ExportInput, Format, require


def reference_frame(run: ExportInput) -> str:
    cal = run.calibration
    where = f" ({cal.source})" if cal is not None and cal.source else ""
    return (f"the world frame of the cameras' calibration{where}, in which each camera maps a world point "
            "X to X_c = R X + t (R, t in its CalibratedCamera); origin and axes are the calibration's; metres")


def write(path: str | Path, run: ExportInput, session_description: str | None = None,
          session_start_time: datetime | None = None, identifier: str | None = None) -> None:
    pynwb = require("pynwb", "pynwb")
    ndx_pose = require("ndx_pose", "ndx-pose")
    if not hasattr(ndx_pose, "CalibratedCamera"):
        from graph.errors import InputError

        raise InputError("this export needs ndx-pose >= 0.4 (CalibratedCamera): pip install 'acinoset[export]'")
    from pynwb.behavior import BehavioralTimeSeries

    res = run.result
    X = np.asarray(res.positions, dtype=np.float64)
    sd = np.asarray(res.std, dtype=np.float64)
    who = f" of {run.individual}" if run.individual else ""
    nwb = pynwb.NWBFile(
        session_description=session_description or f"3D pose{who} ({res.skeleton}) by acinoset {res.method}"
                                                   f"{' from ' + run.source if run.source else ''}",
        identifier=identifier or run.individual or str(uuid.uuid4()),
        session_start_time=session_start_time or datetime.now(timezone.utc),
        subject=pynwb.file.Subject(subject_id=run.individual, description="one of several individuals solved "
                                   "together by acinoset") if run.individual else None,
    )
    if run.calibration is not None:
        for cam, name in zip(run.calibration.cameras, run.calibration.names):
            nwb.add_device(ndx_pose.CalibratedCamera(
                name=name, description=f"{cam.model} camera, {cam.size[0]}x{cam.size[1]} px; distortion "
                f"coefficients {cam.camera_model.summary}",
                intrinsic_matrix=cam.K, rotation_matrix=cam.R, translation_vector=cam.t,
                distortion_coefficients=cam.dist))
    else:
        for name in res.camera_names:
            nwb.create_device(name=name, description="camera (its calibration was not in the result file)")

    index = {name: j for j, name in enumerate(res.markers)}
    edges = np.array([[index[a], index[b]] for a, b in res.bones if a in index and b in index],
                     dtype=np.uint8 if len(res.markers) <= 256 else np.uint16).reshape(-1, 2)
    skeleton = ndx_pose.Skeleton(name=res.skeleton, nodes=list(res.markers), edges=edges)
    frame = reference_frame(run)
    series = [ndx_pose.PoseEstimationSeries(
        name=name, description=f"{name}: x, y, z of the marker, NaN where there is no estimate",
        data=X[:, j], unit="meters", reference_frame=frame, rate=float(res.fps), starting_time=0.0)
        for j, name in enumerate(res.markers)]
    pose = ndx_pose.PoseEstimation(
        name="PoseEstimation", pose_estimation_series=series,
        description=f"acinoset {res.method} ({res.skeleton} skeleton) from {len(res.camera_names)} calibrated "
                    f"cameras ({', '.join(res.camera_names)}); per-marker sd in PoseEstimationSD",
        scorer=f"acinoset_{res.method}", source_software="acinoset", source_software_version=__version__,
        skeleton=skeleton)
    sds = BehavioralTimeSeries(name="PoseEstimationSD")
    for j, name in enumerate(res.markers):
        sds.create_timeseries(name=name, data=sd[:, j], unit="meters", rate=float(res.fps), starting_time=0.0,
                              description=f"{name}: posterior standard deviation of x, y, z (metres), "
                                          "the square roots of the diagonal of its 3x3 marginal covariance")
    behavior = nwb.create_processing_module(name="behavior", description="3D pose estimated by acinoset")
    behavior.add(ndx_pose.Skeletons(skeletons=[skeleton]))
    behavior.add(pose)
    behavior.add(sds)
    with pynwb.NWBHDF5IO(str(path), mode="w") as io:
        io.write(nwb)


FORMAT = Format("nwb", ".nwb", "application/x-hdf5", "NWB",
                "Neurodata Without Borders with ndx-pose: markers, skeleton, cameras' calibration, sd", write,
                needs=("pynwb", "ndx_pose"))
