"""acinoset's 3D uncertainty against the Ensemble Kalman Smoother (EKS) on the same simulated runs.

    eks-venv/bin/python bench/bench_eks.py [--frames 500] [--seeds 3] [--members 5] [--repeats 3]
                                           [--no-fisheye]

EKS (``ensemble-kalman-smoother`` on PyPI, ``import eks``) pins ``jax<=0.4.36`` and
``dynamax<=1.0.1``, so it runs in a virtualenv of its own, not the project's (from the repository
root; aniposelib without its opencv-contrib dependency, which would put a second cv2 over
opencv-python-headless)::

    python3 -m venv eks-venv && eks-venv/bin/pip install -e .
    eks-venv/bin/pip install --no-deps aniposelib ensemble-kalman-smoother
    eks-venv/bin/pip install 'jax<=0.4.36' jaxlib 'dynamax<=1.0.1' optax pandas scikit-learn \\
        'python-fasthtml<=0.12.50' sleap_io toml tqdm joblib

What runs. Each seed is one simulated cheetah run on the AcinoSet rig (6 fisheye cameras, 120 fps,
5 px noise, 10 % confident outliers of sigma 100 px; bench/harness.py). EKS is made for an ensemble
of pose models, so each run is observed ``--members`` times: the same truth, each detection set with
its own noise and outliers (``simulate_run(..., seed=s, noise_seed=k)``). Then:

* EKS, ``eks.multicam_smoother.ensemble_kalman_smoother_multicam`` with an aniposelib
  ``CameraGroup`` (its nonlinear path: a 3D random-walk state per keypoint, each model's detections
  triangulated and averaged for the start, the ensemble median in every view as the observation and
  the ensemble variance, weighted by the mean likelihood, as its noise; the process-noise scale
  fitted per keypoint by maximum likelihood; an extended Kalman smoother; per-axis posterior
  variances), on all the members, every option at its default. EKS's projection in that path is a
  pinhole camera with OpenCV's radial-tangential distortion: it has no fisheye model. So EKS gets
  the detections undistorted (exactly, with the rig's fisheye model) into pinhole cameras with the
  same intrinsics and poses and no distortion (``EKS, undistorted``); ``EKS, fisheye as given`` is
  what the rig's own calibration gives it (aniposelib ``FisheyeCamera``s, whose 4 coefficients
  EKS reads as pinhole ones). A detection missing from a member (a marker outside an image) goes
  to EKS as DeepLabCut would write one: a position with a low likelihood (that member's previous
  detection of the marker in that camera, or the next one at the start; likelihood 0.01).
* acinoset ``fte`` (``SolveOptions(method="fte")``), with the ``cheetah`` skeleton and with
  ``points`` (every bodypart a free point, no bones: EKS has no skeleton), on (a) one member (a user
  with one DeepLabCut model), (b) the per-camera ensemble median of x and y (likelihood: the
  members' mean), which is what EKS starts from, and (c) that median with ``measurement_std_px`` set
  from the ensemble's own spread (the median of K draws has about 1.25 sigma / sqrt(K); sigma from
  the median absolute difference between members), since the default 5 px is the noise of one
  member, not of their median.

Every method is judged against the simulated truth: 3D error (:func:`graph.metrics.position_error`)
and the calibration of its per-axis 3D standard deviations
(:func:`graph.metrics.uncertainty_calibration`: share of |error| <= 1 and 2 sigma, median |z|,
RMS z, Gaussian NLL per coordinate). Timings: one untimed warm-up call of every method on a short
run first, then wall-clock and CPU seconds around the call (for EKS: undistortion, building its
``MarkerArray`` and the smoother; EKS builds and compiles its jax functions anew in every call, so
its time includes that compilation, as a user sees it; its own profile split is in the JSON).

Prints a Markdown table and writes bench/results/eks.json.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
import warnings
from importlib import metadata

import harness as h
import numpy as np

from graph.api import SolveOptions, solve
from graph.camera import undistort_points
from graph.io.keypoints import Keypoints
from graph.metrics import uncertainty_calibration
from graph.simulate import simulate_run

MISSING_LIKELIHOOD = 0.01  # what a member's missing detection gets in EKS's input


class _Profile(logging.Handler):
    """Collects EKS's own ``[profile]`` timings (debug log lines)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record):
        msg = record.getMessage()
        if "[profile]" in msg:
            self.lines.append(msg.split("[profile]", 1)[1].strip())

    def take(self) -> dict[str, float]:
        out = {}
        for line in self.lines:
            name, _, sec = line.rpartition(":")
            try:
                out[name.strip()] = float(sec.strip().rstrip("s"))
            except ValueError:
                pass
        self.lines = []
        return out


