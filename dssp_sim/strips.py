"""A picture strip of an episode: depth renders at a few moments, side by side (PNG, matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def save_strip(frames: list[np.ndarray], path: Path, title: str, n: int = 8) -> Path:
    """frames: per tick depth (H, W) uint16; saves ``n`` evenly spaced ones as one PNG."""
    import matplotlib  # deferred: loads matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: loads matplotlib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    picks = np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int)
    fig, axes = plt.subplots(1, len(picks), figsize=(2.2 * len(picks), 2.2))
    for ax, i in zip(np.atleast_1d(axes), picks):
        depth = frames[i].astype(np.float32)
        valid = depth > 0
        shown = np.where(valid, depth, np.nan)
        ax.imshow(shown, cmap="viridis_r")
        ax.set_title(f"tick {i}", fontsize=8)
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
