"""An ensemble of pose models as one observation per camera (as EKS takes them).

DeepLabCut users often train several networks (different seeds or shuffles) and run them all. Their
K detections of a bodypart in one camera and frame, ``z_1 .. z_K``, become one detection:

* the position: the members' median of x and of y (their mean for two members);
* the likelihood: the members' mean;
* the spread: the sample sd per coordinate about their mean,
  ``spread = sqrt( sum_k |z_k - mean z|^2 / (2 (K - 1)) )`` (px), which the combined
  :class:`~graph.io.keypoints.Keypoints` carries as ``spread_px``.

How the spread is used (:func:`relative_noise`, by :func:`graph.solve.problem.build`): members disagree
most where detection is hard, and that differs between cameras (a camera that sees the animal larger,
blurred or from an odd angle) and bodyparts. One frame's spread of two members is one draw, too noisy
to weigh that detection by, so each camera c and marker m gets its typical spread, the median over
frames ``S_cm``, and the detections of (c, m) the noise ``sigma S_cm / median(S)``: relative noise
levels from the ensemble, the overall level ``sigma`` from the options (given, or measured with
``measurement_std_px="auto"``). The members share the errors of their common training labels, which
the spread does not see; the relative weights assume those scale alike. Relative levels are kept
within [1/4, 4].
"""

from __future__ import annotations

import warnings

import numpy as np

from graph.errors import InputError
from graph.io.keypoints import Keypoints

RELATIVE_RANGE = (0.25, 4.0)


def combine(members: list[Keypoints]) -> Keypoints:
    """One camera's ensemble ``members`` (same bodyparts, same frames) as one :class:`Keypoints`
    with ``spread_px`` (module docstring). A detection missing from some members is combined from
    the others (its spread NaN when fewer than two have it)."""
    if not members:
        raise ValueError("an ensemble needs at least one member")
    first = members[0]
    for k in members[1:]:
        if list(k.bodyparts) != list(first.bodyparts):
            raise InputError("the ensemble's members name different bodyparts "
                             f"({', '.join(first.bodyparts[:4])}, ... and {', '.join(k.bodyparts[:4])}, ...)",
                             k.source or None)
        if k.frames != first.frames:
            raise InputError(f"the ensemble's members have different frame counts ({first.frames} and {k.frames})",
                             k.source or None)
    if len(members) == 1:
        return first
    xy = np.stack([k.xy for k in members])  # (K, N, M, 2)
    lik = np.stack([np.nan_to_num(k.likelihood, nan=0.0) for k in members])
    seen = np.isfinite(xy).all(axis=-1)  # (K, N, M)
    with warnings.catch_warnings():  # a detection no member has stays NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        centre = np.nanmedian(xy, axis=0)
        mean = np.nanmean(xy, axis=0)
        count = seen.sum(axis=0)
        dev2 = np.nansum(np.where(seen[..., None], (xy - mean) ** 2, 0.0), axis=(0, 3))
        spread = np.where(count >= 2, np.sqrt(dev2 / (2.0 * np.maximum(count - 1, 1))), np.nan)
    sources = "+".join(k.source for k in members if k.source)
    return Keypoints(bodyparts=list(first.bodyparts), xy=centre, likelihood=lik.mean(axis=0), scorer=first.scorer,
                     source=sources or first.source, spread_px=spread,
                     fps=first.fps if all(k.fps == first.fps for k in members) else None)


def relative_noise(spread: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """Each camera's and marker's relative detection noise (C, M) from the members' spreads
    (N, C, M; NaN where a camera has no ensemble or a member missed) over the valid detections
    (module docstring); 1 where there is no spread to judge by. None when no camera has one."""
    s = np.where(valid & np.isfinite(spread), spread, np.nan)
    if not np.isfinite(s).any():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        typical = np.nanmedian(s, axis=0)  # (C, M)
    ok = np.isfinite(typical) & (typical > 0)
    if not ok.any():
        return None
    rel = np.where(ok, typical / np.median(typical[ok]), 1.0)
    return np.clip(rel, *RELATIVE_RANGE)
