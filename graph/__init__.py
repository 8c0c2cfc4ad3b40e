"""acinoset estimation library: 3D animal pose from calibrated multi-camera 2D keypoints.

The front door is :func:`graph.api.solve`; everything a caller needs is re-exported here.
"""

from graph.api import Progress, Result, SolveOptions, SolveReport, solve
from graph.errors import InputError

__version__ = "0.1.0"
__all__ = ["solve", "SolveOptions", "Result", "SolveReport", "Progress", "InputError", "__version__"]
