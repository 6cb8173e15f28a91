"""progress.html: a page in the run folder refreshed while `train` runs (`train --progress-page N`,
docs/REPORT_HTML.md), so that a user can open it from disk and reload; no server.

Every N steps (and at the last step) `watcher` rewrites RUN/progress.html: the loss and PSNR
curves of metrics.jsonl (inline SVG) and the render of the first test view (else the first
frame) from the newest checkpoint beside its photo. The page reloads itself every
REFRESH_SECONDS.
"""

from __future__ import annotations

import html
import time
from pathlib import Path

import numpy as np

from jaxnerf_grid.data import working
from jaxnerf_grid.render import views
from jaxnerf_grid.report import html as report_html
from jaxnerf_grid.train import checkpoint
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.util import io

REFRESH_SECONDS = 30
PAGE = "progress.html"


def svg_curve(values: list[tuple[float, float]], title: str, width: int = 420, height: int = 160) -> str:
    """An SVG line plot of (x, y) pairs (non-finite y left out), axes labelled with the ranges."""
    pts = [(float(x), float(y)) for x, y in values if np.isfinite(y)]
    if not pts:
        return f"<p>{html.escape(title)}: no values yet.</p>"
    xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    x0, x1 = xs.min(), max(xs.max(), xs.min() + 1)
    y0, y1 = ys.min(), max(ys.max(), ys.min() + 1e-9)
    pad = 30
    px = pad + (xs - x0) / (x1 - x0) * (width - 2 * pad)
    py = height - pad - (ys - y0) / (y1 - y0) * (height - 2 * pad)
    line = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(px, py))
    return (f'<svg class="curve" width="{width}" height="{height}" xmlns="http://www.w3.org/2000/svg">'
            f'<rect width="{width}" height="{height}" fill="#fafafa" stroke="#ccc"/>'
            f'<polyline fill="none" stroke="#1f4fbf" stroke-width="1.5" points="{line}"/>'
            f'<text x="{pad}" y="16" font-size="12">{html.escape(title)}: {ys[-1]:.4g} at step {xs[-1]:.0f}</text>'
            f'<text x="{pad}" y="{height - 8}" font-size="10">step {x0:.0f}</text>'
            f'<text x="{width - pad}" y="{height - 8}" font-size="10" text-anchor="end">{x1:.0f}</text>'
            f'<text x="2" y="{pad}" font-size="10">{y1:.3g}</text>'
            f'<text x="2" y="{height - pad}" font-size="10">{y0:.3g}</text></svg>')


def write_progress_page(run_dir, records: list[dict], step: int, view: dict | None, seconds: float) -> Path:
    """Writes RUN/progress.html (atomic). records: metrics.jsonl's; view: {"name", "gt" [H, W, 3],
    "rgb" [H, W, 3], "depth" [H, W], "step"} of the newest checkpoint, or None."""
    path = Path(run_dir) / PAGE
    curves = [svg_curve([(r["step"], r.get("loss", np.nan)) for r in records], "loss"),
              svg_curve([(r["step"], r.get("psnr", np.nan)) for r in records], "training PSNR (dB)")]
    body = [f"<h1>Training {html.escape(Path(run_dir).name)}: step {step}</h1>",
            f"<p>Written {time.strftime('%Y-%m-%d %H:%M:%S')} after {seconds:.0f} s of training in this "
            f"process; the page reloads every {REFRESH_SECONDS} s.</p>", "".join(curves)]
    if view is not None:
        body.append(f"<p>{html.escape(view['name'])}, the checkpoint of step {view['step']}:</p>")
        body.append(report_html.views_html([view]))
    text = "\n".join(["<!DOCTYPE html>", "<html><head><meta charset=\"utf-8\">",
                      f'<meta http-equiv="refresh" content="{REFRESH_SECONDS}">',
                      f"<title>step {step}: {html.escape(Path(run_dir).name)}</title>",
                      f"<style>{report_html.STYLE}</style><script>{report_html.SCRIPT}</script></head><body>",
                      *body, '<div id="overlay" onclick="this.style.display=\'none\'"><img alt="full size"></div>',
                      "</body></html>"])
    with io.naming_path(path):
        io.atomic_write_bytes(path, text.encode("utf-8"))
    return path


def watcher(run_dir, ds, cfg, every: int):
    """The `on_step` callable of `train.train` that rewrites progress.html every `every` steps and
    at cfg.train.max_steps: the curves of metrics.jsonl and the first test view rendered from the
    newest checkpoint (a step that is not a checkpoint shows the last one)."""
    run_dir = Path(run_dir)
    start = time.perf_counter()
    test = np.asarray(ds.split["test"])
    index = int(test[0]) if len(test) else 0
    targets = ds.clean_images if ds.clean_images is not None else ds.images

    def on_step(step: int) -> None:
        if step % every and step != cfg.train.max_steps:
            return
        view = None
        if checkpoint.latest_checkpoint(run_dir) is not None:
            params, saved = train.load_params(run_dir, cfg, ds)
            rendered = views.render_view(params, cfg, ds, index)
            view = {"name": f"view {index}", "gt": working.as_float(targets[index]),
                    "rgb": np.clip(rendered["rgb"], 0, 1), "depth": rendered["depth"], "step": saved}
        write_progress_page(run_dir, train.read_log(run_dir / "metrics.jsonl"), step, view,
                            time.perf_counter() - start)

    return on_step
