"""The built-in DPT's training data mix: a cache of frames built once on the CPU, and batches
drawn from it with augmentation (for `experiments/train_dpt_mix.py`).

    python -m experiments.dpt_data OUT.npz --scenes DIR [DIR ...] [--real DIR [DIR ...]]
        [--height 180] [--width 240]

The cache (one compressed .npz, `build_cache`), every frame at one size (cover-resize + centre crop):
- synthetic frames: every training view of the `--scenes` (folders written by `jaxnerf-grid
  synth`, any preset and clutter level): RGB, the 9-class semantic labels, inverse depth; and
  each cluttered view's clean twin (`load_synthetic`);
- real photos (`--real`, folders of .jpg / .png; never committed): static scenes, so every pixel
  is "static, class unknown" (label STATIC_UNKNOWN) and they have no depth;
- a sprite bank: every connected distractor component of the synthetic frames (person, vehicle,
  bird; any size, one pixel included) with its class and exact mask, to paste onto the real
  photos at batch time.

A batch (`sample_batch`) mixes synthetic frames, real photos with sprites pasted at random
(the pasted pixels are the mask, exactly) and real photos left empty (an empty mask: what is not
a transient), then augments: a random scale crop (zoom 1-1.5x), horizontal flips, colour jitter
(brightness, contrast, saturation) and, for a share of frames, a blur by down- and up-sampling
(the demo's 160 px photos are upsampled to the working size).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from jaxnerf_grid.masks.foreground import SYNTHETIC_DYNAMIC

NUM_CLASSES = 9
STATIC_UNKNOWN = 9           # label of a real photo's pixels: static, class unknown (no class loss, only "not dynamic")
DYNAMIC = tuple(sorted(SYNTHETIC_DYNAMIC))   # (6 person, 7 vehicle, 8 bird)
assert DYNAMIC == tuple(range(DYNAMIC[0], DYNAMIC[-1] + 1)), "paste counts coverage by an id range"
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
# Shares of a batch: synthetic frames, real photos with pasted sprites, real photos left empty.
MIX = (0.55, 0.3, 0.15)


def cover_resize(image: np.ndarray, height: int, width: int, interpolation=None) -> np.ndarray:
    """[h, w, ...] -> [height, width, ...]: resized (aspect kept) to cover the target, centre-cropped."""
    import cv2

    h, w = image.shape[:2]
    s = max(height / h, width / w)
    nh, nw = max(height, round(h * s)), max(width, round(w * s))
    interp = interpolation if interpolation is not None else (cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    out = cv2.resize(image, (nw, nh), interpolation=interp)
    y, x = (nh - height) // 2, (nw - width) // 2
    return out[y:y + height, x:x + width]


def list_photos(folder) -> list[Path]:
    """The photos of a folder (recursive, sorted); a missing or empty folder is an error naming it."""
    folder = Path(folder)
    photos = sorted(p for p in folder.rglob("*") if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
    if not photos:
        raise SystemExit(f"{folder}: no photos (.jpg / .png) found")
    return photos


def load_synthetic(root: Path, height: int, width: int):
    """A synth scene's training views -> (rgb [N, h, w, 3] uint8, labels [N, h, w] uint8, inverse depth
    [N, h, w] float16), cover-resized to (height, width); labels / depth by nearest neighbour.

    Each view with distractors also gives its clean twin (the generator's `clean_file_path`, the
    same view without them), labelled like the view except that the pixels the distractors
    covered are STATIC_UNKNOWN (static, class not rendered): an empty mask in the synthetic domain."""
    import cv2

    from jaxnerf_grid.util import io

    def inverse(path):
        depth = io.read_exr(path)
        return np.where(np.isfinite(depth) & (depth > 0), 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)

    def rgb8(path):
        return np.clip(io.read_image(path) * 255.0 + 0.5, 0, 255).astype(np.uint8)

    meta = io.read_json(root / "transforms.json")
    rgbs, labels, invs = [], [], []

    def add(rgb, sem, inv):
        rgbs.append(cover_resize(rgb, height, width))
        labels.append(cover_resize(sem, height, width, cv2.INTER_NEAREST))
        invs.append(cover_resize(inv, height, width, cv2.INTER_NEAREST))

    for f in meta["frames"]:
        if f.get("split", "train") != "train" or "semantic_file_path" not in f:
            continue
        sem = cv2.imread(str(root / f["semantic_file_path"]), cv2.IMREAD_UNCHANGED)
        add(rgb8(root / f["file_path"]), sem, inverse(root / f["depth_file_path"]))
        dyn = np.isin(sem, DYNAMIC)
        if dyn.any() and "clean_file_path" in f and "clean_depth_file_path" in f:
            add(rgb8(root / f["clean_file_path"]), np.where(dyn, STATIC_UNKNOWN, sem).astype(sem.dtype),
                inverse(root / f["clean_depth_file_path"]))
    return np.stack(rgbs), np.stack(labels).astype(np.uint8), np.stack(invs).astype(np.float16)


def sprite_components(rgb: np.ndarray, labels: np.ndarray) -> list[tuple]:
    """Distractor sprites of one labelled frame: each 8-connected component of the dynamic classes
    that does not touch the border, any size.

    rgb [H, W, 3] uint8, labels [H, W] -> [(rgb [h, w, 3] uint8, mask [h, w] bool, class id)], the class
    the component's most common dynamic label."""
    import cv2

    dyn = np.isin(labels, DYNAMIC)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(dyn.astype(np.uint8), connectivity=8)
    h, w = dyn.shape
    out = []
    for c in range(1, n):
        x, y, bw, bh, _area = (int(v) for v in stats[c])
        if x == 0 or y == 0 or x + bw == w or y + bh == h:
            continue
        m = comp[y:y + bh, x:x + bw] == c
        cls = int(np.bincount(labels[y:y + bh, x:x + bw][m], minlength=NUM_CLASSES).argmax())
        out.append((rgb[y:y + bh, x:x + bw].copy(), m, cls))
    return out


