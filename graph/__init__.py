"""acinoset estimation library: 3D animal pose from calibrated multi-camera 2D keypoints.

The front door is :func:`graph.api.solve`; everything a caller needs is re-exported here. The
re-exports load on first use, so that ``import graph`` (and the command line's ``--help``) stays
quick: the solvers import gtsam and the compiled kernels.
"""

__version__ = "0.1.0"  # the one place: pyproject.toml reads it from here

_EXPORTS = {"solve": "graph.api", "SolveOptions": "graph.types", "Result": "graph.types",
            "SolveReport": "graph.types", "Progress": "graph.types", "InputError": "graph.errors"}
__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'graph' has no attribute {name!r}")
