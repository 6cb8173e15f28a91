"""The tables' figures: labelled image grids and line plots (matplotlib), written as PNG.

`line_plot` returns the plot as an RGB image array, so plots stack with other images
(`vstack`) and are written like them (`write_figure`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxnerf_grid.util import io


def label_image(img: np.ndarray, text: str, height: int = 14) -> np.ndarray:
    """img [H, W, 3] float -> [H + height, W, 3] with `text` above it on white."""
    import cv2

    bar = np.full((height, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (2, height - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar.astype(np.float32) / 255.0, img.astype(np.float32)], axis=0)


def _stack(images: list[np.ndarray], axis: int, gap: int) -> np.ndarray:
    """Concatenates [h, w, 3] images along `axis` (1: side by side, 0: top to bottom), padding the
    other extent with white and putting a white gap between neighbours."""
    other = 1 - axis
    size = max(i.shape[other] for i in images)
    out = []
    for k, im in enumerate(images):
        pad = [(0, 0), (0, 0), (0, 0)]
        pad[other] = (0, size - im.shape[other])
        if k:
            gap_shape = [0, 0, 3]
            gap_shape[axis], gap_shape[other] = gap, size
            out.append(np.ones(gap_shape, np.float32))
        out.append(np.pad(im, pad, constant_values=1.0))
    return np.concatenate(out, axis=axis)


def hstack(images: list[np.ndarray], gap: int = 3) -> np.ndarray:
    return _stack(images, 1, gap)


def vstack(images: list[np.ndarray], gap: int = 3) -> np.ndarray:
    return _stack(images, 0, gap)


def line_plot(series: list[dict], xlabel: str, ylabel: str, title: str, size=(760, 480),
              log2_x: bool = True) -> np.ndarray:
    """A line plot drawn with matplotlib (no pyplot, no global state). series: [{"label",
    "x": [...], "y": [...] (None: no point), "dashed": bool, optional "colour_index",
    optional "err": [...] (error bars, +- err)}]; size: (width, height) in pixels; log2_x: the
    x axis in log2 scale, ticks at the x values. Returns an RGB float image [H, W, 3] in [0, 1]."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = size
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    palette = [f"C{i}" for i in range(10)]
    xs = sorted({x for s in series for x in s["x"]})
    for i, s in enumerate(series):
        pts = [(x, y, e) for x, y, e in zip(s["x"], s["y"], s.get("err") or [None] * len(s["x"])) if y is not None]
        if not pts:
            continue
        x, y, err = zip(*pts)
        colour = palette[s.get("colour_index", i) % len(palette)]
        ax.plot(x, y, label=s["label"], color=colour, marker="o", markersize=3,
                linestyle="--" if s.get("dashed") else "-", linewidth=1.5)
        if any(e for e in err):  # +- err, each series' bars nudged sideways so overlapping ones show
            nudge = (i % 8 - 3.5) * 0.012
            bar_x = [v * 2 ** nudge for v in x] if log2_x else [v + nudge * (max(xs) - min(xs)) for v in x]
            ax.errorbar(bar_x, y, yerr=[e or 0.0 for e in err], fmt="none", ecolor=colour, elinewidth=1, capsize=2)
    if log2_x and xs:
        ax.set_xscale("log", base=2)
        ax.set_xticks(xs, [f"{x:g}" for x in xs])
        ax.minorticks_off()
    ax.grid(True, color="0.85")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    if any(s["x"] for s in series):
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.tight_layout()
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return rgba[..., :3].astype(np.float32) / 255.0


def write_figure(ctx, name: str, image: np.ndarray) -> Path:
    path = ctx.results / f"{name}.png"
    io.write_png(path, np.clip(image, 0, 1))
    return path