def pack_sprites(sprites: list[tuple]) -> dict:
    """Sprites -> flat arrays for an .npz: sprite_rgb [P, 3] uint8, sprite_mask [P] bool (P = sum of
    the boxes' pixels), sprite_shape [S, 2] int32, sprite_class [S] uint8."""
    if not sprites:
        return {"sprite_rgb": np.zeros((0, 3), np.uint8), "sprite_mask": np.zeros(0, bool),
                "sprite_shape": np.zeros((0, 2), np.int32), "sprite_class": np.zeros(0, np.uint8)}
    return {"sprite_rgb": np.concatenate([s[0].reshape(-1, 3) for s in sprites]),
            "sprite_mask": np.concatenate([s[1].ravel() for s in sprites]),
            "sprite_shape": np.array([s[1].shape for s in sprites], np.int32),
            "sprite_class": np.array([s[2] for s in sprites], np.uint8)}


def unpack_sprites(cache) -> list[tuple]:
    """The inverse of `pack_sprites`: [(rgb [h, w, 3] uint8, mask [h, w] bool, class id)]."""
    out, start = [], 0
    for (h, w), cls in zip(cache["sprite_shape"], cache["sprite_class"]):
        n = int(h) * int(w)
        out.append((cache["sprite_rgb"][start:start + n].reshape(h, w, 3),
                    cache["sprite_mask"][start:start + n].reshape(h, w), int(cls)))
        start += n
    return out


