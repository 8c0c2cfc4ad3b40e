"""Pictures of a calibration (matplotlib, PNG): the rig and the board views in 3D, the residuals
per camera, and how much of each image the board covered."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graph.calibrate.extrinsics import RigResult
from graph.camera import Calibration
from graph.viewer.figures import _figure, _set_equal_3d


def viewing_frame(result: RigResult) -> np.ndarray:
    """The rotation ``V`` (3, 3) the rig is drawn in, ``x' = V x``: the world itself when its z is up
    (``--origin board:FRAME``); with camera 1 as the world (z its optical axis, not up),
    :func:`upright_frame`."""
    return np.eye(3) if result.origin != "camera1" else upright_frame(result.calibration.cameras)


def upright_frame(cams: list) -> np.ndarray:
    """``V`` whose z is the cameras' mean up, ``u = -mean_i R_i[1]`` (an image's y runs down, and
    cameras are mostly mounted upright: the average of the cameras' up vectors, as
    structure-from-motion tools level a reconstruction), and its x camera 1's viewing direction made
    level."""
    up = -np.mean([c.R[1] for c in cams], axis=0)
    if np.linalg.norm(up) < 1e-6:
        return np.eye(3)
    up /= np.linalg.norm(up)
    ahead = cams[0].R[2] - (cams[0].R[2] @ up) * up
    if np.linalg.norm(ahead) < 1e-6:  # camera 1 looks straight up or down
        ahead = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    ahead /= np.linalg.norm(ahead)
    return np.stack([ahead, np.cross(up, ahead), up])


def refine_figure(old: Calibration, result, path: Path) -> Path:
    """A refinement (:class:`graph.calibrate.refine.RefineResult`): each camera before (grey) and
    after (blue: kept; orange: refined but not kept), centre and viewing direction, drawn upright
    (:func:`upright_frame` of the old rig), in the rig's own units."""
    from graph.io.calibration import resolve_units

    units, _ = resolve_units(old, "auto")
    fig = _figure(7.5, 6.0)
    ax = fig.add_subplot(projection="3d")
    V = upright_frame(old.cameras)
    before = np.stack([c.center for c in old.cameras]) @ V.T
    after = np.stack([c.center for c in result.refined.cameras]) @ V.T
    scale = 0.15 * float(np.ptp(np.vstack([before, after]), axis=0).max() or 1.0)
    colour = "tab:blue" if result.accepted else "tab:orange"
    for cams, centres, col in ((old.cameras, before, "0.6"), (result.refined.cameras, after, colour)):
        for c, C in zip(cams, centres):
            d = (V @ c.R[2]) * scale
            ax.scatter(*C, color=col, s=24)
            ax.plot(*np.stack([C, C + d]).T, color=col, lw=1.5)
    for name, C in zip(old.names, after):
        ax.text(*C, name, fontsize=8)
    _set_equal_3d(ax, np.vstack([before, after]), min_extent=scale)
    for axis, label in zip("xyz", ("ahead of camera 1", "left", "up")):
        getattr(ax, f"set_{axis}label")(f"{label} ({units})")
    verdict = "refined" if result.accepted else "kept the old rig (refined in orange)"
    ax.set_title(f"before (grey) and after: {verdict}; leave one camera out {np.nanmean(result.loo_old_px):.2f} -> "
                 f"{np.nanmean(result.loo_new_px):.2f} px", fontsize=9)
    fig.savefig(path)
    return path


def rig_figure(result: RigResult, path: Path, board_outline: np.ndarray) -> Path:
    """Cameras (centre and viewing direction) and the board of every view used, drawn upright
    (:func:`viewing_frame`)."""
    fig = _figure(7.5, 6.0)
    ax = fig.add_subplot(projection="3d")
    cams = result.calibration.cameras
    V = viewing_frame(result)
    centres = np.stack([c.center for c in cams]) @ V.T
    boards = [(board_outline @ T[:3, :3].T + T[:3, 3]) @ V.T for T in result.board_poses.values()]
    scale = 0.1 * float(np.ptp(np.vstack([centres, *boards]), axis=0).max())
    pts = [centres]
    for X in boards:
        ax.plot(*np.vstack([X, X[:1]]).T, color="0.55", lw=0.8)
        pts.append(X)
    for c, C, name in zip(cams, centres, result.calibration.names):
        d = (V @ c.R[2]) * scale
        ax.scatter(*C, color="tab:blue", s=24)
        ax.plot(*np.stack([C, C + d]).T, color="tab:blue", lw=1.5)
        ax.text(*(C + 0.3 * d), name, fontsize=8)
    _set_equal_3d(ax, np.vstack(pts), min_extent=0.1)
    upright = result.origin != "camera1"
    ax.set_xlabel("x (m)" if upright else "ahead of camera 1 (m)")
    ax.set_ylabel("y (m)" if upright else "left (m)")
    ax.set_zlabel("z (m)" if upright else "up (m)")
    ax.set_title(f"{len(cams)} cameras, {len(result.board_poses)} board views, RMS {result.rms_px:.2f} px "
                 f"(origin: {result.origin})", fontsize=9)
    fig.savefig(path)
    return path


def residuals_figure(result: RigResult, path: Path) -> Path:
    """The length of every corner's residual, per camera (box plot), and the RMS of each."""
    fig = _figure(7.0, 3.8)
    ax = fig.add_subplot()
    data = [np.linalg.norm(e, axis=1) for e in result.residuals]
    ax.boxplot(data, showfliers=True, flierprops={"markersize": 2})
    ax.set_xticks(range(1, len(data) + 1), [f"{c.name}\n{c.rms_px:.2f} px" for c in result.cameras], fontsize=8)
    ax.set_ylabel("reprojection error (px)")
    ax.set_title("residual per corner, by camera (RMS below the name)", fontsize=9)
    fig.savefig(path)
    return path


def coverage_figure(result: RigResult, path: Path) -> Path:
    """Every corner the solve used, in each camera's image, coloured by its error."""
    n = len(result.residuals)
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig = _figure(3.6 * cols, 2.4 * rows)
    for i, (uv, e, cam) in enumerate(zip(result.corners_used, result.residuals, result.calibration.cameras)):
        ax = fig.add_subplot(rows, cols, i + 1)
        W, H = cam.size
        sc = ax.scatter(uv[:, 0], uv[:, 1], c=np.linalg.norm(e, axis=1), s=2, cmap="viridis")
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.set_aspect("equal")
        ax.set_title(result.calibration.names[i], fontsize=8)
        ax.tick_params(labelsize=6)
        fig.colorbar(sc, ax=ax, shrink=0.8).ax.tick_params(labelsize=6)
    fig.suptitle("corners used, coloured by reprojection error (px)", fontsize=9)
    fig.savefig(path)
    return path


def write_figures(result: RigResult, directory: str | Path, board) -> list[Path]:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    obj = board.object_points()
    grid = board.corner_grid
    outline = obj[[0, grid[0] - 1, len(obj) - 1, len(obj) - grid[0]]]
    return [rig_figure(result, d / "rig.png", outline), residuals_figure(result, d / "residuals.png"),
            coverage_figure(result, d / "coverage.png")]
