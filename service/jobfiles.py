"""A job's files: where its inputs and results lie in the data dir, and how they travel to an RQ worker.

Job input layout (``<data dir>/jobs/<id>/input``), named by :data:`MANIFEST`::

    manifest.json                      {"keypoints": [...], "calibration": ..., "skeleton": ..., "options": {...}}
    keypoints/01/<uploaded name>.csv   one directory per camera, in the calibration's order
    calibration/<uploaded name>.toml
    skeleton/<uploaded name>.toml      optional

Result files (``<data dir>/jobs/<id>/result``): :data:`RESULT_FILES`, one per download format.

Both sides use it: the API stores uploads in this layout and serves results from it, the workers read
and write it (for RQ, as zip archives in Redis under :func:`input_key` and :func:`result_key`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path, PurePosixPath

MANIFEST = "manifest.json"
RESULT_FILES: dict[str, tuple[str, str]] = {  # download format: (file in the job's result dir, media type)
    "csv": ("result.csv", "text/csv"),
    "h5": ("result.h5", "application/x-hdf5"),
    "json": ("result.json", "application/json"),
    "report": ("report.json", "application/json"),
}


def read_manifest(input_dir: Path) -> dict:
    return json.loads((input_dir / MANIFEST).read_text())


def inside(base: Path, rel: str) -> Path:
    """``base / rel`` where ``rel`` is a relative POSIX path that stays inside ``base``."""
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts or not p.parts:
        raise ValueError(f"bad path in job manifest: {rel!r}")
    return base.joinpath(*p.parts)


def input_key(token: str) -> str:
    """Redis key of the input files of the RQ job ``token``."""
    return f"acinoset:input:{token}"


def result_key(token: str) -> str:
    """Redis key of the result files of the RQ job ``token``."""
    return f"acinoset:result:{token}"


def pack_files(base: Path, rels: list[str]) -> bytes:
    """Files under ``base`` as one zip archive (deflate, fast level), names relative to ``base``."""
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for rel in rels:  # one compress call per file (the GIL is released while it runs)
            z.writestr(rel, inside(base, rel).read_bytes())
    return buf.getvalue()


def unpack_files(archive: bytes, base: Path, allowed: tuple[str, ...] | None = None) -> list[str]:
    """Extract :func:`pack_files`' archive under ``base`` (names that would leave it are refused;
    with ``allowed``, other names are skipped). Returns the names extracted."""
    import io
    import zipfile

    names = []
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        for info in z.infolist():
            if info.is_dir() or (allowed is not None and info.filename not in allowed):
                continue
            p = inside(base, info.filename)
            p.parent.mkdir(parents=True, exist_ok=True)
            with z.open(info) as src, open(p, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
            names.append(info.filename)
    return names


def input_archive(input_dir: Path) -> bytes:
    """What an RQ worker needs to run a job: the manifest and the input files, zipped."""
    m = read_manifest(input_dir)
    rels = [MANIFEST, *m["keypoints"], m["calibration"], *([m["skeleton"]] if m.get("skeleton") else [])]
    return pack_files(input_dir, rels)
