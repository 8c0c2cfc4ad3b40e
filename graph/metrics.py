"""How good is an estimate: 3D error against the truth, reprojection error, NRMSE, PCK and the
calibration of its uncertainty.

C cameras, N frames, M markers. Missing values are NaN and are left out of every statistic (each
result says how many values it used).

* 3D error of marker m in frame n: ``e_nm = |X_nm - X*_nm|`` (Euclidean, metres; reported in mm).
* Reprojection RMSE over the set S of observed (camera, frame, marker)::

      RMSE = sqrt( (1/|S|) sum_S |u_cnm - z_cnm|^2 )        (pixels)

* NRMSE (the AcinoSet paper's normalised reprojection error): each residual is divided by the
  square root of the area ``A_cn = (max u - min u)(max v - min v)`` of the bounding box of the
  reference points of camera c in frame n, so that near and far cameras count alike::

      NRMSE = sqrt( (1/|S|) sum_S |u_cnm - z_cnm|^2 / A_cn )

* PCK (percentage of correct keypoints, as AcinoSet's ``residual_error``): a reprojected marker is
  correct when ``|u_cnm - z_cnm| < s * d_cn``, where ``d_cn`` is the nose-to-eye distance in the
  reference points of camera c, frame n (``l_eye``, or ``r_eye`` where ``l_eye`` is missing) and
  ``s`` a scale (1 by default).
* Calibration of a per-axis 3D standard deviation ``sigma_nma`` (axis a = x, y, z) against the
  truth: ``z_nma = (X_nma - X*_nma) / sigma_nma``. A calibrated sigma gives ``z ~ N(0, 1)``: 68.3 %
  of ``|z| <= 1``, 95.4 % of ``|z| <= 2``, median ``|z|`` 0.674, RMS ``z`` 1 (see
  :func:`uncertainty_calibration`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from graph.camera import Calibration


@dataclass
class PositionError:
    """3D error against the truth. ``per_frame`` is (N, M) in metres, NaN where either is missing."""

    markers: list[str]
    per_frame: np.ndarray
    mean_mm: float
    median_mm: float
    rmse_mm: float
    p90_mm: float
    max_mm: float
    per_marker_mean_mm: dict[str, float]
    per_marker_median_mm: dict[str, float]
    coverage: float  # share of true (frame, marker) values that have an estimate
    count: int

    def to_dict(self) -> dict:
        return {"mean_mm": self.mean_mm, "median_mm": self.median_mm, "rmse_mm": self.rmse_mm,
                "p90_mm": self.p90_mm, "max_mm": self.max_mm, "coverage": self.coverage, "count": self.count,
                "per_marker_mean_mm": self.per_marker_mean_mm, "per_marker_median_mm": self.per_marker_median_mm}


@dataclass
class ReprojectionError:
    """Reprojection error against reference 2D points."""

    rmse_px: float
    nrmse: float
    median_px: float
    per_camera_rmse_px: list[float]
    per_marker_rmse_px: dict[str, float]
    count: int


@dataclass
class PCK:
    """Share of reprojected markers within ``scale`` nose-to-eye lengths of the reference."""

    overall: float
    per_marker: dict[str, float]
    per_camera: list[float]
    table: np.ndarray  # (C, M): share correct per camera and marker, NaN where nothing to judge
    scale: float
    count: int


@dataclass
class UncertaintyCalibration:
    """How well per-axis 3D standard deviations describe the actual errors (per axis: x, y, z).

    A calibrated estimate has ``within_1sigma`` near 0.683, ``within_2sigma`` near 0.954,
    ``median_abs_z`` near 0.674 and ``rms_z`` near 1; smaller shares (larger z) mean the stated
    sigma is too small (overconfident), larger shares too large. ``nll`` is the mean Gaussian
    negative log-likelihood per coordinate in nats with lengths in millimetres (lower is better;
    it rewards sigmas that are both small and honest).
    """

    within_1sigma: float  # share of coordinates with |error| <= sigma, all axes together
    within_2sigma: float
    within_1sigma_axis: list[float]  # the same per axis (x, y, z)
    within_2sigma_axis: list[float]
    median_abs_z: float
    rms_z: float
    rms_z_axis: list[float]
    nll: float
    rmse_mm: float  # RMS error per coordinate, for scale
    rms_sigma_mm: float  # RMS stated sigma per coordinate
    count: int  # coordinates judged

    def to_dict(self) -> dict:
        return {"within_1sigma": self.within_1sigma, "within_2sigma": self.within_2sigma,
                "within_1sigma_axis": self.within_1sigma_axis, "within_2sigma_axis": self.within_2sigma_axis,
                "median_abs_z": self.median_abs_z, "rms_z": self.rms_z, "rms_z_axis": self.rms_z_axis,
                "nll": self.nll, "rmse_mm": self.rmse_mm, "rms_sigma_mm": self.rms_sigma_mm, "count": self.count}


@dataclass
class Evaluation:
    """One solved run judged against a simulated one's truth (see :func:`evaluate`)."""

    method: str
    position: PositionError
    reprojection_truth: ReprojectionError  # against the true projections: accuracy in pixels
    reprojection_detections: ReprojectionError  # against the inlier detections: fit to the data
    pck: PCK
    seconds: float
    notes: list[str] = field(default_factory=list)

    def row(self) -> dict:
        """The numbers a summary table shows."""
        return {"method": self.method, "mean_mm": self.position.mean_mm, "median_mm": self.position.median_mm,
                "p90_mm": self.position.p90_mm, "coverage": self.position.coverage,
                "reproj_rmse_px": self.reprojection_detections.rmse_px,
                "reproj_rmse_truth_px": self.reprojection_truth.rmse_px,
                "nrmse": self.reprojection_truth.nrmse, "pck": self.pck.overall, "seconds": self.seconds}