def members_of(cal, frames: int, seed: int, k: int):
    """``k`` detection sets of one simulated run (same truth, independent noise and outliers)."""
    return [simulate_run(cal, frames=frames, fps=h.TARGET["fps"], noise=h.TARGET["noise"],
                         outliers=h.TARGET["outliers"], outlier_std=h.TARGET["outlier_std"], seed=seed,
                         confident_outliers=1.0, noise_seed=i) for i in range(k)]


# ------------------------------------------------------------------------------------------- EKS


def pinhole_group(cal):
    """aniposelib pinhole cameras with the rig's intrinsics and poses and no distortion."""
    import cv2
    from aniposelib.cameras import Camera, CameraGroup

    return CameraGroup([Camera(matrix=c.K, dist=np.zeros(5), size=c.size, rvec=cv2.Rodrigues(c.R)[0].ravel(),
                               tvec=c.t, name=name) for c, name in zip(cal.cameras, cal.names)])


def to_pinhole(cam, uv: np.ndarray) -> np.ndarray:
    """Fisheye pixels (..., 2) to the pixels of the same camera without distortion."""
    xn = undistort_points(cam, uv)
    return xn @ cam.K[:2, :2].T + cam.K[:2, 2]


def _fill_missing(xy: np.ndarray, lik: np.ndarray):
    """(N, M, 2), (N, M): NaN detections take the nearest earlier (else later) detection of that
    marker, with a low likelihood, as DeepLabCut writes an unseen bodypart."""
    xy, lik = xy.copy(), lik.copy()
    miss = ~np.isfinite(xy).all(axis=-1)
    if not miss.any():
        return xy, lik
    N = xy.shape[0]
    for m in np.nonzero(miss.any(axis=0))[0]:
        ok = np.nonzero(~miss[:, m])[0]
        if ok.size == 0:
            xy[:, m] = 0.0
        else:
            prev = np.searchsorted(ok, np.arange(N), side="right") - 1
            src = ok[np.where(prev >= 0, prev, 0)]
            xy[miss[:, m], m] = xy[src[miss[:, m]], m]
        lik[miss[:, m], m] = MISSING_LIKELIHOOD
    return xy, lik


def eks_marker_array(cal, members, undistort: bool):
    """EKS's input, (models, cameras, frames, keypoints, [x, y, likelihood])."""
    from eks.marker_array import MarkerArray

    K, C = len(members), len(cal)
    N, M = members[0].frames, len(members[0].markers)
    arr = np.zeros((K, C, N, M, 3))
    for k, run in enumerate(members):
        for c, (cam, kp) in enumerate(zip(cal.cameras, run.keypoints)):
            xy = to_pinhole(cam, kp.xy) if undistort else kp.xy
            xy, lik = _fill_missing(xy, kp.likelihood)
            arr[k, c, :, :, :2] = xy
            arr[k, c, :, :, 2] = lik
    return MarkerArray(arr, data_fields=["x", "y", "likelihood"])


def run_eks(cal, members, cgroup, undistort: bool):
    """EKS's multi-camera smoother, defaults; returns positions, per-axis std (N, M, 3), s."""
    from eks.multicam_smoother import ensemble_kalman_smoother_multicam

    markers = list(members[0].markers)
    ma = eks_marker_array(cal, members, undistort)
    _, s, df3 = ensemble_kalman_smoother_multicam(ma, keypoint_names=markers, camera_names=list(cal.names),
                                                  camgroup=cgroup)
    scorer = df3.columns.get_level_values(0)[0]
    pos = np.stack([np.stack([df3[(scorer, m, a)].to_numpy() for a in "xyz"], axis=-1) for m in markers], axis=1)
    var = np.stack([np.stack([df3[(scorer, m, f"{a}_posterior_var")].to_numpy() for a in "xyz"], axis=-1)
                    for m in markers], axis=1)
    return pos, np.sqrt(np.clip(var, 0.0, None)), [float(v) for v in s]


# -------------------------------------------------------------------------------------- acinoset


