"""Pictures for people: the confusion matrix and depth / truth / prediction strips.

matplotlib with the Agg backend (no display needed); colours come from the label table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.core.labels import NAMES, colorize


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def confusion_figure(confusion: np.ndarray, path: Path, title: str = "") -> None:
    """Row-normalised confusion matrix (recall on the diagonal) with counts per row."""
    plt = _plt()
    cm = np.asarray(confusion, np.float64)
    rows = cm.sum(axis=1, keepdims=True)
    norm = np.divide(cm, rows, out=np.zeros_like(cm), where=rows > 0)
    fig, ax = plt.subplots(figsize=(8, 7), dpi=100)
    im = ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    ax.set_xticks(range(len(NAMES)), NAMES, rotation=45, ha="right")
    ax.set_yticks(
        range(len(NAMES)), [f"{n} ({int(r)})" for n, r in zip(NAMES, rows[:, 0], strict=True)]
    )
    for i in range(len(NAMES)):
        for j in range(len(NAMES)):
            if norm[i, j] >= 0.01:
                colour = "white" if norm[i, j] > 0.5 else "black"
                ax.text(
                    j, i, f"{norm[i, j]:.2f}", ha="center", va="center", fontsize=7, color=colour
                )
    ax.set_xlabel("predicted")
    ax.set_ylabel("true (pixels)")
    ax.set_title(title or "confusion matrix, rows normalised")
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def frames_figure(examples, path: Path, crf_name: str = "crf") -> None:
    """One row per frame: depth, ground truth, forest argmax, CRF result."""
    plt = _plt()
    n = max(len(examples), 1)
    fig, axes = plt.subplots(n, 4, figsize=(16, 3.2 * n), dpi=80, squeeze=False)
    titles = ("depth (mm)", "truth", "forest", f"CRF ({crf_name})")
    for r, (depth, truth, pred, final) in enumerate(examples):
        valid = depth > 0
        lo, hi = np.percentile(depth[valid], [1, 99]) if valid.any() else (0, 1)
        axes[r, 0].imshow(np.where(valid, depth, np.nan), cmap="viridis", vmin=lo, vmax=hi)
        for c, img in enumerate((truth, pred, final), start=1):
            axes[r, c].imshow(colorize(img))
    for c, t in enumerate(titles):
        axes[0, c].set_title(t)
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def _save(fig, path: Path) -> None:
    """Atomic: the figure replaces `path` whole or not at all."""
    with atomic_write(path) as f:
        fig.savefig(f, format=Path(path).suffix.lstrip(".") or "png")
