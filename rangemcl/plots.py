"""Pictures for people: range images as PNG. Matplotlib is imported only when a picture is made."""

from __future__ import annotations

from pathlib import Path

import numpy as np


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
    plt.imsave(path, image)
    return path
