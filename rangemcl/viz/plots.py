"""Pictures for people: range images as PNG. Matplotlib is imported only when a picture is made."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write


def save_range_image_png(
    path, ranges: np.ndarray, max_range_m: float | None = None, row_scale: int = 4
) -> Path:
    """Write an ``(H, W)`` range image as a colour PNG (near = bright, no return = black).

    Rows are repeated ``row_scale`` times so that sensors with few beams stay readable.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import cm

    r = np.asarray(ranges, dtype=np.float64)
    valid = r > 0
    top = float(max_range_m) if max_range_m else float(r[valid].max()) if valid.any() else 1.0
    colours = cm.turbo(1.0 - np.clip(r / top, 0.0, 1.0))[..., :3]  # (H, W, 3)
    colours[~valid] = 0.0
    image = np.repeat(colours, max(1, int(row_scale)), axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: plt.imsave(fh, image, format="png"))
    return path


def _map_background(ax, mesh_map, max_points: int = 150_000) -> None:
    """The map's non-ground vertices from above, light grey."""
    if mesh_map.budgeted:  # a map within a memory budget: read tile by tile
        v = mesh_map.background_points(max_points)
    else:
        v = mesh_map.vertices[~mesh_map.is_ground]
    if len(v) > max_points:
        v = v[:: int(np.ceil(len(v) / max_points))]
    ax.scatter(v[:, 0], v[:, 1], s=0.2, c="0.75", linewidths=0, rasterized=True)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_localization(
    out_dir, mesh_map, estimate, truth, first_frame: int, converged_frame, snapshots
) -> list[Path]:
    """``trajectory.png`` (estimate and truth over the map from above), ``error.png`` (location and yaw
    error per frame) and ``particles.png`` (particle clouds at a few frames) in ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rangemcl.evaluation.metrics import pose_errors

    out_dir = Path(out_dir)
    written = []
    est = np.asarray(estimate)
    k0 = 0 if converged_frame is None else max(0, converged_frame - first_frame)

    fig, ax = plt.subplots(figsize=(8, 8))
    _map_background(ax, mesh_map)
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], "-", c="k", lw=1.5, label="ground truth")
    if converged_frame is not None:
        ax.plot(est[k0:, 0], est[k0:, 1], "-", c="tab:red", lw=1.0, label="estimate (after convergence)")
        ax.plot(*est[k0, :2], "o", c="tab:red", ms=5)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right")
    ax.set_title("rangemcl localize: trajectory")
    fig.tight_layout()
    written.append(out_dir / "trajectory.png")
    fig.savefig(written[-1], dpi=130)
    plt.close(fig)

    if truth is not None:
        loc, yaw = pose_errors(est, truth)
        frames = first_frame + np.arange(len(est))
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
        a1.semilogy(frames, np.maximum(loc, 1e-3), c="tab:blue")
        a1.set_ylabel("location error (m)")
        a2.semilogy(frames, np.maximum(yaw, 1e-3), c="tab:orange")
        a2.set_ylabel("yaw error (deg)")
        a2.set_xlabel("frame")
        for a in (a1, a2):
            if converged_frame is not None:
                a.axvline(converged_frame, c="k", ls="--", lw=0.8, label="converged")
            a.grid(True, which="both", alpha=0.3)
        if converged_frame is not None:
            a1.legend(loc="upper right")
        fig.tight_layout()
        written.append(out_dir / "error.png")
        fig.savefig(written[-1], dpi=130)
        plt.close(fig)

    if snapshots:
        names = sorted(snapshots)
        if len(names) > 6:  # the first frames of the search, the convergence, the end
            keep = {*[n for n in names if n.endswith("converged")][:1], names[-1]}
            names = sorted({*[n for n in names if n not in keep][: 6 - len(keep)], *keep})
        cols = min(3, len(names))
        rows = int(np.ceil(len(names) / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 5 * rows), squeeze=False)
        for ax, name in zip(axes.ravel(), names, strict=False):
            p = snapshots[name]
            _map_background(ax, mesh_map, 60_000)
            ax.scatter(p[:, 0], p[:, 1], s=1.0, c="tab:red", linewidths=0)
            frame = int(name.split("_")[1])
            if truth is not None and 0 <= frame - first_frame < len(truth):
                ax.plot(*truth[frame - first_frame, :2], "x", c="k", ms=10, mew=2)
            ax.set_title(
                f"frame {frame}: {len(p)} particles" + (" (converged)" if name.endswith("converged") else "")
            )
        for ax in axes.ravel()[len(names) :]:
            ax.axis("off")
        fig.tight_layout()
        written.append(out_dir / "particles.png")
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)
    return written