def build_cache(scenes: list[Path], real_dirs: list[Path], out: Path, height: int = 180, width: int = 240) -> dict:
    """Writes the cache .npz (module docstring); returns a summary {synthetic, real, sprites, by_class, bytes}."""
    import cv2

    from jaxnerf_grid.util import io

    rgbs, labels, invs, sprites = [], [], [], []
    for root in scenes:
        rgb, lab, inv = load_synthetic(Path(root), height, width)
        rgbs.append(rgb), labels.append(lab), invs.append(inv)
        for r, lb in zip(rgb, lab):
            sprites += sprite_components(r, lb)
    real = []
    for folder in real_dirs:
        for p in list_photos(folder):
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise SystemExit(f"{p}: not a readable image")
            real.append(cover_resize(img[..., ::-1], height, width))
    syn_x = np.concatenate(rgbs) if rgbs else np.zeros((0, height, width, 3), np.uint8)
    arrays = {"syn_x": syn_x,
              "syn_y": np.concatenate(labels) if labels else np.zeros((0, height, width), np.uint8),
              "syn_inv": np.concatenate(invs) if invs else np.zeros((0, height, width), np.float16),
              "real_x": np.stack(real) if real else np.zeros((0, height, width, 3), np.uint8),
              **pack_sprites(sprites)}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    by_class = {SYNTHETIC_DYNAMIC[c]: int(np.sum(arrays["sprite_class"] == c)) for c in DYNAMIC}
    summary = {"synthetic": int(len(syn_x)), "real": len(real), "sprites": len(sprites), "by_class": by_class,
               "bytes": out.stat().st_size, "size": [height, width]}
    io.write_json(out.with_suffix(".json"), {**summary, "scenes": [Path(s).name for s in scenes],
                                              "real_dirs": [Path(d).name for d in real_dirs]})
    return summary


