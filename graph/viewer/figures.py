"""PNG figures of a solved run (matplotlib).

People judge a 3D reconstruction by looking at it. Every picture here answers one question:

- ``skeleton.png``: where is the animal, and is the skeleton plausible? The whole scene with the
  cameras and the path of the first marker, and a close-up of the skeleton at a few frames.
- ``reprojection_error.png``: which camera disagrees about which marker? The median pixel distance
  between each camera's detections and the estimate drawn into that camera, marker x camera, with
  the number of detections the robust loss rejected in each cell.
- ``coordinates.png``: does any marker jump? x, y, z of every marker over time with a band of
  ``+-2 std`` (the estimate's marginal standard deviation).
- ``parameters.png`` (kinematic skeletons only): the pose parameters over time, ``+-2 std``.
- ``body_and_clocks.png`` (when the solve estimated or was given them): did the animal or the
  clocks differ from what was assumed? The body's lengths against the model's, and each camera's
  time offset, with their uncertainty.
- ``flags.png``: what did the solver flag? Per frame and marker, how many cameras saw it (grey
  level), the detections rejected as outliers (crosses) and the frames no marker was seen twice in
  (hatched), above the per-frame reprojection error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from graph.types import Result
from graph.viewer.payload import (
    animal_size,
    assumed_noise_px,
    camera_centers,
    error_table,
    frame_error,
    frame_ranges,
    is_length_param,
    ranges_text,
)


def _figure(width: float, height: float, layout: Literal["constrained"] | None = "constrained"):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=110, layout=layout)


def _title(result: Result) -> str:
    N = result.positions.shape[0]
    return (f"{result.method} / {result.skeleton}: {N} frames at {result.fps:g} fps, "
            f"{len(result.markers)} markers, {len(result.camera_names)} cameras")


def _snapshot_frames(result: Result, k: int) -> list[int]:
    ok = np.flatnonzero(np.isfinite(result.positions).all(axis=2).sum(axis=1) >= 2)
    if ok.size == 0:
        return []
    pick = np.unique(np.round(np.linspace(0, ok.size - 1, min(k, ok.size))).astype(int))
    return [int(ok[i]) for i in pick]


def _side_style(name: str):
    """Left markers solid, right dashed, midline dotted-free solid grey: readable without colour."""
    if name.startswith("l_") or name.startswith("left"):
        return "-"
    if name.startswith("r_") or name.startswith("right"):
        return "--"
    return "-"


def _set_equal_3d(ax, pts: np.ndarray, min_extent: float = 0.2, min_ratio: float = 0.0) -> None:
    """Axis limits around ``pts`` with one scale on every axis; no axis shorter than ``min_extent``
    or than ``min_ratio`` times the longest."""
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.size == 0:
        return
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid = (lo + hi) / 2
    ext = np.maximum(hi - lo, min_extent)
    ext = np.maximum(ext, min_ratio * ext.max()) * 1.08
    ax.set_xlim(mid[0] - ext[0] / 2, mid[0] + ext[0] / 2)
    ax.set_ylim(mid[1] - ext[1] / 2, mid[1] + ext[1] / 2)
    ax.set_zlim(mid[2] - ext[2] / 2, mid[2] + ext[2] / 2)
    ax.set_box_aspect(tuple(ext / ext.max()))


def _draw_skeleton(ax, P: np.ndarray, result: Result, color, label=None, lw=1.6, ms=9) -> None:
    """Bones as lines (left side solid, right side dashed) and markers as dots."""
    idx = {m: i for i, m in enumerate(result.markers)}
    first = True
    for a, b in result.bones:
        if a not in idx or b not in idx:
            continue
        i, j = idx[a], idx[b]
        seg = P[[i, j]]
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], _side_style(b), color=color, lw=lw,
                label=label if first else None)
        first = False
    ok = np.isfinite(P).all(axis=1)
    ax.scatter(P[ok, 0], P[ok, 1], P[ok, 2], color=color, s=ms, depthshade=False,
               label=label if first else None)
    if first:  # no bones to read the body by: name the markers
        for name, p in zip(result.markers, P):
            if np.isfinite(p).all():
                ax.text(p[0], p[1], p[2], f" {name}", fontsize=6, color="0.25")


def plot_skeleton(result: Result, path: Path, calibration=None, snapshots: int = 5) -> Path:
    """The scene with the cameras and the path of the best-seen marker, then the skeleton at a few
    frames, each panel on the same scale (a cube around the animal) so poses compare."""
    pos = np.asarray(result.positions, float)
    frames = _snapshot_frames(result, snapshots)
    cams = camera_centers(result, calibration)
    track = _track_marker(result)
    panels = 1 + max(1, len(frames))
    cols = min(3, panels)
    rows = int(np.ceil(panels / cols))
    fig = _figure(4.6 * cols, 4.2 * rows + 0.4)
    fig.suptitle(_title(result) + ("\nskeleton: solid lines left side, dashed right side" if result.bones
                                   else "\nno bones to draw (free points): markers named"), fontsize=10)

    ax = fig.add_subplot(rows, cols, 1, projection="3d")
    ax.set_title("Scene: cameras and the path of the animal", fontsize=9)
    path_pts = pos[:, track, :]
    ax.plot(path_pts[:, 0], path_pts[:, 1], path_pts[:, 2], color="black", lw=1.5,
            label=f"path of {result.markers[track]}")
    scene = [pos.reshape(-1, 3)]
    if cams is not None:
        ax.scatter(cams[:, 0], cams[:, 1], cams[:, 2], marker="^", s=50, color="tab:red",
                   edgecolor="black", depthshade=False, label="cameras")
        for name, c in zip(result.camera_names, cams):
            ax.text(c[0], c[1], c[2], f"  {name}", fontsize=7)
        scene.append(cams)
    else:
        ax.text2D(0.02, 0.02, "camera positions unknown (pass --calibration)", transform=ax.transAxes,
                  fontsize=8)
    size = animal_size(result)
    _set_equal_3d(ax, np.concatenate(scene), min_extent=size / 3, min_ratio=0.25)
    _label_axes(ax)
    ax.legend(loc="upper left", fontsize=7)

    if not frames:
        ax = fig.add_subplot(rows, cols, 2)
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no frame has an estimate", ha="center", va="center")
    else:
        span = np.nanmax([np.ptp(pos[f][np.isfinite(pos[f]).all(axis=1)], axis=0).max() for f in frames])
        half = max(0.3 * size, 0.6 * float(span))
        for k, f in enumerate(frames):
            ax = fig.add_subplot(rows, cols, k + 2, projection="3d")
            P = pos[f]
            _draw_skeleton(ax, P, result, "tab:blue")
            centre = np.nanmean(P[np.isfinite(P).all(axis=1)], axis=0)
            ax.set_xlim(centre[0] - half, centre[0] + half)
            ax.set_ylim(centre[1] - half, centre[1] + half)
            ax.set_zlim(centre[2] - half, centre[2] + half)
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=15, azim=-70)
            missing = int((~np.isfinite(P).all(axis=1)).sum())
            extra = f", {missing} markers without estimate" if missing else ""
            ax.set_title(f"frame {f} ({f / result.fps:.3f} s){extra}", fontsize=9)
            _label_axes(ax)
    fig.savefig(path)
    return path


def _track_marker(result: Result) -> int:
    """The marker whose path is drawn: the best-observed one (most frames with an estimate)."""
    ok = np.isfinite(result.positions).all(axis=2).sum(axis=0)
    return int(np.argmax(ok)) if ok.size else 0


def _label_axes(ax) -> None:
    ax.set_xlabel("x (m)", fontsize=8, labelpad=2)
    ax.set_ylabel("y (m)", fontsize=8, labelpad=2)
    ax.set_zlabel("z (m)", fontsize=8, labelpad=2)
    ax.tick_params(labelsize=7, pad=0)
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(4))


def plot_reprojection_error(result: Result, path: Path) -> Path:
    """Heat map of the median reprojection error, marker (rows) x camera (columns), each cell
    labelled with its number and its count of rejected detections."""
    t = error_table(result)
    C, M = t.median.shape
    fig = _figure(max(6.0, 1.2 * C + 3.2), max(4.0, 0.34 * M + 1.8))
    ax = fig.add_subplot(1, 1, 1)
    data = t.median.T  # (M, C)
    finite = data[np.isfinite(data)]
    # Colours from 0 to at least twice the expected detection noise: light is as good as the
    # detections allow, dark is worse.
    sigma = assumed_noise_px(result)
    vmax = max(float(np.percentile(finite, 98)) if finite.size else 0.0, 2 * sigma)
    im = ax.imshow(np.ma.masked_invalid(data), cmap=_light_magma(), vmin=0, vmax=vmax, aspect="auto",
                   interpolation="nearest")
    ax.set_facecolor("white")
    for m in range(M):
        for c in range(C):
            v = data[m, c]
            nout = t.outliers[c, m]
            nobs = t.observations[c, m]
            if nobs == 0:
                ax.add_patch(_hatch_cell(c, m))
                ax.text(c, m, "not seen", ha="center", va="center", fontsize=7, color="0.3")
                continue
            txt = "all rejected" if not np.isfinite(v) else f"{v:.1f}"
            if nout:
                txt += f"  ({nout}\u00d7)"
            dark = np.isfinite(v) and v / vmax > 0.7
            ax.text(c, m, txt, ha="center", va="center", fontsize=7.5,
                    color="white" if dark else "black")
    ax.set_xticks(range(C), result.camera_names, fontsize=8)
    ax.set_yticks(range(M), result.markers, fontsize=8)
    ax.set_xlabel("camera")
    rmse = result.report.reprojection_rmse_px if hasattr(result.report, "reprojection_rmse_px") else np.nan
    ax.set_title("Median reprojection error (px) per marker and camera\n"
                 f"(n\u00d7): detections rejected as outliers; run RMSE "
                 f"{rmse:.2f} px, {int(t.outliers.sum())} of {int(t.observations.sum())} rejected",
                 fontsize=10)
    cb = fig.colorbar(im, ax=ax, shrink=0.9)
    cb.set_label(f"median error (px); expected detection noise {sigma:g} px")
    fig.savefig(path)
    return path


def _light_magma():
    """magma_r without its darkest quarter, so black numbers stay readable on every cell."""
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap

    return ListedColormap(colormaps["magma_r"](np.linspace(0.0, 0.75, 256)))


def _hatch_cell(c: int, m: int):
    from matplotlib.patches import Rectangle

    return Rectangle((c - 0.5, m - 0.5), 1, 1, facecolor="0.93", edgecolor="0.6", hatch="///", lw=0)


def _shade_frames(ax, frames, label=None) -> None:
    for k, (a, b) in enumerate(frame_ranges(frames)):
        ax.axvspan(a - 0.5, b + 0.5, facecolor="0.85", edgecolor="0.55", hatch="//", lw=0,
                   label=label if k == 0 else None, zorder=0)


def plot_coordinates(result: Result, path: Path) -> Path:
    """x, y, z of every marker over frames, each with a ``+-2 std`` band; hatched frames are those
    in which no marker was seen by two cameras."""
    pos = np.asarray(result.positions, float)
    std = np.asarray(result.std, float)
    N, M, _ = pos.shape
    f = np.arange(N)
    height = 1.05 * M + 1.4
    fig = _figure(13, height, layout=None)  # constrained layout is slow with 3M panels
    fig.subplots_adjust(left=0.12, right=0.985, top=1 - 0.75 / height, bottom=0.5 / height,
                        hspace=0.25, wspace=0.18)
    axes = fig.subplots(M, 3, sharex=True, squeeze=False)
    fig.suptitle(_title(result) + "\nmarker coordinates (m) with \u00b12 std band; hatched: frames "
                 "with no marker seen by two cameras", fontsize=10)
    unconstrained = result.report.unconstrained_frames if hasattr(result.report, "unconstrained_frames") else []
    bad_markers = set(getattr(result.report, "unconstrained_markers", []) or [])
    for m in range(M):
        for k, axis in enumerate("xyz"):
            ax = axes[m, k]
            y = pos[:, m, k]
            s = 2 * std[:, m, k]
            _shade_frames(ax, unconstrained)
            ax.fill_between(f, y - s, y + s, color="tab:blue", alpha=0.25, lw=0)
            ax.plot(f, y, color="tab:blue", lw=1.0)
            ax.tick_params(labelsize=7)
            ax.margins(x=0)
            if m == 0:
                ax.set_title(axis, fontsize=10)
            if k == 0:
                name = result.markers[m] + (" (never seen twice)" if result.markers[m] in bad_markers else "")
                ax.set_ylabel(name, fontsize=8, rotation=0, ha="right", va="center")
            if not np.isfinite(y).any():
                ax.text(0.5, 0.5, "no estimate", transform=ax.transAxes, ha="center", va="center",
                        fontsize=8)
    for k in range(3):
        axes[-1, k].set_xlabel(f"frame ({result.fps:g} fps)", fontsize=8)
    fig.savefig(path)
    return path


def plot_parameters(result: Result, path: Path) -> Path | None:
    """Pose parameters over frames with ``+-2 std``: angles in degrees, positions in metres.
    Nothing is drawn for skeletons without angles (free points): their parameters are the markers."""
    if result.params is None or not result.param_names:
        return None
    names = list(result.param_names)
    if all(is_length_param(n) for n in names):
        return None
    q = np.asarray(result.params, float)
    qs = np.asarray(result.params_std, float) if result.params_std is not None else np.full_like(q, np.nan)
    N, P = q.shape
    cols = 5
    rows = int(np.ceil(P / cols))
    height = 1.7 * rows + 1.0
    fig = _figure(14, height, layout=None)
    fig.subplots_adjust(left=0.05, right=0.99, top=1 - 0.8 / height, bottom=0.5 / height, hspace=0.45, wspace=0.25)
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False)
    fig.suptitle(_title(result) + "\npose parameters with \u00b12 std band (angles in degrees); hatched: "
                 "frames with no marker seen by two cameras", fontsize=10)
    f = np.arange(N)
    for p in range(rows * cols):
        ax = axes.flat[p]
        if p >= P:
            ax.set_visible(False)
            continue
        scale, unit = (1.0, "m") if is_length_param(names[p]) else (180 / np.pi, "\u00b0")
        y = q[:, p] * scale
        s = 2 * qs[:, p] * scale
        _shade_frames(ax, getattr(result.report, "unconstrained_frames", []) or [])
        ax.fill_between(f, y - s, y + s, color="tab:green", alpha=0.25, lw=0)
        ax.plot(f, y, color="tab:green", lw=1.0)
        ax.set_title(f"{names[p]} ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.margins(x=0)
    for ax in axes[-1]:
        ax.set_xlabel("frame", fontsize=8)
    fig.savefig(path)
    return path


def plot_flags(result: Result, path: Path) -> Path:
    """What the solver flagged, frame by frame: per-frame reprojection error above, and below per
    marker the number of cameras that saw it (grey level), rejected detections (crosses) and
    frames with no marker seen by two cameras (hatched)."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    N, M = result.positions.shape[:2]
    C = len(result.camera_names)
    ncams = np.asarray(result.ncams).astype(int)
    out = np.asarray(result.outlier, bool) & np.isfinite(result.residuals)
    rep = result.report
    unconstrained = list(getattr(rep, "unconstrained_frames", []) or [])
    bad_markers = list(getattr(rep, "unconstrained_markers", []) or [])

    fig = _figure(13, 0.28 * M + 4.2)
    gs = fig.add_gridspec(2, 1, height_ratios=[1.0, max(2.0, 0.14 * M)])
    ax0 = fig.add_subplot(gs[0])
    ax = fig.add_subplot(gs[1], sharex=ax0)
    ferr = frame_error(result)
    _shade_frames(ax0, unconstrained, label="no marker seen by two cameras")
    ax0.plot(np.arange(N), ferr, color="black", lw=1.0, label="reprojection RMSE")
    nout = out.sum(axis=(0, 2))
    ax0b = ax0.twinx()
    ax0b.bar(np.arange(N), nout, color="tab:red", alpha=0.35, width=1.0, label="rejected detections")
    ax0.set_zorder(ax0b.get_zorder() + 1)  # the line above the bars
    ax0.patch.set_visible(False)
    ax0b.set_ylabel("rejected", fontsize=8)
    ax0b.tick_params(labelsize=7)
    ax0.set_ylabel("px", fontsize=8)
    ax0.tick_params(labelsize=7)
    h0, l0 = ax0.get_legend_handles_labels()
    h1, l1 = ax0b.get_legend_handles_labels()
    ax0.legend(h0 + h1, l0 + l1, fontsize=8, loc="upper right")
    ax0.set_title(_title(result) + "\nper frame: reprojection RMSE (line), rejected detections (bars)",
                  fontsize=10)

    # Darker: fewer cameras. A marker seen by every camera is white; one seen by none, black.
    greys = ListedColormap([(0.15 + 0.85 * k / max(C, 1),) * 3 for k in range(C + 1)])
    norm = BoundaryNorm(np.arange(-0.5, C + 1.5), greys.N)
    im = ax.imshow(ncams.T, aspect="auto", cmap=greys, norm=norm, interpolation="nearest",
                   extent=(-0.5, N - 0.5, M - 0.5, -0.5))
    _shade_frames(ax, unconstrained)
    cc, nn, mm = np.nonzero(out)
    if nn.size:
        ax.scatter(nn, mm, marker="x", s=14, color="tab:red", lw=1.0, label="rejected detection")
        ax.legend(fontsize=8, loc="upper right")
    ax.set_yticks(range(M), [m + (" *" if m in bad_markers else "") for m in result.markers], fontsize=7)
    ax.set_xlabel(f"frame ({result.fps:g} fps)", fontsize=8)
    ax.tick_params(labelsize=7)
    cb = fig.colorbar(im, ax=ax, ticks=range(C + 1), shrink=0.9)
    cb.set_label("cameras that saw the marker", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    lines = []
    if bad_markers:
        lines.append("* never seen by two cameras: " + ", ".join(bad_markers))
    if unconstrained:
        lines.append("frames with no marker seen twice: " + ranges_text(unconstrained))
    lines.append(f"{int(out.sum())} detections rejected as outliers in {int((nout > 0).sum())} frames")
    ax.set_title("; ".join(lines), fontsize=8.5)
    fig.savefig(path)
    return path


def plot_body_and_clocks(result: Result, path: Path) -> Path | None:
    """Did the animal or the clocks differ from what was assumed? The body's lengths as estimated
    (with +-2 sd) against the model's, per length group (or bone), and each camera's time offset
    in frames (with +-2 sd; cameras the motion did not time are marked). None when the solve had
    neither."""
    rep = result.report
    lengths = rep.body_lengths or {}
    offsets = rep.time_offsets_frames
    if not lengths and offsets is None:
        return None
    panels = int(bool(lengths)) + int(offsets is not None)
    fig = _figure(11, 3.6 * panels)
    axes = fig.subplots(panels, 1, squeeze=False)[:, 0]
    k = 0
    if lengths:
        ax = axes[k]
        k += 1
        names = list(lengths)
        x = np.arange(len(names))
        est = np.array([lengths[n]["length_m"] for n in names]) * 100
        sd = np.array([lengths[n]["std_m"] for n in names]) * 100
        model = np.array([lengths[n]["model_m"] for n in names]) * 100
        ax.bar(x - 0.2, model, width=0.4, color="0.75", label="model")
        ax.bar(x + 0.2, est, width=0.4, color="tab:blue", yerr=2 * sd, capsize=3, label="estimated (+-2 sd)")
        ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("length (cm)", fontsize=8)
        ax.legend(fontsize=8)
        ax.set_title(_title(result) + "\nthe body: each length as estimated against the model's", fontsize=10)
    if offsets is not None:
        ax = axes[k]
        sd = np.asarray(rep.time_offsets_std_frames or np.zeros(len(offsets)), dtype=float)
        x = np.arange(len(offsets))
        lost = set(rep.offsets_not_identified or [])
        colors = ["tab:red" if n in lost else "tab:blue" for n in result.camera_names]
        ax.bar(x, offsets, color=colors, yerr=2 * sd, capsize=3)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xticks(x, result.camera_names, fontsize=8)
        ax.set_ylabel("frames", fontsize=8)
        ax.set_title("the clocks: each camera's time offset (frame n is at n + offset; +-2 sd"
                     + ("; red: not identified by the motion" if lost else "") + ")", fontsize=10)
    fig.savefig(path)
    return path


# every figure of a result, by its file's stem (a result without angles has no parameters figure, one
# without a body or clocks estimated no body_and_clocks)
FIGURES = ("skeleton", "reprojection_error", "coordinates", "parameters", "flags", "body_and_clocks")


def write_figures(result: Result, out_dir: str | Path, calibration=None, snapshots: int = 5,
                  only: tuple[str, ...] = FIGURES) -> list[Path]:
    """Write every PNG figure (of :data:`FIGURES`, or those named in ``only``) into ``out_dir``;
    returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    draw = {"skeleton": lambda p: plot_skeleton(result, p, calibration, snapshots),
            "reprojection_error": lambda p: plot_reprojection_error(result, p),
            "coordinates": lambda p: plot_coordinates(result, p),
            "parameters": lambda p: plot_parameters(result, p),
            "flags": lambda p: plot_flags(result, p),
            "body_and_clocks": lambda p: plot_body_and_clocks(result, p)}
    written = [draw[name](out / f"{name}.png") for name in FIGURES if name in only]
    return [p for p in written if p is not None]