def _stat(values: np.ndarray, fn) -> float:
    values = values[np.isfinite(values)]
    return float(fn(values)) if values.size else float("nan")


def position_error(estimate: np.ndarray, truth: np.ndarray, markers: list[str]) -> PositionError:
    """3D error of ``estimate`` (N, M, 3) against ``truth`` (N, M, 3), both metres."""
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if estimate.shape != truth.shape:
        raise ValueError(f"estimate {estimate.shape} and truth {truth.shape} differ in shape")
    e = np.linalg.norm(estimate - truth, axis=-1)  # NaN where either is missing
    mm = e * 1000.0
    have_truth = np.isfinite(truth).all(axis=-1)
    count = int(np.isfinite(e).sum())
    return PositionError(
        markers=list(markers), per_frame=e,
        mean_mm=_stat(mm, np.mean), median_mm=_stat(mm, np.median),
        rmse_mm=_stat(mm, lambda v: np.sqrt(np.mean(v**2))), p90_mm=_stat(mm, lambda v: np.percentile(v, 90)),
        max_mm=_stat(mm, np.max),
        per_marker_mean_mm={m: _stat(mm[:, k], np.mean) for k, m in enumerate(markers)},
        per_marker_median_mm={m: _stat(mm[:, k], np.median) for k, m in enumerate(markers)},
        coverage=count / max(int(have_truth.sum()), 1), count=count)


def uncertainty_calibration(estimate: np.ndarray, std: np.ndarray, truth: np.ndarray) -> UncertaintyCalibration:
    """Calibration of the per-axis standard deviations ``std`` of ``estimate``, both (N, M, 3) in
    metres, against ``truth`` (N, M, 3).

    Per coordinate (frame n, marker m, axis a), with ``e = X - X*`` and ``z = e / sigma``::

        within_k = (1/|S|) #{ |z| <= k },   k = 1, 2
        rms_z    = sqrt( (1/|S|) sum z^2 )
        NLL      = (1/|S|) sum [ log(sigma) + log(2 pi) / 2 + z^2 / 2 ]     (sigma in mm)

    over the set S of coordinates where estimate, sigma and truth are finite and ``sigma > 0``.
    Each axis is judged on its own (a per-axis sigma says nothing about correlations between axes).
    """
    X = np.asarray(estimate, dtype=np.float64)
    sd = np.asarray(std, dtype=np.float64)
    T = np.asarray(truth, dtype=np.float64)
    if not (X.shape == sd.shape == T.shape) or X.shape[-1:] != (3,):
        raise ValueError(f"estimate {X.shape}, std {sd.shape} and truth {T.shape} must all be (N, M, 3)")
    e = (X - T) * 1000.0  # mm
    sigma = sd * 1000.0
    with np.errstate(invalid="ignore"):
        use = np.isfinite(e) & np.isfinite(sigma) & (sigma > 0)
    count = int(use.sum())
    if not count:
        nan = float("nan")
        return UncertaintyCalibration(nan, nan, [nan] * 3, [nan] * 3, nan, nan, [nan] * 3, nan, nan, nan, 0)
    z = np.where(use, e / np.where(use, sigma, 1.0), np.nan)
    az = np.abs(z)

    def share(k, axis=None):
        if axis is None:
            return float((az[use] <= k).mean())
        u = use[..., axis]
        return float((az[..., axis][u] <= k).mean()) if u.any() else float("nan")

    def rms(v, m):
        return float(np.sqrt(np.mean(v[m] ** 2))) if m.any() else float("nan")

    nll = np.log(sigma[use]) + 0.5 * np.log(2 * np.pi) + 0.5 * z[use] ** 2
    return UncertaintyCalibration(
        within_1sigma=share(1.0), within_2sigma=share(2.0),
        within_1sigma_axis=[share(1.0, a) for a in range(3)], within_2sigma_axis=[share(2.0, a) for a in range(3)],
        median_abs_z=float(np.median(az[use])), rms_z=rms(z, use),
        rms_z_axis=[rms(z[..., a], use[..., a]) for a in range(3)],
        nll=float(nll.mean()), rmse_mm=rms(e, use), rms_sigma_mm=rms(sigma, use), count=count)