def ensemble_median(cal, members) -> list[Keypoints]:
    """Per camera: the members' median x and y, their mean likelihood."""
    out = []
    for c in range(len(cal)):
        xy = np.stack([m.keypoints[c].xy for m in members])
        lik = np.stack([m.keypoints[c].likelihood for m in members])
        with warnings.catch_warnings():  # a marker no member saw stays NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(xy, axis=0)
        out.append(Keypoints(bodyparts=list(members[0].markers), xy=med, likelihood=lik.mean(axis=0),
                             source=cal.names[c]))
    return out


def ensemble_median_std_px(members) -> float:
    """The noise of the ensemble median, from the members' spread alone: the members' sigma from
    the median absolute difference of every pair of members (``x_i - x_j ~ N(0, 2 sigma^2)``, so
    ``sigma = 1.4826 median|x_i - x_j| / sqrt(2)``; robust to the outliers), times 1.2533 / sqrt(K)
    (the large-K standard deviation of a median)."""
    xy = np.stack([np.stack([kp.xy for kp in m.keypoints]) for m in members])  # (K, C, N, M, 2)
    K = len(members)
    diffs = np.concatenate([np.abs(xy[i] - xy[j]).ravel() for i in range(K) for j in range(i + 1, K)])
    sigma = 1.4826 * float(np.nanmedian(diffs)) / np.sqrt(2.0)
    return 1.2533 * sigma / np.sqrt(K)


def run_ours(cal, keypoints, skeleton: str, fps: float, measurement_std_px: float = 5.0):
    r = solve(keypoints, cal, SolveOptions(method="fte", fps=fps, skeleton=skeleton,
                                           measurement_std_px=measurement_std_px))
    return r.positions, r.std


