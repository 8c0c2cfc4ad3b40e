"""Where the tests read real recordings and calibrations: the shared data folder, never a copy in the project.

``SHARED_DATA`` is ``$ACINOSET_SHARED_DATA`` when set; otherwise the first ``shared/data`` folder
beside the project root or beside one of its ancestors (for a checkout at ``/x/acinoset``:
``/x/shared/data``, then ``/shared/data``), so that a clone or worktree elsewhere with the data
beside it finds it too. With none found it is ``<project root>/../shared/data``, which does not exist.

Tests that can do without a recording skip when it is absent (:func:`needs`); the calibration
tests read :data:`ACINOSET_CALIB` unconditionally and fail without it.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _shared_data() -> Path:
    given = os.environ.get("ACINOSET_SHARED_DATA")
    if given:
        return Path(given).expanduser().resolve()
    found = (base / "shared" / "data" for base in ROOT.parents)
    return next((p for p in found if p.is_dir()), ROOT.parent / "shared" / "data")


SHARED_DATA = _shared_data()
ACINOSET_CALIB = SHARED_DATA / "acinoset_calib"  # AcinoSet's public board detections and calibrations
EKS_FLY = SHARED_DATA / "eks_fly"  # the EKS repository's tethered fly: 3 cameras, Anipose calibration in mm
SLEAP_MINIMAL = SHARED_DATA / "sleap_minimal"  # SLEAP's minimal multi-camera session: one mouse, 4 cameras
ACINOSET_RIG = SHARED_DATA / "acinoset_2019_rig.json"  # AcinoSet's 2019 six-camera rig


def needs(path: Path) -> pytest.MarkDecorator:
    """Skip the test (or module, as ``pytestmark``) when ``path`` of the shared data is absent."""
    return pytest.mark.skipif(not path.exists(), reason=f"needs the shared data's {path.name} ({path})")