def bounding_box_area(points: np.ndarray) -> np.ndarray:
    """Area (px^2) of the bounding box of the finite points (..., M, 2) over M; NaN if none."""
    p = np.asarray(points, dtype=np.float64)
    with warnings.catch_warnings():  # all-NaN slices give NaN, which is the answer
        warnings.simplefilter("ignore", RuntimeWarning)
        w = np.nanmax(p[..., 0], axis=-1) - np.nanmin(p[..., 0], axis=-1)
        h = np.nanmax(p[..., 1], axis=-1) - np.nanmin(p[..., 1], axis=-1)
    return w * h


def reprojection_error(reprojections: np.ndarray, reference: np.ndarray, markers: list[str],
                       mask: np.ndarray | None = None, box_reference: np.ndarray | None = None) -> ReprojectionError:
    """Reprojection RMSE and NRMSE of ``reprojections`` (C, N, M, 2) against ``reference`` (C, N, M, 2).

    ``mask`` (C, N, M) limits the set S (default: where both are finite). The NRMSE boxes come
    from ``box_reference`` (default ``reference``), over all its finite markers in that frame.
    """
    u = np.asarray(reprojections, dtype=np.float64)
    z = np.asarray(reference, dtype=np.float64)
    if u.shape != z.shape:
        raise ValueError(f"reprojections {u.shape} and reference {z.shape} differ in shape")
    r2 = ((u - z) ** 2).sum(axis=-1)  # (C, N, M)
    use = np.isfinite(r2)
    if mask is not None:
        use &= np.asarray(mask, dtype=bool)
    area = bounding_box_area(z if box_reference is None else box_reference)  # (C, N)
    norm = r2 / np.where(area > 0, area, np.nan)[..., None]
    count = int(use.sum())

    def rms(x, m):
        return float(np.sqrt(np.mean(x[m]))) if m.any() else float("nan")

    nuse = use & np.isfinite(norm)
    return ReprojectionError(
        rmse_px=rms(r2, use), nrmse=rms(norm, nuse),
        median_px=float(np.median(np.sqrt(r2[use]))) if count else float("nan"),
        per_camera_rmse_px=[rms(r2[c], use[c]) for c in range(r2.shape[0])],
        per_marker_rmse_px={m: rms(r2[:, :, k], use[:, :, k]) for k, m in enumerate(markers)},
        count=count)


def nose_to_eye_px(points: np.ndarray, markers: list[str]) -> np.ndarray:
    """The PCK length ``d_cn`` (C, N): nose to ``l_eye`` (``r_eye`` where ``l_eye`` is missing) in
    ``points`` (C, N, M, 2). Raises ValueError if the markers lack a nose or both eyes."""
    idx = {m: k for k, m in enumerate(markers)}
    if "nose" not in idx or not ({"l_eye", "r_eye"} & idx.keys()):
        raise ValueError("PCK needs the markers nose and l_eye or r_eye")
    p = np.asarray(points, dtype=np.float64)
    nose = p[..., idx["nose"], :]
    eye = p[..., idx["l_eye"], :] if "l_eye" in idx else np.full_like(nose, np.nan)
    if "r_eye" in idx:
        eye = np.where(np.isfinite(eye).all(axis=-1, keepdims=True), eye, p[..., idx["r_eye"], :])
    return np.linalg.norm(nose - eye, axis=-1)


