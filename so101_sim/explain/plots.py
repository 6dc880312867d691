"""Figures for the `so101-sim explain` page, as PNG bytes (matplotlib's Agg canvas, no pyplot
state, so nothing leaks into a caller's matplotlib session)."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

BLUE, CORAL, GREY = "#2b6cb0", "#e4572e", "#888888"


def png(fig: Figure) -> bytes:
    """The figure as PNG bytes."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi, bbox_inches="tight")
    return buf.getvalue()


def _joint_axes(n: int, names: list[str], title: str) -> tuple[Figure, list[Any]]:
    cols = 3 if n > 4 else n
    rows = -(-n // cols)
    fig = Figure(figsize=(3.6 * cols, 2.4 * rows), dpi=80)
    axes = [fig.add_subplot(rows, cols, i + 1) for i in range(n)]
    for ax, name in zip(axes, names, strict=False):
        ax.set_title(name, fontsize=10)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig, axes


def _kp_colours(n: int) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["hsv"](np.linspace(0, 1, n, endpoint=False))


def frames_figure(orig: list[np.ndarray], crops: list[np.ndarray], boxes: list[Any],
                  labels: list[str], keypoints: list[dict] | None = None,
                  grid: tuple[int, int] | None = None) -> bytes:
    """Per obs step: the recorded frame (crop box drawn) and the crop the backbone sees,
    with the spatial-softmax keypoints on both and the feature cells on the crop when given."""
    n = len(orig)
    fig = Figure(figsize=(8.0 * n, 3.3), dpi=80)
    for i in range(n):
        ax_o = fig.add_subplot(1, 2 * n, 2 * i + 1)
        ax_c = fig.add_subplot(1, 2 * n, 2 * i + 2)
        ax_o.imshow(orig[i])
        ax_c.imshow(crops[i], interpolation="nearest")
        if boxes[i] is not None:
            x, y, w, h = boxes[i]
            ax_o.add_patch(Rectangle((x, y), w, h, fill=False, ec="yellow", lw=1.2, ls="--"))
        if keypoints:
            kp = keypoints[i]
            col = _kp_colours(len(kp["crop_px"]))
            o, c = np.asarray(kp["orig_px"]), np.asarray(kp["crop_px"])
            ax_o.scatter(o[:, 0], o[:, 1], s=28, c=col, marker="o", edgecolors="black",
                         linewidths=0.6)
            ax_c.scatter(c[:, 0], c[:, 1], s=40, c=col, marker="o", edgecolors="black",
                         linewidths=0.6)
        if grid:
            h, w = crops[i].shape[:2]
            for r in range(1, grid[0]):
                ax_c.axhline(r * h / grid[0] - 0.5, color="white", lw=0.8, alpha=0.8)
            for c_ in range(1, grid[1]):
                ax_c.axvline(c_ * w / grid[1] - 0.5, color="white", lw=0.8, alpha=0.8)
        ax_o.set_title(f"{labels[i]}\nrecorded {orig[i].shape[0]}×{orig[i].shape[1]}",
                       fontsize=11)
        ax_c.set_title(f"{labels[i]}\npolicy crop {crops[i].shape[0]}×{crops[i].shape[1]}",
                       fontsize=11)
        for ax in (ax_o, ax_c):
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    return png(fig)


def alpha_bar_figure(alphas_cumprod: list[float], k: int) -> bytes:
    ab = np.asarray(alphas_cumprod)
    fig = Figure(figsize=(6.0, 2.8), dpi=80)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(ab)), ab, color=BLUE, label="ᾱ_k (signal kept)")
    ax.plot(np.arange(len(ab)), 1 - ab, color=CORAL, label="1 − ᾱ_k (noise)")
    ax.axvline(k, color=GREY, ls="--")
    ax.scatter([k], [ab[k]], color=BLUE, zorder=3)
    ax.annotate(f"k={k}: ᾱ={ab[k]:.4f}", (k, ab[k]), xytext=(8, -4),
                textcoords="offset points", fontsize=9)
    ax.set_xlabel("diffusion step k", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return png(fig)


def chunk_noise_figure(clean: list, noisy: list, names: list[str], k: int) -> bytes:
    c, n = np.asarray(clean), np.asarray(noisy)
    fig, axes = _joint_axes(c.shape[1], names, f"normalised action chunk: clean A⁰ vs noisy "
                                               f"A^{k} (rows of the chunk on x)")
    for j, ax in enumerate(axes):
        ax.plot(c[:, j], color=BLUE, marker=".", label="A⁰ clean")
        ax.plot(n[:, j], color=CORAL, marker=".", label=f"A^{k} noisy")
    axes[0].legend(fontsize=7)
    return png(fig)


def embedding_figure(sinusoidal: list[float], k: int) -> bytes:
    fig = Figure(figsize=(6.5, 2.4), dpi=80)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(sinusoidal, color=BLUE, lw=1)
    half = len(sinusoidal) // 2
    ax.axvline(half - 0.5, color=GREY, ls="--")
    ax.set_title(f"sinusoidal embedding of k={k}: sin half | cos half", fontsize=10)
    ax.set_xlabel("dimension", fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return png(fig)


def noise_pred_figure(eps: list, pred: list, names: list[str]) -> bytes:
    e, p = np.asarray(eps), np.asarray(pred)
    fig, axes = _joint_axes(e.shape[1], names, "actual noise ε (blue) vs predicted ε_θ (coral)"
                                               " over the chunk")
    for j, ax in enumerate(axes):
        ax.plot(e[:, j], color=BLUE, marker="o", ms=3, label="ε")
        ax.plot(p[:, j], color=CORAL, marker="o", ms=3, label="ε_θ")
    axes[0].legend(fontsize=7)
    return png(fig)


def denoise_steps_figure(samples: list, timesteps: list[int], names: list[str]) -> bytes:
    """The normalised chunk before each DDIM step and after the last: noise becoming a chunk."""
    from matplotlib import colormaps

    x = np.asarray(samples)
    n = len(x)
    cols = min(6, n)
    rows = -(-n // cols)
    fig = Figure(figsize=(2.3 * cols, 2.0 * rows + 0.4), dpi=80)
    colours = colormaps["tab10"](np.arange(x.shape[2]))
    lim = min(3.5, max(1.2, float(np.abs(x).max()) * 1.05))
    for i in range(n):
        ax = fig.add_subplot(rows, cols, i + 1)
        for j in range(x.shape[2]):
            ax.plot(x[i, :, j], color=colours[j], lw=1.1, label=names[j] if i == 0 else None)
        ax.set_ylim(-lim, lim)
        ax.set_title("start: pure noise" if i == 0 else
                     (f"after step k={timesteps[i - 1]}" if i < n - 1 else "final chunk"),
                     fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.legend(loc="lower center", ncol=x.shape[2], fontsize=8, frameon=False)
    fig.suptitle("the normalised chunk through the sampler (x: chunk row; one line per joint)",
                 fontsize=11)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return png(fig)


def final_chunk_figure(final: list, truth: list, pad: list[bool], executed: list,
                       names: list[str]) -> bytes:
    """The sampled chunk against the recorded actions, in LeRobot units; executed rows shaded."""
    f, gt = np.asarray(final), np.asarray(truth)
    fig, axes = _joint_axes(f.shape[1], names, "sampled chunk (coral) vs recorded actions "
                                               "(dashed), LeRobot units; yellow: executed rows")
    rows = np.arange(f.shape[0])
    padded = np.asarray(pad, dtype=bool)
    for j, ax in enumerate(axes):
        if executed[0] is not None:
            ax.axvspan(executed[0] - 0.5, executed[1] - 0.5, color="#f6e05e", alpha=0.35, lw=0)
        ax.plot(rows, f[:, j], color=CORAL, lw=2, marker=".", label="sampled")
        ax.plot(rows, gt[:, j], color="black", ls="--", lw=1.2, label="recorded")
        if padded.any():
            ax.scatter(rows[padded], gt[padded, j], marker="x", color="black", s=20,
                       label="padding")
        span = max(np.ptp(np.concatenate([f[:, j], gt[:, j]])), 2.0)
        mid = (max(f[:, j].max(), gt[:, j].max()) + min(f[:, j].min(), gt[:, j].min())) / 2
        ax.set_ylim(mid - 0.65 * span, mid + 0.65 * span)
    axes[0].legend(fontsize=7)
    return png(fig)
