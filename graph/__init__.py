"""acinoset estimation library: 3D animal pose from calibrated multi-camera 2D keypoints.

The front door is :func:`graph.api.solve`; everything a caller needs is re-exported here. The
re-exports load on first use, so that ``import graph`` (and the command line's ``--help``) stays
quick: the solvers import gtsam and the compiled kernels.
"""

import os

__version__ = "0.1.0"  # the one place: pyproject.toml reads it from here

# LLVM's optimisation level for every kernel compiled in this process, unless the user set one: set here,
# before any module of the package imports numba (numba builds its code generator when it is imported).
# Level 1 gives the same numbers bit for bit and as fast a solve as numba's default 3, in three quarters of
# the compile time (graph.compiled)
os.environ.setdefault("NUMBA_OPT", "1")

_EXPORTS = {"solve": "graph.api", "SolveOptions": "graph.types", "Result": "graph.types",
            "SolveReport": "graph.types", "Progress": "graph.types", "InputError": "graph.errors"}
__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'graph' has no attribute {name!r}")