def pck(reprojections: np.ndarray, reference: np.ndarray, markers: list[str], scale: float = 1.0,
        mask: np.ndarray | None = None) -> PCK:
    """PCK of ``reprojections`` (C, N, M, 2) against ``reference`` (C, N, M, 2), threshold ``scale``
    times the reference's nose-to-eye length in that camera and frame. Cases where the threshold,
    the reference or the reprojection is missing are not judged."""
    u = np.asarray(reprojections, dtype=np.float64)
    z = np.asarray(reference, dtype=np.float64)
    d = np.linalg.norm(u - z, axis=-1)  # (C, N, M)
    thr = scale * nose_to_eye_px(z, markers)  # (C, N)
    judged = np.isfinite(d) & np.isfinite(thr)[..., None] & (thr[..., None] > 0)
    if mask is not None:
        judged &= np.asarray(mask, dtype=bool)
    correct = judged & (d < thr[..., None])

    def share(c, j):
        n = int(j.sum())
        return float(c.sum() / n) if n else float("nan")

    C, _, M = d.shape
    table = np.array([[share(correct[c, :, k], judged[c, :, k]) for k in range(M)] for c in range(C)])
    return PCK(overall=share(correct, judged),
               per_marker={m: share(correct[:, :, k], judged[:, :, k]) for k, m in enumerate(markers)},
               per_camera=[share(correct[c], judged[c]) for c in range(C)], table=table, scale=scale,
               count=int(judged.sum()))


def align_markers(names: list[str], positions: np.ndarray, want: list[str]) -> np.ndarray:
    """``positions`` (N, len(names), 3) reordered to ``want``; NaN for names it lacks."""
    idx = {m: k for k, m in enumerate(names)}
    out = np.full(positions.shape[:1] + (len(want),) + positions.shape[2:], np.nan)
    for k, m in enumerate(want):
        if m in idx:
            out[:, k] = positions[:, idx[m]]
    return out


def evaluate(result, run, likelihood_threshold: float | None = None) -> Evaluation:
    """Judge a :class:`graph.api.Result` against the :class:`graph.simulate.SimulatedRun` it solved.

    The 3D error and PCK use the run's markers (matched by name). The reprojection error against
    the detections counts the inlier detections (no simulated outlier, swap or dropout) above the
    likelihood threshold (default: the one the solve used), the same set for every method.
    """
    markers = list(run.markers)
    est = align_markers(list(result.markers), np.asarray(result.positions), markers)
    pos = position_error(est, run.positions, markers)
    C = len(run.keypoints)
    reproj = np.stack([align_markers(list(result.markers), np.asarray(result.reprojections[c]), markers)
                       for c in range(C)])
    truth_uv = run.projections
    thr = result.options.likelihood_threshold if likelihood_threshold is None else likelihood_threshold
    det = np.stack([k.xy for k in run.keypoints])
    lik = np.stack([k.likelihood for k in run.keypoints])
    inlier = (lik >= thr) & ~run.outlier & ~run.swapped & ~run.dropout & np.isfinite(det).all(axis=-1)
    notes = []
    try:
        score = pck(reproj, truth_uv, markers)
    except ValueError as e:
        score = PCK(float("nan"), {}, [], np.zeros((0, 0)), 1.0, 0)
        notes.append(str(e))
    return Evaluation(
        method=result.method, position=pos,
        reprojection_truth=reprojection_error(reproj, truth_uv, markers),
        reprojection_detections=reprojection_error(reproj, det, markers, mask=inlier, box_reference=truth_uv),
        pck=score, seconds=float(result.report.seconds.get("total", float("nan"))), notes=notes)


# ------------------------------------------------------------------------- leave one camera out

LOCO_CONFIDENCE = 0.9  # a held-out detection is judged when its likelihood is at least this


@dataclass
class HeldOutCamera:
    """One camera left out: the reconstruction from the others projected into it, against its own
    confident detections. ``errors`` (N, M) are the pixel distances, NaN where not judged."""

    camera: str
    median_px: float
    p90_px: float
    mean_px: float
    count: int  # confident detections with a prediction
    confident: int  # the camera's confident detections
    coverage: float  # count / confident
    seconds: float  # the reconstruction's wall time
    per_marker_median_px: dict[str, float]
    errors: np.ndarray
    warnings: list[str] = field(default_factory=list)  # what the reconstruction warned of
    # the share of judged detections inside the reconstruction's own 90 % prediction ellipse
    # (:func:`prediction_share`); None when the method gives no uncertainty
    within_90: float | None = None
    inside: np.ndarray | None = None  # (N, M) that test: 1 inside, 0 outside, NaN where not made

    def to_dict(self) -> dict:
        return {"camera": self.camera, "median_px": self.median_px, "p90_px": self.p90_px, "mean_px": self.mean_px,
                "count": self.count, "confident": self.confident, "coverage": self.coverage,
                "seconds": self.seconds, "per_marker_median_px": self.per_marker_median_px,
                "warnings": self.warnings, "within_90": self.within_90}


