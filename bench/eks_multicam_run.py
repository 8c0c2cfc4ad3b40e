"""Run EKS's multi-camera smoother on DeepLabCut CSVs, in EKS's own virtualenv (it pins an old jax).

    eks-venv/bin/python bench/eks_multicam_run.py REQUEST.json

REQUEST.json: ``{"calibration": Anipose TOML, "cameras": [names to use, in order],
"members": [[one CSV per camera used] per ensemble member], "out": OUT.npz}``. Writes OUT.npz with
``positions`` (frames, keypoints, 3) in the calibration's units, ``posterior_var`` (same shape),
``keypoints``, ``smooth_param`` and ``seconds`` (the smoother call alone: EKS builds and compiles its
jax functions in every call, which is counted, as a user sees it). Used by bench/bench_fly_loco.py;
imports nothing of acinoset.

Every option of ``ensemble_kalman_smoother_multicam`` stays at its default; the camera group is
aniposelib's, read from the calibration, so EKS takes its nonlinear path (a 3D state per keypoint
projected through the calibrated cameras, the smoothing parameter fitted by maximum likelihood).
A missing detection goes in as DeepLabCut writes an unseen bodypart: the member's previous position
of that keypoint (the next one at the start) with likelihood 0.01.
"""

from __future__ import annotations

import json
import sys
import time
import warnings

import numpy as np
import pandas as pd

MISSING_LIKELIHOOD = 0.01


def read_dlc(path: str) -> tuple[list[str], np.ndarray]:
    """Bodyparts and (frames, bodyparts, [x, y, likelihood]) of a single-animal DeepLabCut CSV."""
    df = pd.read_csv(path, header=[0, 1, 2], index_col=0)
    parts = list(dict.fromkeys(df.columns.get_level_values(1)))
    arr = np.stack([df.xs(p, axis=1, level=1)[[c for c in df.xs(p, axis=1, level=1).columns
                                               if c[-1] in ("x", "y", "likelihood")]].to_numpy(float)
                    for p in parts], axis=1)
    return parts, arr


def fill_missing(a: np.ndarray) -> np.ndarray:
    """(frames, keypoints, 3): NaN positions take the nearest earlier (else later) detection."""
    a = a.copy()
    miss = ~np.isfinite(a[..., :2]).all(-1)
    for k in np.nonzero(miss.any(0))[0]:
        ok = np.nonzero(~miss[:, k])[0]
        if ok.size == 0:
            a[:, k, :2] = 0.0
        else:
            prev = np.searchsorted(ok, np.arange(len(a)), side="right") - 1
            a[miss[:, k], k, :2] = a[ok[np.where(prev >= 0, prev, 0)][miss[:, k]], k, :2]
        a[miss[:, k], k, 2] = MISSING_LIKELIHOOD
    return a


def main(request_path: str) -> int:
    warnings.filterwarnings("ignore")
    from aniposelib.cameras import CameraGroup
    from eks.marker_array import MarkerArray
    from eks.multicam_smoother import ensemble_kalman_smoother_multicam

    req = json.loads(open(request_path, encoding="utf-8").read())
    cgroup = CameraGroup.load(req["calibration"]).subset_cameras_names(req["cameras"])
    parts = None
    models = []
    for member in req["members"]:
        views = []
        for path in member:
            p, a = read_dlc(path)
            parts = parts or p
            views.append(fill_missing(a))
        models.append(np.stack(views))
    arr = np.stack(models)  # (models, cameras, frames, keypoints, 3)
    t0 = time.perf_counter()
    ma = MarkerArray(arr, data_fields=["x", "y", "likelihood"])
    _, s, df3 = ensemble_kalman_smoother_multicam(ma, keypoint_names=parts, camera_names=list(req["cameras"]),
                                                  camgroup=cgroup)
    seconds = time.perf_counter() - t0
    scorer = df3.columns.get_level_values(0)[0]
    pos = np.stack([np.stack([df3[(scorer, k, a)].to_numpy() for a in "xyz"], -1) for k in parts], 1)
    var = np.stack([np.stack([df3[(scorer, k, f"{a}_posterior_var")].to_numpy() for a in "xyz"], -1)
                    for k in parts], 1)
    np.savez(req["out"], positions=pos, posterior_var=var, keypoints=np.array(parts),
             smooth_param=np.asarray(s, dtype=float), seconds=seconds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
