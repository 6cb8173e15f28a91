"""Transient masks from the photos alone, by a multi-view plane sweep: an offline experiment
for the photometric evidence (docs/ROBUST.md), not a part of the package.

    python scripts/sweep_masks_offline.py DATA OUT [--views 4] [--depths 64] [--near 0.5] [--far 20]
        [--threshold 0.005] [--median 5]

For each training frame of the dataset DATA (transforms.json layout with cameras), every pixel
is put at `--depths` depths between --near and --far (uniform in disparity, normalised units)
along its ray; at each depth its 3x3 neighbourhood is compared with the 3x3 neighbourhood at the
point's projection (bilinear) in each of the --views training photos with the nearest camera
centres (`photo_consistency.neighbour_frames`, the comparison of `photo_consistency`, here at
every depth instead of the rendered one). A static pixel matches some neighbour at its true
depth; a transient (a passer-by, a bird, a pasted sprite) is where it is in one photo only, so
no depth makes any neighbour agree. The pixel's score is the smallest mean squared difference
over depths and neighbours; it is flagged when the score exceeds --threshold, and the flags are
median-filtered over --median x --median pixels. OUT is a copy of DATA with the flags written
as masks (M = M_w = the flags, weights 1 - M; mask_source "sweep (offline)"), so that a robust
run can take them as its prior (`train.robust = dpt+robust`). Where the dataset has distractor
masks (the pasted-transient benchmark's), the share of the distractor pixels and of the static
pixels flagged is printed per frame.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.data.formats import load_dataset
from jaxnerf_grid.masks import photo_consistency as pc
from jaxnerf_grid.nerf import rays
from jaxnerf_grid.util import io


def bilinear_neighbourhoods(images, frames, x, y):
    """The 3x3 neighbourhoods at sub-pixel positions (x, y: pixel coordinates, centres at
    integers), bilinear. images: [T, H, W, 3]; frames, x, y: [...]. Returns [..., 9, 3]."""
    _, height, width, _ = images.shape
    x0 = jnp.clip(jnp.floor(x), 0, width - 2)
    y0 = jnp.clip(jnp.floor(y), 0, height - 2)
    ax, ay = (x - x0)[..., None, None], (y - y0)[..., None, None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)

    def at(r, c):
        return pc.neighbourhoods(images, frames, r, c)

    return ((1 - ay) * ((1 - ax) * at(y0, x0) + ax * at(y0, x0 + 1))
            + ay * ((1 - ax) * at(y0 + 1, x0) + ax * at(y0 + 1, x0 + 1)))


def make_depth_errors(images, c2w, intrinsics, neighbours):
    """A jitted function (frame [N], row [N], col [N], origins [N, 3], directions [N, 3], depth)
    -> [N] the smallest neighbourhood difference over the neighbours that see the point at that
    depth (+inf where none does)."""
    _, height, width, _ = images.shape

    @jax.jit
    def errors(frame, row, col, origins, directions, depth):
        points = origins + directions * depth
        own = pc.neighbourhoods(images, frame, row, col)
        others = neighbours[frame]
        u, v, ahead = pc.project(points[:, None, :], c2w[others], intrinsics[others])
        x, y = u - 0.5, v - 0.5
        inside = ahead & (x >= 1) & (x <= width - 3) & (y >= 1) & (y <= height - 3)
        theirs = bilinear_neighbourhoods(images, others, x, y)
        err = jnp.mean((theirs - own[:, None]) ** 2, axis=(-2, -1))
        return jnp.min(jnp.where(inside, err, jnp.inf), axis=-1)

    return errors


def main(argv: list[str]) -> int:
    import cv2

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data")
    p.add_argument("out")
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--depths", type=int, default=64)
    p.add_argument("--near", type=float, default=0.5)
    p.add_argument("--far", type=float, default=20.0)
    p.add_argument("--threshold", type=float, default=0.005)
    p.add_argument("--median", type=int, default=5)
    args = p.parse_args(argv)
    ds = load_dataset(args.data)
    train = np.asarray(ds.split["train"])
    images = jnp.asarray(ds.images[train])
    _, height, width, _ = images.shape
    errors = make_depth_errors(images, jnp.asarray(ds.c2w[train]), jnp.asarray(ds.intrinsics[train]),
                               jnp.asarray(pc.neighbour_frames(ds.c2w[train], args.views)))
    depths = 1.0 / np.linspace(1.0 / args.near, 1.0 / args.far, args.depths)
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(args.data, out)
    meta = io.read_json(out / "transforms.json")
    rows, cols = (jnp.asarray(a.ravel()) for a in np.mgrid[0:height, 0:width])
    shares = []
    for local, index in enumerate(train):
        t0 = time.perf_counter()
        fx, fy, cx, cy = ds.intrinsics[index]
        r = rays.generate_rays(jnp.asarray(ds.c2w[index]), fx, fy, cx, cy, width, height)
        origins, directions = r.origins.reshape(-1, 3), r.directions.reshape(-1, 3)
        frame = jnp.full(height * width, local, jnp.int32)
        best = jnp.full(height * width, jnp.inf)
        for depth in depths:
            best = jnp.minimum(best, errors(frame, rows, cols, origins, directions, float(depth)))
        score = np.asarray(best).reshape(height, width)
        flags = (np.isfinite(score) & (score > args.threshold)).astype(np.uint8) * 255
        mask = (cv2.medianBlur(flags, args.median) if args.median > 1 else flags) > 127
        line = f"frame {local}: flagged {mask.mean():.1%}"
        if ds.distractor_masks is not None:
            truth = np.asarray(ds.distractor_masks[index], bool)
            shares.append((mask[truth].mean(), mask[~truth].mean()))
            line += f" | distractor pixels {shares[-1][0]:.1%}, static {shares[-1][1]:.1%}"
        print(f"{line} ({time.perf_counter() - t0:.0f} s)", flush=True)
        frame_meta = meta["frames"][index]
        stem = Path(frame_meta["file_path"]).stem
        io.write_png(out / "masks" / f"{stem}.png", mask.astype(np.float32))
        io.write_exr(out / "weights" / f"{stem}.exr", 1.0 - mask.astype(np.float32))
        frame_meta.update(mask_path=f"masks/{stem}.png", weight_path=f"weights/{stem}.exr",
                          masked_share=round(float(mask.mean()), 4))
    for frame_meta in meta["frames"]:  # test frames: nothing flagged
        if "mask_path" not in frame_meta:
            stem = Path(frame_meta["file_path"]).stem
            io.write_png(out / "masks" / f"{stem}.png", np.zeros((height, width), np.float32))
            io.write_exr(out / "weights" / f"{stem}.exr", np.ones((height, width), np.float32))
            frame_meta.update(mask_path=f"masks/{stem}.png", weight_path=f"weights/{stem}.exr")
    meta["mask_source"] = "sweep (offline)"
    meta["mask_params"] = {k: getattr(args, k) for k in ("views", "depths", "near", "far", "threshold", "median")}
    io.write_json(out / "transforms.json", meta)
    if shares:
        mean = np.mean(shares, axis=0)
        print(f"mean over the training frames: distractor pixels flagged {mean[0]:.1%}, static {mean[1]:.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
