"""Export a solved run to the formats other tools read: NWB (ndx-pose), OpenSim TRC, C3D, EKS's CSV.

The front door is :func:`export`::

    from graph.export import export
    export("run.h5", "nwb", "run.nwb")                       # or a Result in memory
    export(result, "trc", "run.trc", axes="opensim", calibration=cal)

One module per format (:mod:`.nwb`, :mod:`.trc`, :mod:`.c3d`, :mod:`.csv_var`), each with
``write(path, run, **options)`` taking an :class:`ExportInput`, and a :class:`Format` saying once its
name, file extension, media type, label, help line and optional libraries. :data:`REGISTRY` collects
them, and the command line (:mod:`.cli`) and the REST service read it: a new format is its module,
its name in the import of the modules and in :data:`REGISTRY` below, and a test
(``docs/recipe-export-format.md``). NWB and C3D need libraries that are not part of the base install
(``pip install acinoset[export]``); without them the export fails with one line naming the extra.
"""

from __future__ import annotations

import functools
from pathlib import Path

from graph.camera import Calibration
from graph.errors import InputError
from graph.export import c3d, csv_var, nwb, trc
from graph.export.base import ExportInput, Format, load_input
from graph.types import Result

__all__ = ["REGISTRY", "FORMATS", "EXTENSIONS", "ExportInput", "Format", "available", "export", "load_input"]


def _registry(*formats: Format) -> dict[str, Format]:
    names = [f.name for f in formats]
    if len(set(names)) != len(names):
        raise ValueError(f"two export formats share a name: {names}")
    return {f.name: f for f in formats}


# every format, in the order they are offered (command line choices, downloads, buttons)
REGISTRY: dict[str, Format] = _registry(nwb.FORMAT, trc.FORMAT, c3d.FORMAT, csv_var.FORMAT)
FORMATS: tuple[str, ...] = tuple(REGISTRY)
EXTENSIONS: dict[str, str] = {name: f.extension for name, f in REGISTRY.items()}


@functools.lru_cache(maxsize=None)
def available(format: str) -> bool:
    """Whether this install can write ``format`` (its libraries are installed; nothing is imported;
    looked up once per process)."""
    import importlib.util

    return format in REGISTRY and all(importlib.util.find_spec(m) is not None for m in REGISTRY[format].needs)


def export(source: str | Path | Result, format: str, out: str | Path, *,
           calibration: str | Path | Calibration | None = None, individual: str | None = None,
           **options) -> Path:
    """Write the run ``source`` (a result H5 written by ``graph.io.results.write_h5``, or a :class:`Result`)
    to ``out`` in ``format`` (one of :data:`FORMATS`). ``calibration`` (a file or a
    :class:`Calibration`) overrides the one stored in the H5; the per-format ``options`` are the
    keyword arguments of its ``write`` (:attr:`Format.options`); ``individual`` names the one to write
    of a file of several (``graph.io.results.write_group_h5``). Returns ``out`` as a Path."""
    if format not in REGISTRY:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, not {format!r}")
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError("the output folder does not exist", out)
    REGISTRY[format].write(out, load_input(source, calibration, individual), **options)
    return out
