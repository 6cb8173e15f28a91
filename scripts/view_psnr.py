"""PSNR and depth percentiles of a trained run's renders of chosen frames (training or test),
with a picture of photo | render per frame: a quick look at whether a run learned geometry.

    python scripts/view_psnr.py RUN FRAMES OUT.png      (FRAMES: comma-separated dataset indices)

Prints one line per frame: index, split, PSNR against the photo, the 5th / 50th / 95th
percentile of the rendered depth (normalised units). Used for docs/ROBUST.md's fountain-P11 table.
"""

from __future__ import annotations

import sys

import numpy as np

from jaxnerf_grid.render import views
from jaxnerf_grid.train import loop as train
from jaxnerf_grid.train.runs import load_run_and_dataset
from jaxnerf_grid.util import io


def main(argv: list[str]) -> int:
    run, frames, out = argv[0], [int(a) for a in argv[1].split(",")], argv[2]
    cfg, _, ds = load_run_and_dataset(run, None, False, False, False)
    params, _ = train.load_params(run, cfg, ds)
    test = set(int(i) for i in ds.split["test"])
    rows = []
    for i in frames:
        view = views.render_view(params, cfg, ds, i)
        rgb, photo = np.clip(view["rgb"], 0, 1), ds.images[i]
        psnr = -10 * np.log10(np.mean((rgb - photo) ** 2))
        lo, mid, hi = np.percentile(view["depth"], [5, 50, 95])
        print(f"{i} {'test' if i in test else 'train'} psnr {psnr:.2f} depth {lo:.2f} {mid:.2f} {hi:.2f}")
        rows.append(np.concatenate([photo, rgb], 1))
    io.write_png(out, np.concatenate(rows, 0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
