"""What every exporter is given (:class:`ExportInput`) and declares (:class:`Format`), and the shared
pieces: the optional libraries, the axes of the output frame, and the per-marker pixel error turned
into a length."""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from graph.camera import Calibration
from graph.errors import InputError
from graph.types import Result

EXPORTED = ("positions", "std", "residuals", "outlier")  # the per-frame arrays the exporters read


@dataclass
class ExportInput:
    """A solved run and the rig it was solved with (metres; None when unknown)."""

    result: Result
    calibration: Calibration | None = None
    source: str = ""  # the file it came from, for descriptions
    individual: str | None = None  # whose result, of several individuals solved together


@dataclass(frozen=True)
class Format:
    """One export format, declared once by its module (``FORMAT = Format(...)``) and read by everything
    that offers it: :func:`graph.export.export`, ``acinoset export``, the REST API's downloads and the
    job page (through the API's list of formats).

    ``write(path, run, **options)`` writes ``run`` (an :class:`ExportInput`) to ``path``; its keyword
    parameters after those two are the format's :attr:`options`. ``extension`` is the file-name
    suffix with its dot, and may hold several parts (``.var.csv``): a job's export is kept as
    ``result`` + extension beside its own ``result.csv``, ``result.h5`` and ``result.json``, so it
    must be none of those. ``needs`` are the importable names of the optional libraries the writer
    imports (the ``export`` extra); without them the format is not :func:`graph.export.available`.
    """

    name: str  # what --format and ?format= take: "nwb"
    extension: str  # ".nwb"
    media_type: str  # "application/x-hdf5"
    label: str  # a short name, as on a button: "NWB"
    help: str  # one line: what the file holds, for whom
    write: Callable[..., None]
    needs: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.extension.startswith(".") or len(self.extension) < 2:
            raise ValueError(f"{self.name}: extension must start with a dot, not {self.extension!r}")

    @property
    def options(self) -> dict[str, Any]:
        """The keyword options of :attr:`write` and their defaults (``inspect.Parameter.empty`` for none)."""
        params = list(inspect.signature(self.write).parameters.values())[2:]
        return {p.name: p.default for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def load_input(source: str | Path | Result, calibration: str | Path | Calibration | None = None,
               individual: str | None = None) -> ExportInput:
    """A result H5 (with the rig stored in it, if any; of a file of several individuals, the one
    named) or a :class:`Result`, plus an explicit calibration file or object, which wins over the
    stored one."""
    from graph.io.calibration import in_metres, load_calibration
    from graph.io.results import read_calibration, read_individual, read_result

    stored = None
    if isinstance(source, Result):
        result, name = source, ""
    else:
        result, name = read_result(source, individual=individual, arrays=EXPORTED), Path(source).name
        stored = read_calibration(source)
        individual = individual or read_individual(source)
    if calibration is not None:
        cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
        stored, _ = in_metres(cal, result.options.calibration_units)
        if len(stored) != len(result.camera_names):
            raise InputError(f"has {len(stored)} cameras, the result {len(result.camera_names)}",
                             calibration if not isinstance(calibration, Calibration) else None)
    return ExportInput(result=result, calibration=stored, source=name, individual=individual)


def require(module: str, package: str):
    """Import an optional library or fail with one line naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise InputError(f"this export needs {package}, which is not installed: "
                         "pip install 'acinoset[export]'") from None


# ---------------------------------------------------------------------------------------- axes

AXES_PRESETS = {
    # the calibration's frame as it is
    "xyz": "x,y,z",
    # OpenSim's y-up from a z-up world: a rotation of -90 degrees about x, (x, y, z) -> (x, z, -y)
    "opensim": "x,z,-y",
}


def axes_matrix(spec: str | None) -> np.ndarray:
    """The rotation ``A`` (3x3) with ``X_out = A X_world`` from ``"x,z,-y"`` (each output axis as a
    signed world axis) or a preset (:data:`AXES_PRESETS`). A mirror (det -1) is refused: it would
    turn left into right."""
    text = AXES_PRESETS.get((spec or "xyz").strip().lower(), spec or "")
    parts = [p.strip().lower() for p in text.split(",")]
    A = np.zeros((3, 3))
    try:
        if len(parts) != 3:
            raise ValueError
        for row, p in enumerate(parts):
            sign = -1.0 if p.startswith("-") else 1.0
            A[row, "xyz".index(p.lstrip("+-"))] = sign
    except ValueError:
        raise ValueError(f"axes must be three signed world axes such as x,z,-y (or one of "
                         f"{', '.join(AXES_PRESETS)}), not {spec!r}") from None
    if not np.allclose(A @ A.T, np.eye(3)) or np.linalg.det(A) < 0:
        raise ValueError(f"axes {spec!r} is not a rotation (each axis once, determinant +1)")
    return A


def error_as_length(run: ExportInput) -> np.ndarray | None:
    """Each marker's reprojection error as a distance at the marker (N, M), metres, or None without
    a calibration.

    For camera ``c`` with the marker at depth ``Z_c`` (along the optical axis) and focal length
    ``f_c = (fx + fy) / 2``, a pixel residual ``r`` is ``r Z_c / f_c`` metres across the ray (to
    first order; exact for an undistorted camera at the image centre). Averaged over the cameras
    whose detection the estimate used (not rejected, above the likelihood threshold), as
    ``Result.error`` averages pixels. NaN where no camera was used.
    """
    cal = run.calibration
    res = run.result
    if cal is None:
        return None
    X = np.asarray(res.positions, dtype=np.float64)  # (N, M, 3)
    dist = []
    for c, cam in enumerate(cal.cameras):
        Z = X @ cam.R[2] + cam.t[2]
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        dist.append(np.asarray(res.residuals[c], dtype=np.float64) * Z / f)
    d = np.where(np.asarray(res.outlier, dtype=bool), np.nan, np.stack(dist))
    with np.errstate(invalid="ignore"):
        cnt = np.isfinite(d).sum(0)
        return np.where(cnt > 0, np.nansum(d, 0) / np.maximum(cnt, 1), np.nan)
