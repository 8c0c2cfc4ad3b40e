"""Export a solved run to the formats other tools read: NWB (ndx-pose), OpenSim TRC, C3D, EKS's CSV.

The front door is :func:`export`::

    from graph.export import export
    export("run.h5", "nwb", "run.nwb")                       # or a Result in memory
    export(result, "trc", "run.trc", axes="opensim", calibration=cal)

One module per format (:mod:`.nwb`, :mod:`.trc`, :mod:`.c3d`, :mod:`.csv_var`), each with
``write(path, run, **options)`` taking an :class:`ExportInput`. NWB and C3D need libraries that are
not part of the base install (``pip install acinoset[export]``); without them the export fails with
one line naming the extra.
"""

from __future__ import annotations

import functools
import importlib
from pathlib import Path

from graph.camera import Calibration
from graph.errors import InputError
from graph.export.base import ExportInput, load_input
from graph.types import Result

__all__ = ["FORMATS", "EXTENSIONS", "ExportInput", "available", "export", "load_input"]

# format -> (module, default file extension)
_MODULES: dict[str, tuple[str, str]] = {
    "nwb": ("graph.export.nwb", ".nwb"),
    "trc": ("graph.export.trc", ".trc"),
    "c3d": ("graph.export.c3d", ".c3d"),
    "csv-var": ("graph.export.csv_var", ".csv"),
}
FORMATS: tuple[str, ...] = tuple(_MODULES)
EXTENSIONS: dict[str, str] = {fmt: ext for fmt, (_, ext) in _MODULES.items()}
# the optional libraries each format needs (the ``export`` extra)
NEEDS: dict[str, tuple[str, ...]] = {"nwb": ("pynwb", "ndx_pose"), "c3d": ("ezc3d",)}


@functools.lru_cache(maxsize=None)
def available(format: str) -> bool:
    """Whether this install can write ``format`` (its libraries are installed; nothing is imported;
    looked up once per process)."""
    import importlib.util

    return format in _MODULES and all(importlib.util.find_spec(m) is not None for m in NEEDS.get(format, ()))


def export(source: str | Path | Result, format: str, out: str | Path, *,
           calibration: str | Path | Calibration | None = None, **options) -> Path:
    """Write the run ``source`` (a result H5 written by ``graph.io.results.write_h5``, or a :class:`Result`)
    to ``out`` in ``format`` (one of :data:`FORMATS`). ``calibration`` (a file or a
    :class:`Calibration`) overrides the one stored in the H5; the per-format ``options`` are the
    keyword arguments of that module's ``write``. Returns ``out`` as a Path."""
    if format not in _MODULES:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, not {format!r}")
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError("the output folder does not exist", out)
    module = importlib.import_module(_MODULES[format][0])
    module.write(out, load_input(source, calibration), **options)
    return out