@dataclass
class LeaveOneCameraOut:
    """Leave-one-camera-out prediction error (:func:`leave_one_camera_out`): per held-out camera and
    over all of them pooled (every judged detection of every camera counts once)."""

    method: str
    confidence: float
    markers: list[str]
    cameras: list[HeldOutCamera]
    median_px: float
    p90_px: float
    mean_px: float
    count: int
    coverage: float
    seconds: float  # all the reconstructions together
    notes: list[str] = field(default_factory=list)
    within_90: float | None = None  # pooled share inside the 90 % prediction ellipse (None: no uncertainty)

    def to_dict(self) -> dict:
        return {"method": self.method, "confidence": self.confidence, "median_px": self.median_px,
                "p90_px": self.p90_px, "mean_px": self.mean_px, "count": self.count, "coverage": self.coverage,
                "seconds": self.seconds, "within_90": self.within_90, "cameras": [c.to_dict() for c in self.cameras],
                "notes": self.notes}


class Reconstruction(NamedTuple):
    """What a reconstructor returns: marker names and positions (N, M, 3) in the world frame and
    units of the calibration it was given; with, when the method has them, the positions' standard
    deviations (N, M, 3, same units) and the detection noise it assumed (px), which
    :func:`prediction_share` checks against the held-out camera. A plain ``(markers, positions)``
    pair is accepted too."""

    markers: list[str]
    positions: np.ndarray
    std: np.ndarray | None = None
    sigma_px: float | None = None


# reconstruct(keypoints of the kept cameras, their calibration) -> Reconstruction or (markers, positions)
Reconstructor = Callable[[list, "Calibration"], "Reconstruction | tuple[list[str], np.ndarray]"]
PREDICTION_LEVEL = 0.9


def prediction_share(camera, positions: np.ndarray, std: np.ndarray, sigma_px: float, markers: list[str],
                     detections, judged: np.ndarray, level: float = PREDICTION_LEVEL) -> tuple[float, np.ndarray]:
    """Is the reconstruction's uncertainty honest on a recording without 3D truth? The share of the
    held-out camera's ``judged`` detections (N, M) that fall inside the ``level`` prediction ellipse
    the reconstruction implies for them, and which did (N, M: 1 inside, 0 outside, NaN where not
    tested: not judged, or no deviation to test with).

    A detection z of marker m at frame n, predicted at ``uv = pi(X)`` with ``J = d uv / d X``::

        r = z - uv,   S = J diag(std^2) J^T + sigma_px^2 I,   inside: r^T S^-1 r <= chi2_2(level) = -2 ln(1 - level)

    (the position's uncertainty carried into the image, plus the detection noise the method
    assumed for every camera; the result keeps each position's per-axis deviations, not their
    correlations). An honest method puts about ``level`` of them inside; far fewer: its deviations,
    or the noise it assumed, are too small for this rig; nearly all: too large."""
    uv, J = camera.project_with_jacobian(np.asarray(positions, dtype=np.float64))
    z = _matched_detections(detections, markers, positions.shape[0])[0]
    r = z - uv
    S = np.einsum("nmai,nmi,nmbi->nmab", J, np.square(std), J) + sigma_px ** 2 * np.eye(2)
    ok = judged & np.isfinite(r).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
    S[~ok] = np.eye(2)
    r = np.where(ok[..., None], r, 0.0)
    d2 = np.einsum("nma,nmab,nmb->nm", r, np.linalg.inv(S), r)
    inside = np.where(ok, (d2 <= -2.0 * np.log1p(-level)).astype(np.float64), np.nan)
    return (float(np.nanmean(inside)) if ok.any() else float("nan")), inside


def _matched_detections(detections, markers: list[str], frames: int) -> tuple[np.ndarray, np.ndarray]:
    """A camera's detections (N, M, 2) and likelihoods (N, M) of ``markers``, matched by bodypart
    name: NaN and 0 where it has none."""
    from graph.io.keypoints import match_bodyparts

    match = match_bodyparts(detections, markers)
    z = np.full((frames, len(markers), 2), np.nan)
    lik = np.zeros((frames, len(markers)))
    have = match.index >= 0
    z[:, have] = detections.xy[:, match.index[have]]
    lik[:, have] = np.nan_to_num(detections.likelihood[:, match.index[have]], nan=0.0)
    return z, lik