# ------------------------------------------------------------------------------------------ main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--seeds", type=int, default=3, help="simulated runs (seeds 0..S-1)")
    ap.add_argument("--members", type=int, default=5, help="ensemble size K")
    ap.add_argument("--repeats", type=int, default=3, help="timed solves per run of each acinoset method")
    ap.add_argument("--eks-repeats", type=int, default=1, help="timed calls per run of each EKS variant")
    ap.add_argument("--no-fisheye", action="store_true", help="skip EKS on the fisheye calibration as given")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    profile = _Profile()
    for name in ("eks.multicam_smoother", "eks.core"):
        lg = logging.getLogger(name)
        lg.setLevel(logging.DEBUG)
        lg.addHandler(profile)
        lg.propagate = False

    cal = h.rig()
    info = h.machine()
    info["versions"].update({d: metadata.version(d) for d in ("ensemble-kalman-smoother", "jaxlib", "dynamax",
                                                              "optax", "pandas")})
    pin_cg = pinhole_group(cal)
    fish_cg = h.anipose_group(cal)
    # the undistorted detections and the pinhole cameras describe the same rays
    probe = members_of(cal, 20, seed=98, k=1)[0]
    pin = np.stack([to_pinhole(c, u) for c, u in zip(cal.cameras, probe.projections)])
    pin_direct = np.stack([np.asarray(cam.project(probe.positions.reshape(-1, 3))).reshape(pin.shape[1:])
                           for cam in pin_cg.cameras])
    pinhole_check_px = float(np.nanmax(np.abs(pin - pin_direct)))
    print(f"# acinoset vs EKS {info['versions']['ensemble-kalman-smoother']}: {args.frames} frames, "
          f"{args.seeds} runs, {args.members} members; {info['cpu']}, {info['cores']} cores, "
          f"load {info['load_average'][0]:.1f}; pinhole check {pinhole_check_px:.1e} px", flush=True)

    fps = h.TARGET["fps"]
    methods = {
        "EKS, undistorted": ("eks", lambda ms, ctx: run_eks(cal, ms, pin_cg, undistort=True)),
        "EKS, fisheye as given": ("eks", lambda ms, ctx: run_eks(cal, ms, fish_cg, undistort=False)),
        "acinoset fte, one member": ("ours", lambda ms, ctx: run_ours(cal, ms[0].keypoints, "cheetah", fps)),
        "acinoset fte, ensemble median": ("ours", lambda ms, ctx: run_ours(cal, ensemble_median(cal, ms),
                                                                           "cheetah", fps)),
        "acinoset fte, median, std from spread": ("ours", lambda ms, ctx: run_ours(
            cal, ensemble_median(cal, ms), "cheetah", fps, ensemble_median_std_px(ms))),
        "acinoset fte points, one member": ("ours", lambda ms, ctx: run_ours(cal, ms[0].keypoints, "points", fps)),
        "acinoset fte points, ensemble median": ("ours", lambda ms, ctx: run_ours(
            cal, ensemble_median(cal, ms), "points", fps)),
        "acinoset fte points, median, std from spread": ("ours", lambda ms, ctx: run_ours(
            cal, ensemble_median(cal, ms), "points", fps, ensemble_median_std_px(ms))),
    }
    if args.no_fisheye:
        del methods["EKS, fisheye as given"]

    # warm-up: numba kernels, jax and XLA on a short run, untimed
    small = members_of(cal, 40, seed=99, k=args.members)
    warmup_s = {}
    for name, (_, fn) in methods.items():
        w0 = time.perf_counter()
        fn(small, None)
        warmup_s[name] = time.perf_counter() - w0
    profile.take()

    per = {name: {"wall": [], "cpu": [], "errors": [], "calibration": [], "eks_profile": [], "s": [],
                  "measurement_std_px": []} for name in methods}
    for seed in range(args.seeds):
        ms = members_of(cal, args.frames, seed=seed, k=args.members)
        truth = ms[0].positions
        for name, (kind, fn) in methods.items():
            repeats = args.eks_repeats if kind == "eks" else args.repeats
            out, t = h.timed(lambda: fn(ms, None), repeats=repeats, warmup=False)
            pos, std = out[0], out[1]
            d = per[name]
            d["wall"] += t.wall
            d["cpu"] += t.cpu
            d["errors"].append(h.error_mm(pos, ms[0]))
            d["calibration"].append(uncertainty_calibration(pos, std, truth).to_dict())
            if kind == "eks":
                d["eks_profile"].append(profile.take())
                d["s"].append(out[2])
            if "spread" in name:
                d["measurement_std_px"].append(ensemble_median_std_px(ms))
            c = d["calibration"][-1]
            print(f"  seed {seed} {name:<46} {t.median:7.2f} s  mean {d['errors'][-1]['mean_mm']:6.1f} mm  "
                  f"<=1sd {c['within_1sigma']:.3f}  <=2sd {c['within_2sigma']:.3f}  NLL {c['nll']:.2f}", flush=True)

    def avg(rows, key):
        return float(np.mean([r[key] for r in rows]))

    def avg_axis(rows, key):
        return [float(v) for v in np.mean([r[key] for r in rows], axis=0)]

    summary = {}
    for name, d in per.items():
        cal_rows = d["calibration"]
        summary[name] = {
            "median_s": statistics.median(d["wall"]), "cpu_median_s": statistics.median(d["cpu"]),
            "wall_s": d["wall"], "cpu_s": d["cpu"], "warmup_s": warmup_s[name],
            "mean_mm": avg(d["errors"], "mean_mm"), "median_mm": avg(d["errors"], "median_mm"),
            "p90_mm": avg(d["errors"], "p90_mm"), "max_mm": float(np.max([e["max_mm"] for e in d["errors"]])),
            **{k: avg(cal_rows, k) for k in ("within_1sigma", "within_2sigma", "median_abs_z", "rms_z", "nll",
                                            "rmse_mm", "rms_sigma_mm")},
            **{k: avg_axis(cal_rows, k) for k in ("within_1sigma_axis", "within_2sigma_axis", "rms_z_axis")},
            "per_run": [{"error": e, "calibration": c} for e, c in zip(d["errors"], cal_rows)]}
        if d["eks_profile"]:
            summary[name]["eks_profile"] = d["eks_profile"]
            summary[name]["smooth_param"] = d["s"]
        if d["measurement_std_px"]:
            summary[name]["measurement_std_px"] = d["measurement_std_px"]

    def axes(v):
        return "/".join(f"{x:.2f}" for x in v)

    rows = [[name, s["mean_mm"], s["median_mm"], s["p90_mm"], axes(s["within_1sigma_axis"]),
             axes(s["within_2sigma_axis"]), s["median_abs_z"], s["rms_z"], s["nll"], s["rms_sigma_mm"],
             s["median_s"], s["cpu_median_s"]] for name, s in summary.items()]
    print()
    print(h.markdown_table(["method", "3D mean mm", "3D median mm", "p90 mm", "<= 1 sd x/y/z", "<= 2 sd x/y/z",
                            "median abs z", "RMS z", "NLL", "RMS sd mm", "wall s (median)", "CPU s (median)"],
                           rows))
    path = h.save("eks", {"machine": info, "args": vars(args), "protocol": h.TARGET,
                          "pinhole_check_px": pinhole_check_px, "missing_likelihood": MISSING_LIKELIHOOD,
                          "results": summary})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
