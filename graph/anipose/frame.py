"""Anipose's output frame: ``[triangulation] axes`` and ``reference_point``, as ``anipose
triangulate`` computes it (``correct_coordinate_frame`` in lambdaloop/anipose).

``axes = [["x", "a", "b"], ["z", "c", "d"]]`` asks that the direction from bodypart ``a`` to ``b``
be the output's x and from ``c`` to ``d`` its z. With ``med(p)`` the median over the frames where
``p`` has an estimate:

* each listed axis row ``M[k] += (med(b) - med(a)) / |med(b) - med(a)|`` (rows of one axis add up);
* with ``k1, k2`` the first two axes named, the third row is ``M[k1] x M[k2]`` when (k1, k2) is
  (x, y), (z, x) or (y, z), else ``M[k2] x M[k1]`` (a right-handed triple);
* every row scaled to unit length (rows are not made orthogonal: Anipose does not);
* ``center = med(M X_ref)`` over the reference point's frames, and the output ``X' = M X - center``.
"""

from __future__ import annotations

import numpy as np

from graph.errors import InputError

AXIS = {"x": 0, "y": 1, "z": 2}


def _median(positions: np.ndarray, j: int, name: str) -> np.ndarray:
    p = positions[:, j]
    p = p[np.isfinite(p[:, 0])]
    if not len(p):
        raise InputError(f"[triangulation] axes / reference_point: {name} has no estimate in any frame")
    return np.median(p, axis=0)


def anipose_frame(positions: np.ndarray, markers: list[str], axes,
                  reference_point: str) -> tuple[np.ndarray, np.ndarray]:
    """``(M, center)`` of Anipose's frame for ``positions`` (N, M, 3); see the module docstring."""
    index = {m: j for j, m in enumerate(markers)}
    for name in [reference_point, *(p for spec in axes for p in spec[1:3])]:
        if name not in index:
            raise InputError(f"[triangulation] axes / reference_point name {name!r}, not a bodypart of the trial")
    X = np.asarray(positions, dtype=np.float64)
    M = np.zeros((3, 3))
    named: list[int] = []
    for spec in axes:
        if len(spec) != 3 or spec[0] not in AXIS:
            raise InputError(f"[triangulation] axes entries are [\"x|y|z\", bodypart, bodypart], not {spec!r}")
        k = AXIS[spec[0]]
        d = _median(X, index[spec[2]], spec[2]) - _median(X, index[spec[1]], spec[1])
        M[k] += d / np.linalg.norm(d)
        if k not in named:
            named.append(k)
    if len(named) < 2:
        raise InputError("[triangulation] axes must name two different axes")
    a, b = named[:2]
    c = 3 - a - b
    M[c] = np.cross(M[a], M[b]) if (a, b) in ((0, 1), (2, 0), (1, 2)) else np.cross(M[b], M[a])
    M /= np.linalg.norm(M, axis=1)[:, None]
    center = _median(X @ M.T, index[reference_point], reference_point)
    return M, center