def held_out_errors(camera, positions: np.ndarray, markers: list[str], detections,
                    confidence: float = LOCO_CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Pixel distances (N, M) between ``positions`` (N, M, 3; the camera's world units) projected by
    ``camera`` and the camera's own :class:`~graph.io.keypoints.Keypoints` ``detections``, matched by
    bodypart name, where the detection's likelihood is at least ``confidence``; NaN elsewhere. Also
    the mask (N, M) of the confident detections (judged or not: a missing prediction is not judged)."""
    z, lik = _matched_detections(detections, markers, positions.shape[0])
    confident = (lik >= confidence) & np.isfinite(z).all(axis=-1)
    uv = camera.project(np.asarray(positions, dtype=np.float64))
    e = np.linalg.norm(uv - z, axis=-1)
    return np.where(confident, e, np.nan), confident


def leave_one_camera_out(keypoints: list, calibration, options=None, *, confidence: float = LOCO_CONFIDENCE,
                         reconstruct: Reconstructor | None = None, method: str | None = None,
                         judge: list | None = None, progress: Callable[[str], None] | None = None
                         ) -> LeaveOneCameraOut:
    """Judge a 3D method on a recording without 3D truth: for each camera c, reconstruct from the
    other cameras, project into c and compare with c's confident detections (likelihood at least
    ``confidence``). Needs three or more cameras (two left after one is held out).

    The error of camera c, frame n, marker m is ``e = |pi_c(X_nm) - z_cnm|`` (pixels) over the set
    of c's detections with likelihood >= ``confidence`` for which the reconstruction has a position;
    the result gives its median, 90th percentile and mean per camera and pooled over all cameras, and
    the share of the confident detections that got a position (``coverage``: a method that leaves
    hard points out scores them not at all, so compare coverages too). The markers judged are the
    reconstruction's (matched to each camera's bodyparts by name).

    By default each reconstruction is :func:`graph.api.solve` with ``options`` (its
    :class:`~graph.types.SolveOptions`, default ones if None). The calibration's units are settled
    once on the whole rig (``options.calibration_units``; two cameras alone may look like a rig in
    metres when the whole one is in millimetres) and every reconstruction is given them. Another
    method is scored the same way by passing ``reconstruct(keypoints, calibration) -> (markers,
    positions)``, which gets the kept cameras in the calibration's own units and returns positions
    in those units. ``judge`` (one :class:`~graph.io.keypoints.Keypoints` per camera, default
    ``keypoints``) are the detections each held-out camera is scored against: for instance one
    ensemble member's, to compare a method given the ensemble with methods given that member.
    Warnings a reconstruction gives are kept in its camera's ``warnings``, not raised.

    A reconstructor that returns its uncertainty (:class:`Reconstruction`; the default one does) is
    judged on it too: ``within_90``, the share of the judged detections inside the 90 % prediction
    ellipse it implies (:func:`prediction_share`): the 3D truth a simulation has, replaced by a
    camera the reconstruction did not see.
    """
    from graph.camera import CALIBRATION_UNITS, Calibration
    from graph.errors import InputError
    from graph.io.calibration import resolve_units
    from graph.io.keypoints import check_same_frames

    C = len(calibration)
    if C < 3:
        raise InputError(f"leaving one camera out needs three or more cameras; the calibration has {C}",
                         calibration.source or None)
    if len(keypoints) != C:
        raise InputError(f"{len(keypoints)} keypoint file(s) given for a calibration of {C} camera(s)",
                         calibration.source or None)
    if not 0.0 <= confidence <= 1.0:
        raise ValueError(f"confidence must be in [0, 1], not {confidence}")
    check_same_frames(keypoints)
    judge = keypoints if judge is None else judge
    if len(judge) != C:
        raise InputError(f"{len(judge)} sets of detections to judge by for {C} cameras", calibration.source or None)
    notes: list[str] = []
    if reconstruct is None:
        from dataclasses import replace

        from graph.types import SolveOptions

        options = options or SolveOptions()
        units, note = resolve_units(calibration, options.calibration_units)
        scale = CALIBRATION_UNITS[units]
        if note:
            notes.append(note)
        options = replace(options, calibration_units=units)
        reconstruct = _solver_reconstruct(options, scale)
        method = method or options.method
    method = str(method or getattr(reconstruct, "__name__", "reconstruct"))

    held: list[HeldOutCamera] = []
    markers: list[str] | None = None
    for c in range(C):
        keep = [i for i in range(C) if i != c]
        name = calibration.names[c]
        if progress:
            progress(f"camera {c + 1}/{C} ({name}) held out")
        sub = Calibration(cameras=[calibration.cameras[i] for i in keep], source=calibration.source,
                          metadata=dict(calibration.metadata))
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:  # kept with the camera they came from
            warnings.simplefilter("always")
            out = reconstruct([keypoints[i] for i in keep], sub)
        seconds = time.perf_counter() - t0
        names, positions = out[0], out[1]
        said = list(dict.fromkeys(str(w.message) for w in caught))
        markers = list(names) if markers is None else markers
        positions = align_markers(list(names), np.asarray(positions, dtype=np.float64), markers)
        e, confident = held_out_errors(calibration.cameras[c], positions, markers, judge[c], confidence)
        n_conf = int(confident.sum())
        share, inside = None, None
        std, sigma_px = (out[2], out[3]) if len(out) > 3 else (None, None)
        if std is not None and sigma_px is not None:
            std = align_markers(list(names), np.asarray(std, dtype=np.float64), markers)
            share, inside = prediction_share(calibration.cameras[c], positions, std, sigma_px, markers, judge[c],
                                             np.isfinite(e))
        held.append(HeldOutCamera(
            camera=name, median_px=_stat(e, np.median), p90_px=_stat(e, lambda v: np.percentile(v, 90)),
            mean_px=_stat(e, np.mean), count=int(np.isfinite(e).sum()), confident=n_conf,
            coverage=float(np.isfinite(e).sum() / n_conf) if n_conf else float("nan"), seconds=seconds,
            per_marker_median_px={m: _stat(e[:, k], np.median) for k, m in enumerate(markers)}, errors=e,
            warnings=said, within_90=share, inside=inside))
    pooled = np.concatenate([h.errors.ravel() for h in held])
    n_conf = sum(h.confident for h in held)
    count = int(np.isfinite(pooled).sum())
    insides = [h.inside for h in held if h.inside is not None]
    return LeaveOneCameraOut(
        method=method, confidence=confidence, markers=markers or [], cameras=held,
        median_px=_stat(pooled, np.median), p90_px=_stat(pooled, lambda v: np.percentile(v, 90)),
        mean_px=_stat(pooled, np.mean), count=count, coverage=count / n_conf if n_conf else float("nan"),
        seconds=float(sum(h.seconds for h in held)), notes=notes,
        within_90=(float(np.nanmean(np.concatenate([i.ravel() for i in insides])))
                   if count and len(insides) == len(held) else None))


def _solver_reconstruct(options, scale: float) -> Reconstructor:
    """:func:`graph.api.solve` with ``options`` as a reconstructor: positions back in the
    calibration's units (``scale`` metres per unit)."""
    from graph.api import solve

    def reconstruct(keypoints, calibration):
        result = solve(keypoints, calibration, options)
        return Reconstruction(list(result.markers), np.asarray(result.positions) / scale,
                              np.asarray(result.std) / scale, float(result.report.sigma_px))

    return reconstruct


