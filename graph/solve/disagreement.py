"""A camera that disagrees with the others: each camera's detections against the other cameras' 3D.

A camera whose calibration entry is wrong (another camera's copied in, another session's), or whose
keypoint file is another camera's, puts its detections far from where the rest of the rig says they
are. The robust loss rejects most of them, but not all, and with three cameras a faulty one can take
the estimate with it wherever the two others do not both see a marker. This module names it.

The check, for each camera ``c`` (a cheap stand-in for a leave-one-out solve per camera):

* ``X_{-c}``: every sampled point triangulated from the other cameras alone, with the robust
  triangulation (:func:`graph.solve.triangulate.robust_points`: the best of the all-view and pairwise
  candidates under a Cauchy cost, then Cauchy IRLS);
* its held-out error ``e_c``: the median over ``c``'s valid detections of ``|pi_c(X_{-c}) - z_c|``, px;
* how well the others agree among themselves, ``a_c``: the noise :func:`graph.solve.noise.scatter_px`
  measures on their own residuals at ``X_{-c}`` (each scaled by ``sqrt(n / (n - 3))`` for the three
  coordinates the point took), times the Rayleigh median ``sqrt(2 ln 2)``: the median length of a
  2D residual of that noise.

Camera ``c`` is named when ``e_c >= FLOOR_PX`` and ``e_c >= RATIO * r_c``, the reference ``r_c``
the larger of ``a_c`` and the median of the other cameras' held-out errors. It takes four cameras or
more: with three, each camera's "others" are a pair, and two views agree with each other about
anything (one degree of freedom a point), so a good camera can look as far off as the faulty one.
Measured (bench/bench_sleap_loco.py): on SLEAP's minimal session, whose calibration entry for
``side`` is a copy of ``top``'s, ``side`` sits 97 px from the others' estimate, 7.3 times the
reference (13 px; the other cameras 12-24 px held out, 0.5-1.8 times theirs); with ``mid`` left
out, three cameras, ``side`` was 96 px and ``top`` 60 px against the others' agreement of 4 and
1 px: both would have been named. On the AcinoSet rig simulated (six cameras, 5 px noise, 10 %
outliers) every camera is 7-8 px held out, at most 1.2 times its reference.

Cost: ``C`` triangulations of at most :data:`MAX_POINTS` points (frames taken evenly through the run).
:func:`worth_checking` decides from a solve's own residuals, for free, whether to pay it: only when
some camera has a share of its detections rejected, or a median residual, well above the others'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.camera import Calibration
from graph.solve.noise import RAYLEIGH_MEDIAN, scatter_px, triangulation_dof
from graph.solve.triangulate import robust_points

FLOOR_PX = 15.0  # a camera nearer than this to the others' estimate is not called out, whatever the ratio
RATIO = 4.0  # held-out error over the reference beyond which a camera disagrees
MAX_POINTS = 3000  # frame x marker points triangulated per camera left out
GATE_REJECTED = 0.1  # a camera with this share of its detections rejected by the robust loss is checked
GATE_RATIO = 2.0  # ... and one whose median residual is this many times the median of the others'
MIN_CAMERAS = 4


@dataclass(frozen=True)
class CameraAgreement:
    """One camera against the others: ``held_out_px`` (``e_c``), ``agreement_px`` (``a_c``, the
    others' among themselves), ``reference_px`` (``r_c``) and ``count`` detections judged; NaN
    where nothing could be judged."""

    camera: str
    held_out_px: float
    agreement_px: float
    reference_px: float
    count: int

    @property
    def disagrees(self) -> bool:
        return bool(self.held_out_px >= FLOOR_PX and self.held_out_px >= RATIO * self.reference_px)


def _sample(frames: int, markers: int, max_points: int) -> np.ndarray:
    """At most ``max_points // markers`` frames, evenly through the run."""
    n = max(1, min(frames, max_points // max(markers, 1)))
    return np.unique(np.linspace(0, frames - 1, n).round().astype(np.int64))


def camera_agreement(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
                     max_points: int = MAX_POINTS) -> list[CameraAgreement]:
    """:class:`CameraAgreement` of each camera from detections ``meas`` (N, C, M, 2), ``valid`` (N, C, M),
    the triangulation's Cauchy scale ``sigma_px``. Needs :data:`MIN_CAMERAS` (else: empty)."""
    N, C, M, _ = meas.shape
    if C < MIN_CAMERAS:
        return []
    rows = _sample(N, M, max_points)
    meas, valid = meas[rows], valid[rows]
    n = meas.shape[0]
    held, agree, counts = np.full(C, np.nan), np.full(C, np.nan), np.zeros(C, dtype=np.int64)
    for c in range(C):
        keep = [i for i in range(C) if i != c]
        others = Calibration(cameras=[calibration.cameras[i] for i in keep])
        X, _, used = robust_points(others, meas[:, keep], valid[:, keep], sigma_px)
        flat = X.reshape(-1, 3)
        judged = valid[:, c] & np.isfinite(X).all(-1)
        if judged.any():
            uv = calibration.cameras[c].project(flat).reshape(n, M, 2)
            e = np.linalg.norm(uv - meas[:, c], axis=-1)[judged]
            e = e[np.isfinite(e)]
            counts[c] = e.size
            held[c] = float(np.median(e)) if e.size else np.nan
        views = used.reshape(n, M, len(keep)).sum(-1)  # (n, M) views each point was triangulated from
        dof = triangulation_dof(views)
        res = [np.where(used.reshape(n, M, len(keep))[..., j],
                        np.linalg.norm(calibration.cameras[i].project(flat).reshape(n, M, 2) - meas[:, i], axis=-1),
                        np.nan) * dof for j, i in enumerate(keep)]
        agree[c] = scatter_px(np.stack(res)) * RAYLEIGH_MEDIAN
    out = []
    for c in range(C):
        others_held = np.delete(held, c)
        others_held = others_held[np.isfinite(others_held)]
        reference = agree[c]
        if others_held.size >= 2:
            reference = float(np.nanmax([reference, np.median(others_held)]))
        out.append(CameraAgreement(camera=calibration.names[c], held_out_px=float(held[c]),
                                   agreement_px=float(agree[c]), reference_px=float(reference),
                                   count=int(counts[c])))
    return out


def worth_checking(residuals_px: np.ndarray, outlier: np.ndarray) -> bool:
    """Whether a solve's residuals (C, N, M, px; NaN where no detection was used) and rejections
    (C, N, M) hint at a disagreeing camera: a camera with :data:`GATE_REJECTED` of its detections
    rejected, or a median residual :data:`GATE_RATIO` times the median of the others' and at
    least half :data:`FLOOR_PX`."""
    r = np.asarray(residuals_px, dtype=np.float64)
    C = r.shape[0]
    if C < MIN_CAMERAS:
        return False
    seen = np.isfinite(r).sum(axis=(1, 2))
    rejected = (np.asarray(outlier) & np.isfinite(r)).sum(axis=(1, 2)) / np.maximum(seen, 1)
    if np.any((seen > 0) & (rejected >= GATE_REJECTED)):
        return True
    medians = np.array([np.median(r[c][np.isfinite(r[c])]) if seen[c] else np.nan for c in range(C)])
    for c in range(C):
        rest = np.delete(medians, c)
        rest = rest[np.isfinite(rest)]
        if np.isfinite(medians[c]) and rest.size and medians[c] >= max(0.5 * FLOOR_PX, GATE_RATIO * np.median(rest)):
            return True
    return False


def disagreement_warning(named: list[CameraAgreement], agreements: list[CameraAgreement]) -> str:
    """The one-line warning naming the cameras ``named`` (of ``agreements``), with how far off each is."""
    rest = [a for a in agreements if a not in named and np.isfinite(a.held_out_px)]
    lo, hi = (min(a.held_out_px for a in rest), max(a.held_out_px for a in rest)) if rest else (np.nan, np.nan)
    others = f", the other cameras {lo:.0f}-{hi:.0f} px from theirs" if rest else ""
    if len(named) == 1:
        a = named[0]
        return (f"camera {a.camera} disagrees with the others: its detections sit {a.held_out_px:.0f} px (median) "
                f"from where the other cameras' 3D projects into it{others}; likely causes: its calibration entry "
                f"(another camera's copied in, another session's) or a keypoint file of another camera; solve "
                f"without it to compare")
    which = ", ".join(f"{a.camera} ({a.held_out_px:.0f} px)" for a in named)
    return (f"cameras {which} disagree with the others: their detections sit that far (median) from where the other "
            f"cameras' 3D projects into them{others}; likely causes: their calibration entries (another camera's "
            f"copied in, another session's) or keypoint files of other cameras; solve without them to compare")


def check(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
          max_points: int = MAX_POINTS) -> tuple[list[CameraAgreement], str | None]:
    """The cameras that disagree (:attr:`CameraAgreement.disagrees`) and the warning naming them
    (None: none does)."""
    agreements = camera_agreement(calibration, meas, valid, sigma_px, max_points)
    named = [a for a in agreements if a.disagrees]
    return named, (disagreement_warning(named, agreements) if named else None)


CHI2_2_90 = -2.0 * float(np.log(0.1))  # chi^2 with 2 degrees of freedom at 0.9: the 90 % ellipse's radius^2


def held_out_noise(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
                   share: float = 0.9, max_points: int = MAX_POINTS) -> float:
    """The detection noise (px per coordinate) that a held-out camera accepts: the smallest ``sigma``
    at which ``share`` of each camera's detections fall inside the 90 % ellipse its prediction from
    the other cameras gives, pooled over the cameras (NaN with fewer than three cameras).

    For camera ``c``, ``X_{-c}`` triangulated from the others with information ``H`` (px^-2 m^2 per
    unit weight, :func:`graph.solve.triangulate.robust_points`: covariance ``sigma^2 H^-1``) and
    ``J = d pi_c / d X`` there, a detection ``z`` is predicted as ``N(pi_c(X_{-c}), sigma^2 A)``,
    ``A = J H^-1 J^T + I``: inside the ellipse when ``q = e^T A^-1 e <= sigma^2 chi2_2(0.9)``,
    ``e = z - pi_c(X_{-c})``. So ``sigma`` is ``sqrt(quantile_share(q) / chi2_2(0.9))``. Unlike the
    scatter of a fit's residuals (which sees only how the cameras agree about the estimate they make
    together), a camera's own errors (its calibration, its detector's bias) are in ``e``."""
    N, C, M, _ = meas.shape
    if C < 3:
        return float("nan")
    rows = _sample(N, M, max_points)
    meas, valid = meas[rows], valid[rows]
    qs = []
    for c in range(C):
        keep = [i for i in range(C) if i != c]
        others = Calibration(cameras=[calibration.cameras[i] for i in keep])
        X, H, _ = robust_points(others, meas[:, keep], valid[:, keep], sigma_px)
        X, H = X.reshape(-1, 3), H.reshape(-1, 3, 3)
        z = meas[:, c].reshape(-1, 2)
        judged = valid[:, c].ravel() & np.isfinite(X).all(-1)
        if not judged.any():
            continue
        uv, J = calibration.cameras[c].project_with_jacobian(X[judged])
        with np.errstate(all="ignore"):
            A = J @ np.linalg.pinv(H[judged]) @ np.swapaxes(J, -1, -2) + np.eye(2)
            e = z[judged] - uv
            ok = np.isfinite(e).all(-1) & np.isfinite(A).all(axis=(-1, -2))
            q = np.einsum("ki,kij,kj->k", e[ok], np.linalg.inv(A[ok]), e[ok])
        qs.append(q[np.isfinite(q)])
    q = np.concatenate(qs) if qs else np.zeros(0)
    if q.size < 10:
        return float("nan")
    return float(np.sqrt(np.quantile(q, share) / CHI2_2_90))