# ------------------------------------------------------------------------------- batches
def paste(image: np.ndarray, labels: np.ndarray, sprites: list[tuple], rng: np.random.Generator,
          coverage: float, max_tries: int = 60) -> None:
    """Pastes random sprites (each scaled by 0.5-2.5x, nearest neighbour, wholly inside) into
    image [H, W, 3] uint8 and writes their classes into labels [H, W], in place, until `coverage`
    of the pixels are sprite or `max_tries` sprites were tried. The pasted pixels are exactly the
    sprite's mask."""
    import cv2

    h, w = labels.shape
    covered = 0
    for _ in range(max_tries):
        if covered >= coverage * h * w:
            break
        rgb, m, cls = sprites[int(rng.integers(len(sprites)))]
        f = float(np.exp(rng.uniform(np.log(0.5), np.log(2.5))))
        sh, sw = max(1, round(m.shape[0] * f)), max(1, round(m.shape[1] * f))
        if sh >= h or sw >= w:
            continue
        rgb = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_NEAREST)
        m = cv2.resize(m.astype(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST) > 0
        y, x = int(rng.integers(0, h - sh + 1)), int(rng.integers(0, w - sw + 1))
        image[y:y + sh, x:x + sw][m] = rgb[m]
        region = labels[y:y + sh, x:x + sw]
        covered += int(np.sum(m & ((region < DYNAMIC[0]) | (region > DYNAMIC[-1]))))   # DYNAMIC: consecutive ids
        region[m] = cls


def augment(rgb: np.ndarray, labels: np.ndarray, inv: np.ndarray, out_hw: tuple, rng: np.random.Generator):
    """One frame's augmentation: random scale crop (zoom 1-1.5x) resized to out_hw, horizontal flip,
    colour jitter, and (a third of the time) a blur by down-up sampling (factor 0.5-0.9).

    rgb [H, W, 3] uint8, labels [H, W] uint8, inv [H, W] float -> float32 rgb [h, w, 3] in [0, 1],
    uint8 labels [h, w], float32 inv [h, w] (labels / depth nearest neighbour)."""
    import cv2

    H, W = labels.shape
    oh, ow = out_hw
    zoom = rng.uniform(1.0, 1.5)
    ch, cw = min(H, max(8, round(H / zoom))), min(W, max(8, round(W / zoom)))
    y, x = int(rng.integers(0, H - ch + 1)), int(rng.integers(0, W - cw + 1))
    rgb = cv2.resize(rgb[y:y + ch, x:x + cw], (ow, oh), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
    labels = cv2.resize(labels[y:y + ch, x:x + cw], (ow, oh), interpolation=cv2.INTER_NEAREST)
    inv = cv2.resize(np.asarray(inv[y:y + ch, x:x + cw], np.float32), (ow, oh), interpolation=cv2.INTER_NEAREST)
    if rng.uniform() < 0.5:
        rgb, labels, inv = rgb[:, ::-1], labels[:, ::-1], inv[:, ::-1]
    if rng.uniform() < 1 / 3:
        f = rng.uniform(0.5, 0.9)
        small = cv2.resize(rgb, (max(1, round(ow * f)), max(1, round(oh * f))), interpolation=cv2.INTER_AREA)
        rgb = cv2.resize(small, (ow, oh), interpolation=cv2.INTER_LINEAR)
    grey = rgb.mean(axis=-1, keepdims=True)
    rgb = grey + (rgb - grey) * rng.uniform(0.7, 1.3)                       # saturation
    rgb = rgb.mean() + (rgb - rgb.mean()) * rng.uniform(0.75, 1.25)         # contrast
    rgb = rgb * rng.uniform(0.75, 1.25)                                     # brightness
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), np.ascontiguousarray(labels), np.ascontiguousarray(inv)


def frame_kinds(batch: int, num_synthetic: int, num_real: int, rng: np.random.Generator, mix=MIX) -> np.ndarray:
    """[batch] ints: 0 synthetic frame, 1 real photo with pasted sprites, 2 real photo left empty,
    drawn by `mix` (real kinds only when there are real photos, synthetic only when there are frames)."""
    p = np.array(mix, np.float64) * np.array([num_synthetic > 0, num_real > 0, num_real > 0], np.float64)
    if p.sum() == 0:
        raise SystemExit("the data cache holds no frames")
    return rng.choice(3, size=batch, p=p / p.sum())


def sample_batch(cache: dict, sprites: list[tuple], batch: int, out_hw: tuple, rng: np.random.Generator,
                 mix=MIX) -> dict:
    """A training batch from the cache: {"x" [B, h, w, 3] float32 in [0, 1], "y" [B, h, w] uint8 (0-8
    classes, STATIC_UNKNOWN on real photos outside pasted sprites), "inv" [B, h, w] float32,
    "has_depth" [B] bool (synthetic frames only), "kind" [B] (`frame_kinds`)}."""
    kinds = frame_kinds(batch, len(cache["syn_x"]), len(cache["real_x"]), rng, mix)
    xs, ys, invs = [], [], []
    for k in kinds:
        if k == 0:
            i = int(rng.integers(len(cache["syn_x"])))
            rgb, lab, inv = cache["syn_x"][i], cache["syn_y"][i], cache["syn_inv"][i]
        else:
            i = int(rng.integers(len(cache["real_x"])))
            rgb = cache["real_x"][i].copy()
            lab = np.full(rgb.shape[:2], STATIC_UNKNOWN, np.uint8)
            inv = np.zeros(rgb.shape[:2], np.float32)
            if k == 1 and sprites:
                paste(rgb, lab, sprites, rng, coverage=float(rng.uniform(0.01, 0.3)))
        x, y, v = augment(rgb, lab, inv, out_hw, rng)
        xs.append(x), ys.append(y), invs.append(v)
    return {"x": np.stack(xs), "y": np.stack(ys), "inv": np.stack(invs), "has_depth": kinds == 0, "kind": kinds}


def load_cache(path) -> dict:
    """The cache's arrays, in memory ({name: array}); a missing / unreadable file is one-line error."""
    path = Path(path)
    if not path.is_file():
        raise SystemExit(f"{path}: no data cache (build it with python -m experiments.dpt_data)")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="the cache .npz to write (a .json summary is written beside it)")
    p.add_argument("--scenes", nargs="*", default=[], help="synth scene folders (training seeds only)")
    p.add_argument("--real", nargs="*", default=[], help="folders of static real photos (never committed)")
    p.add_argument("--height", type=int, default=180)
    p.add_argument("--width", type=int, default=240)
    args = p.parse_args(argv)
    summary = build_cache([Path(s) for s in args.scenes], [Path(d) for d in args.real], Path(args.out),
                          args.height, args.width)
    print(f"{args.out}: {summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