@dataclass
class LocoDifference:
    """``b`` minus ``a`` on the same held-out detections (:func:`loco_difference`): the pooled median
    and 90th percentile of ``b`` less those of ``a`` (px; negative: ``b`` predicts better) with 95 %
    intervals from a moving-block bootstrap over frames."""

    median_px: float
    median_interval: tuple[float, float]
    p90_px: float
    p90_interval: tuple[float, float]
    share_b_p90_lower: float  # the share of the resamples in which b's p90 was below a's
    block_frames: int
    blocks: int  # runs of block_frames frames a resample; few (under ~30) give too narrow intervals
    resamples: int
    count: int  # detections both judged

    def to_dict(self) -> dict:
        return {"median_px": self.median_px, "median_interval": list(self.median_interval), "p90_px": self.p90_px,
                "p90_interval": list(self.p90_interval), "share_b_p90_lower": self.share_b_p90_lower,
                "block_frames": self.block_frames, "blocks": self.blocks, "resamples": self.resamples,
                "count": self.count}


def decorrelation_lag(series: np.ndarray, max_lag: int) -> int:
    """The first lag ``k >= 1`` at which the sample autocorrelation of ``series`` lies within the
    white-noise band ``+-2 / sqrt(n)``, at most ``max_lag``: frames that far apart are about
    independent, so blocks that long keep the dependence a bootstrap must not break."""
    x = np.asarray(series, dtype=np.float64)
    x = x[np.isfinite(x)] - np.nanmean(x)
    n = x.size
    denom = float(x @ x)
    if n < 3 or denom <= 0:
        return 1
    band = 2.0 / np.sqrt(n)
    for k in range(1, min(max_lag, n - 1) + 1):
        if abs(float(x[:-k] @ x[k:]) / denom) <= band:
            return k
    return max(1, min(max_lag, n - 1))


