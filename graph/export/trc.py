"""OpenSim's marker file, TRC (``.trc``), as OpenSim's ``TRCFileAdapter`` reads and writes it.

Tab-separated. Five header lines, a blank line, then one row per frame::

    PathFileType  4  (X/Y/Z)  run.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    120.0     120.0       500        20          m      120.0         1                   500
    Frame#  Time  nose  <tab><tab>  r_eye ...            (each marker name, then two empty cells)
    <tab><tab>  X1  Y1  Z1  X2  Y2  Z2 ...
    <blank>
    1  0.0  x  y  z  x  y  z ...                          (Frame# from 1, Time = (Frame# - 1) / rate)

Positions in metres (OpenSim's unit), in the calibration's world frame rotated by ``axes``
(:func:`graph.export.base.axes_matrix`; ``opensim`` turns a z-up world into OpenSim's y-up).
A marker without an estimate in a frame has three empty cells, which OpenSim reads as NaN.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graph.export.base import ExportInput, Format, axes_matrix

UNITS_SCALE = {"m": 1.0, "mm": 1000.0}


def write(path: str | Path, run: ExportInput, axes: str | None = None, units: str = "m") -> None:
    """``X_out = A X_world`` (``A`` from ``axes``), scaled to ``units`` (``m``, OpenSim's, or ``mm``)."""
    if units not in UNITS_SCALE:
        raise ValueError(f"TRC units must be one of {', '.join(UNITS_SCALE)}, not {units!r}")
    res = run.result
    A = axes_matrix(axes)
    X = np.asarray(res.positions, dtype=np.float64) @ A.T * UNITS_SCALE[units]
    n, m = X.shape[:2]
    rate = f"{float(res.fps):g}"
    lines = [
        "\t".join(["PathFileType", "4", "(X/Y/Z)", Path(path).name]),
        "\t".join(["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
                   "OrigDataStartFrame", "OrigNumFrames"]),
        "\t".join([rate, rate, str(n), str(m), units, rate, "1", str(n)]),
        "\t".join(["Frame#", "Time"] + [f"{name}\t\t" for name in res.markers]).rstrip("\t"),
        "\t".join(["", ""] + [f"{a}{j + 1}" for j in range(m) for a in "XYZ"]),
        "",
    ]
    flat = X.reshape(n, 3 * m)
    for i in range(n):
        cells = ["" if not np.isfinite(v) else repr(float(v)) for v in flat[i]]
        lines.append("\t".join([str(i + 1), repr(i / float(res.fps))] + cells))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


FORMAT = Format("trc", ".trc", "text/plain", "TRC", "OpenSim marker file, metres", write)
