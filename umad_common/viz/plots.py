"""Pictures for the evaluation report: PR and ROC curves, overlay grids of single frames.

matplotlib with the Agg backend (files only, no display); every function writes one PNG.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from umad_common.metrics.pixel import PixelMetrics  # noqa: E402

LABEL_COLOURS = {0: (40, 40, 40), 1: (230, 30, 30), 255: (255, 255, 255)}


def plot_curves(curves: dict[str, PixelMetrics], pr_path: Path, roc_path: Path) -> None:
    """One precision-recall and one ROC figure with a line per named configuration."""
    fig_pr, ax_pr = plt.subplots(figsize=(6, 5), dpi=110)
    fig_roc, ax_roc = plt.subplots(figsize=(6, 5), dpi=110)
    for name, metrics in curves.items():
        result = metrics.compute()
        if metrics.n_anomaly == 0:
            continue
        pr = metrics.pr_curve()
        ax_pr.step(pr["recall"], pr["precision"], where="post", label=f"{name} (AP {100 * result['AP']:.1f})")
        if metrics.n_normal:
            roc = metrics.roc_curve()
            ax_roc.plot(roc["fpr"], roc["tpr"], label=f"{name} (AUROC {100 * result['AUROC']:.1f})")
    positives = next((m for m in curves.values() if m.n_anomaly), None)
    if positives is not None:
        rate = positives.n_anomaly / max(1, positives.n_anomaly + positives.n_normal)
        ax_pr.axhline(rate, color="grey", lw=0.8, ls=":", label=f"chance ({100 * rate:.2f} % anomaly pixels)")
    ax_roc.plot([0, 1], [0, 1], color="grey", lw=0.8, ls=":")
    ax_roc.axhline(0.95, color="grey", lw=0.6, ls="--")
    for ax, title, xlabel, ylabel in (
        (ax_pr, "Precision-recall (pixels pooled over all frames)", "recall", "precision"),
        (ax_roc, "ROC (pixels pooled over all frames)", "false positive rate", "true positive rate"),
    ):
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel, xlim=(0, 1), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    for fig, path in ((fig_pr, pr_path), (fig_roc, roc_path)):
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


def label_image(labels: np.ndarray) -> np.ndarray:
    """(h, w) 0/1/255 labels -> (h, w, 3) uint8: normal dark, anomaly red, ignored white."""
    out = np.zeros((*labels.shape, 3), np.uint8)
    for value, colour in LABEL_COLOURS.items():
        out[labels == value] = colour
    return out


def plot_overlay_grid(images: dict[str, np.ndarray], title: str, path: Path, columns: int = 4) -> None:
    """A grid of panels: RGB images as they are, label maps coloured, score maps with a colour bar."""
    n = len(images)
    rows = (n + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 2.7 * rows), dpi=100, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (name, image) in zip(axes.ravel(), images.items(), strict=False):
        if name == "ground truth":
            ax.imshow(label_image(image), interpolation="nearest")
        elif image.ndim == 3:
            ax.imshow(image, interpolation="nearest")
        else:
            shown = ax.imshow(image.astype(np.float32), cmap="inferno", interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.035, pad=0.02)
        ax.set_title(name, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_since_visible(curves: dict[str, dict[str, list[dict]]], bin_frames: int, path: Path) -> None:
    """One column per followed map: the anomaly's frame AUROC (top) and its mean score over the normal
    pixels' 99th percentile (bottom) per bin of frames since it first became visible, a line per
    scenario, all scenarios together in black."""
    names = list(curves)
    fig, axes = plt.subplots(2, len(names), figsize=(5 * len(names), 7), dpi=100, squeeze=False)
    for column, name in enumerate(names):
        top, bottom = axes[0, column], axes[1, column]
        for run, bins in curves[name].items():
            x = [b["from"] + bin_frames / 2 for b in bins]
            style = (
                {"color": "black", "lw": 2.2, "marker": "o", "zorder": 3}
                if run == "all"
                else {"lw": 1.0, "marker": "."}
            )
            label = "all scenarios" if run == "all" else run[:22]
            top.plot(x, [100 * b["rank"] if b["rank"] is not None else np.nan for b in bins], label=label, **style)
            ratio = [b["ratio_p99"] if b["ratio_p99"] is not None else np.nan for b in bins]
            bottom.plot(x, ratio, label=label, **style)
        top.axhline(50, color="grey", lw=0.8, ls=":")
        bottom.axhline(1, color="grey", lw=0.8, ls=":")
        top.set(title=name, ylabel="frame AUROC of the anomaly (%)", ylim=(0, 101))
        bottom.set(xlabel="frames since the anomaly first became visible", ylabel="anomaly mean / normal p99")
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
        top.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