def loco_difference(a: LeaveOneCameraOut, b: LeaveOneCameraOut, resamples: int = 2000,
                    seed: int = 0) -> LocoDifference:
    """How much better or worse ``b`` predicts the held-out cameras than ``a`` on the same recording,
    and how sure that is.

    The statistic is ``D = q(e_b) - q(e_a)`` for the pooled median and 90th percentile ``q`` over the
    detections both judged. Errors are correlated within a frame (all cameras and markers share one
    pose) and across neighbouring frames (a smoother's error drifts), so resampling detections one
    by one would give intervals far too narrow. The moving-block bootstrap (Kunsch 1989) resamples
    runs of ``L`` consecutive frames with every camera and marker in them, both methods together
    (paired), ``ceil(N / L)`` runs a resample; the interval is the resamples' 2.5 and 97.5 %
    quantiles of ``D``. ``L`` is :func:`decorrelation_lag` of the per-frame mean difference
    ``mean_cm(e_b - e_a)``, at most ``N / 10``. Both must judge the same recording (same frames).

    The intervals are only as good as the number of runs ``N / L`` is large: on simulated drifting
    errors of two equally good methods (an AR(1) drift of coefficient 0.95) the 95 % interval held
    0 in 90-93 % of 2000-frame recordings (about 40 runs of 48 frames), but in 72 % of 600-frame ones
    (16 runs); ``blocks`` says how many there were."""
    A = np.stack([h.errors for h in a.cameras])  # (C, N, M)
    B = np.stack([h.errors for h in b.cameras])
    if A.shape != B.shape:
        raise ValueError(f"the two scores judged different detections ({A.shape} and {B.shape})")
    both = np.isfinite(A) & np.isfinite(B)
    A = np.where(both, A, np.nan).transpose(1, 0, 2).reshape(A.shape[1], -1)  # (N, C*M)
    B = np.where(both, B, np.nan).transpose(1, 0, 2).reshape(B.shape[1], -1)
    N = A.shape[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames nobody judged
        per_frame = np.nanmean(B - A, axis=1)
    L = decorrelation_lag(per_frame, max(1, N // 10))

    def stats(rows: np.ndarray) -> tuple[float, float]:
        a_, b_ = A[rows].ravel(), B[rows].ravel()
        ok = np.isfinite(a_)
        if not ok.any():
            return float("nan"), float("nan")
        a_, b_ = a_[ok], b_[ok]
        return (float(np.median(b_) - np.median(a_)),
                float(np.percentile(b_, 90) - np.percentile(a_, 90)))

    d_median, d_p90 = stats(np.arange(N))
    rng = np.random.default_rng(seed)
    runs = int(np.ceil(N / L))
    draws = np.empty((resamples, 2))
    offsets = np.arange(L)
    for r in range(resamples):
        starts = rng.integers(0, N - L + 1, runs)
        draws[r] = stats((starts[:, None] + offsets).ravel()[:N])
    lo, hi = np.nanpercentile(draws, [2.5, 97.5], axis=0)
    return LocoDifference(median_px=d_median, median_interval=(float(lo[0]), float(hi[0])), p90_px=d_p90,
                          p90_interval=(float(lo[1]), float(hi[1])),
                          share_b_p90_lower=float(np.mean(draws[:, 1] < 0)), block_frames=L, blocks=runs,
                          resamples=resamples, count=int(both.sum()))


class GroupError(NamedTuple):
    """Several individuals' estimates against several animals' truth (:func:`group_error`)."""

    match: list[int]  # the animal each individual is, by its whole run (-1: none)
    switches: int  # frames in which an individual is nearer another animal than in its last frame
    animal_frames: int  # individual-frames with an estimate
    errors: list[PositionError | None]  # each individual's error against its animal (None: matched to none)

    @property
    def switches_per_10k(self) -> float:
        return 1e4 * self.switches / max(self.animal_frames, 1)


def group_error(estimates: np.ndarray, truth: np.ndarray, markers: list[str]) -> GroupError:
    """Estimates (I, N, M, 3) of I individuals against A animals' truth (N, A, M, 3).

    Each frame, individual ``i`` is the animal nearest it (median marker distance); a 3D identity
    switch is a frame in which that animal differs from the one of its last frame with an estimate.
    The run's match (individual to animal) is the assignment with the least summed median distance
    (Hungarian method); each individual's :class:`PositionError` is against its matched animal."""
    from scipy.optimize import linear_sum_assignment

    count = estimates.shape[0]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmedian(np.linalg.norm(estimates[:, None] - truth.transpose(1, 0, 2, 3)[None], axis=-1), axis=-1)
        whole = np.nanmedian(d, axis=-1)  # (I, A)
    rows, cols = linear_sum_assignment(np.where(np.isfinite(whole), whole, 1e12))
    match = [-1] * count
    for r, c in zip(rows, cols):
        match[int(r)] = int(c)
    switches = frames = 0
    for i in range(count):
        have = np.isfinite(d[i]).any(axis=0)
        nearest = np.argmin(np.where(np.isfinite(d[i]), d[i], np.inf), axis=0)[have]
        frames += int(have.sum())
        switches += int((np.diff(nearest) != 0).sum())
    errors = [position_error(estimates[i], truth[:, match[i]], markers) if match[i] >= 0 else None
              for i in range(count)]
    return GroupError(match=match, switches=switches, animal_frames=frames, errors=errors)
