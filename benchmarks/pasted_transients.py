"""Foreground exclusion on real photos with known transients: the Strecha scenes with the
synthetic generator's distractors pasted in (docs/MASKS.md).

    python -m benchmarks.pasted_transients STRECHA_DIR [--scenes fountain-P11,Herz-Jesus-P25]
        [--rows none,dpt,robust,dpt+robust,gt] [--seeds 0,1,2] [--steps 2400] [--long-side 480]
        [--photos 0] [--test-every 4] [--coverage 0.15] [--reuse] [--work benchmarks/.cache/pasted_transients]
        [--out benchmarks/results/pasted_transients]

STRECHA_DIR is the folder Benchmarking_Camera_Calibration_2008 of the openMVG repository
SfM_quality_evaluation (real 3072 x 2048 photos of static scenes with surveyed cameras; not
part of this repository, never commit it):

    git clone https://github.com/openMVG/SfM_quality_evaluation
    python -m benchmarks.pasted_transients SfM_quality_evaluation/Benchmarking_Camera_Calibration_2008

Per scene (`build_scene`): the photos are shrunk to `--long-side`, the surveyed cameras
(gt_dense_cameras/*.camera, `strecha_dataset.read_camera`) become OpenGL camera-to-world poses
normalised like `jaxnerf-grid poses` does (`normalize.normalize_orbit`), every `--test-every`-th
photo is a clean test view, and into every training photo the distractors of a synthetic tower
scene (people, vehicles, birds cut out of its cluttered training views with their exact
distractor masks, `sprite_bank`) are pasted at random places until `--coverage` of the photo is
covered (`paste_sprites`; the pasted pixels are the mask, exactly, and every other pixel is the
photo's). Rows, each a dataset variant plus config overrides over the `ours` recipe (RECIPE,
near 0.3: the cameras are about 3 units from the scene's centre):

  none        no masks, every pixel weight 1                  train.use_masks = false
  dpt         the built-in DPT's masks (`masking.write_masks`) train.use_masks = true
  robust      no masks, photometric evidence                  train.robust = "robust"
  dpt+robust  the DPT's masks as the prior                    train.robust = "dpt+robust", use_masks
  gt          the pasted masks (M_w = M: pasted pixels weight 0) train.use_masks = true

Each row trains "ours" for `--steps` per seed and is scored on the clean test photos
(`evaluate.evaluate_run`: PSNR, SSIM), with the share of the pasted pixels that training still
used: the mean training weight over them (1 for none; 1 - M_w of the masks for dpt and gt; for
the robust rows the final per-frame weights the trainer writes, when it writes them). A row
whose config this build does not know (train.robust) is skipped with a message. Writes
OUT.json and OUT.md; the datasets and runs stay under --work.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import strecha_dataset as strecha
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError

ROOT = Path(__file__).resolve().parents[1]
ROWS = ("none", "dpt", "robust", "dpt+robust", "gt")
# The recipe every row trains: `ours`, the demo's recipe when the recorded results were made (the
# demo has since moved to ours-lean); kept so that new seeds join the recorded ones.
RECIPE = "ours"
ROW_TRAIN = {"none": {"use_masks": False}, "dpt": {"use_masks": True},
             "robust": {"use_masks": False, "robust": {"mode": "robust"}},
             "dpt+robust": {"use_masks": True, "robust": {"mode": "dpt+robust"}}, "gt": {"use_masks": True}}
ROW_DATA = {"none": "plain", "robust": "plain", "dpt": "dpt", "dpt+robust": "dpt", "gt": "gt"}
NEAR = 0.3  # normalised units; normalize_orbit puts the cameras about 3 units from the centre
SPRITE_SCENE = dict(preset="tower-small", distractors="high", width=320, height=240, num_train=10, num_test=1,
                    supersample=2)


# ------------------------------------------------------------------------------- sprites
def sprite_bank(images: list[np.ndarray], masks: list[np.ndarray], min_pixels: int = 30) -> list[tuple]:
    """Distractors cut out of cluttered images: one sprite per connected component (8-connected)
    of each mask that does not touch the image border and has at least `min_pixels` pixels.

    images: [H, W, 3] float; masks: [H, W] bool (the generator's distractor masks, exact).
    Returns [(rgb [h, w, 3] float32, mask [h, w] bool)], each cropped to its component's box;
    rgb is the image's pixels (outside the mask: unused)."""
    import cv2

    bank = []
    for img, m in zip(images, masks):
        m = np.asarray(m, bool)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
        h, w = m.shape
        for c in range(1, n):
            x, y, bw, bh, area = (int(v) for v in stats[c])
            if area < min_pixels or x == 0 or y == 0 or x + bw == w or y + bh == h:
                continue
            comp = labels[y:y + bh, x:x + bw] == c
            bank.append((np.asarray(img[y:y + bh, x:x + bw], np.float32), comp))
    return bank


def _scaled(sprite: tuple, factor: float) -> tuple:
    """A sprite enlarged (or shrunk) by `factor`, nearest neighbour for both the colours and the
    mask, so the mask stays exactly the set of pixels that carry the sprite's colours."""
    import cv2

    rgb, mask = sprite
    h, w = mask.shape
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    return (cv2.resize(rgb, size, interpolation=cv2.INTER_NEAREST),
            cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0)


def paste_sprites(image: np.ndarray, bank: list[tuple], rng: np.random.Generator, coverage: float,
                  scale: float = 1.0, max_tries: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Pastes randomly chosen sprites at random places (each wholly inside the photo, later ones
    over earlier ones) until at least `coverage` of the pixels are covered or `max_tries` sprites
    were pasted. scale: the sprites' enlargement (each also varied by a factor in [0.7, 1.4]).

    image: [H, W, 3] -> (pasted [H, W, 3] float32, mask [H, W] bool). Where mask is True the
    pixel is the sprite's own colour; everywhere else it is the photo's, unchanged."""
    out = np.array(image, np.float32, copy=True)
    mask = np.zeros(out.shape[:2], bool)
    h, w = mask.shape
    if not bank or coverage <= 0:
        return out, mask
    for _ in range(max_tries):
        if mask.mean() >= coverage:
            break
        rgb, m = _scaled(bank[int(rng.integers(len(bank)))], scale * float(rng.uniform(0.7, 1.4)))
        sh, sw = m.shape
        if sh >= h or sw >= w:
            continue
        y, x = int(rng.integers(0, h - sh + 1)), int(rng.integers(0, w - sw + 1))
        region = out[y:y + sh, x:x + sw]
        region[m] = rgb[m]
        mask[y:y + sh, x:x + sw] |= m
    return out, mask


def synthetic_sprites(work: Path, seed: int = 0, min_pixels: int = 60) -> list[tuple]:
    """The sprite bank of a synthetic high-clutter tower scene (rendered once under `work`);
    components under `min_pixels` (at 320 x 240: specks, birds' wing tips) are left out."""
    from jaxnerf_grid.data.synthetic.generate import generate_scene

    scene = work / "sprites"
    if not (scene / "transforms.json").is_file():
        kw = dict(SPRITE_SCENE)
        generate_scene(kw.pop("preset"), scene, seed=seed, overwrite=True, progress=False, **kw)
    meta = io.read_json(scene / "transforms.json")
    frames = [f for f in meta["frames"] if f.get("split") == "train" and "distractor_mask_path" in f]
    return sprite_bank([io.read_image(scene / f["file_path"]) for f in frames],
                       [io.read_distractor_mask(scene / f["distractor_mask_path"]) for f in frames], min_pixels)


# ------------------------------------------------------------------------------- datasets
def build_scene(scene_dir, out, bank: list[tuple], long_side: int = 480, test_every: int = 4, coverage: float = 0.15,
                seed: int = 0, photos: int = 0, sprite_scale: float | None = None) -> Path:
    """The benchmark's dataset of one Strecha scene under `out` (see the module docstring):
    images/ (training photos with pasted sprites, test photos clean), clean/ (every photo as
    shot), distractor/ (the pasted masks; all zero on test photos), transforms.json. photos: use
    the first this many (0 = all). Returns `out`."""
    from jaxnerf_grid.data.normalize import normalize_orbit
    from jaxnerf_grid.masks.foreground import resize_map

    scene_dir, out = Path(scene_dir), Path(out)
    cams = sorted((scene_dir / "gt_dense_cameras").glob("*.camera"))
    if not cams:
        raise DataError(f"{scene_dir / 'gt_dense_cameras'}: no .camera files (is this a Strecha scene folder?)")
    if photos:
        cams = cams[:photos]
    rng = np.random.default_rng(seed)
    c2w, intr, names = [], [], []
    for cam in cams:
        camera = strecha.read_camera(cam)
        c2w.append(strecha.camera_to_world_gl(camera))
        intr.append((camera["K"], *camera["size"]))
        names.append(cam.name[: -len(".camera")])
    c2w_norm, norm = normalize_orbit(np.stack(c2w))
    for old in (out, *(out.parent / f"{out.name}-{kind}" for kind in ("dpt", "gt"))):
        shutil.rmtree(old, ignore_errors=True)  # the masked copies (`variant`) of an older build too
    frames = []
    for i, (name, (k, w, h)) in enumerate(zip(names, intr)):
        photo_path = scene_dir / "images" / name
        if not photo_path.is_file():
            raise DataError(f"{photo_path}: photo not found (listed by {cams[i]})")
        photo = io.read_image(photo_path)
        if photo.shape[:2] != (h, w):
            raise DataError(f"{photo_path}: {photo.shape[1]}x{photo.shape[0]}, its camera file says {w}x{h}")
        s = long_side / max(w, h)
        sw, sh = max(1, round(w * s)), max(1, round(h * s))
        small = np.clip(resize_map(photo, sh, sw), 0.0, 1.0)
        split = "test" if i % test_every == test_every - 1 else "train"
        if split == "train":
            scale = sprite_scale if sprite_scale is not None else long_side / SPRITE_SCENE["width"]
            pasted, mask = paste_sprites(small, bank, rng, coverage, scale=scale)
        else:
            pasted, mask = small, np.zeros((sh, sw), bool)
        stem = Path(name).stem
        io.write_png(out / "images" / f"{stem}.png", pasted)
        io.write_png(out / "clean" / f"{stem}.png", small)
        io.write_png(out / "distractor" / f"{stem}.png", mask.astype(np.float32))
        frames.append({"file_path": f"images/{stem}.png", "clean_file_path": f"clean/{stem}.png",
                       "distractor_mask_path": f"distractor/{stem}.png", "split": split,
                       "transform_matrix": c2w_norm[i].tolist(),
                       "fl_x": k[0, 0] * sw / w, "fl_y": k[1, 1] * sh / h, "cx": k[0, 2] * sw / w,
                       "cy": k[1, 2] * sh / h, "w": sw, "h": sh,
                       "pasted_share": round(float(mask.mean()), 4)})
    io.write_json(out / "transforms.json", {
        "camera_model": "PINHOLE", "near": NEAR, "far": 1000.0,
        "scene_normalization": {"scale": norm["scale"], "translation": norm["translation"]},
        "source": f"Strecha {scene_dir.name}, pasted distractors (benchmarks/pasted_transients.py)",
        "frames": frames})
    return out


def write_gt_masks(data: Path) -> None:
    """The gt row's masks: M = the pasted mask, weights 1 - M (pasted pixels weight 0)."""
    meta = io.read_json(data / "transforms.json")
    for f in meta["frames"]:
        m = io.read_distractor_mask(data / f["distractor_mask_path"]).astype(np.float32)
        stem = Path(f["file_path"]).stem
        io.write_png(data / "masks" / f"{stem}.png", m)
        io.write_exr(data / "weights" / f"{stem}.exr", 1.0 - m)
        f.update(mask_path=f"masks/{stem}.png", weight_path=f"weights/{stem}.exr")
    meta["mask_source"] = "ground-truth"
    meta["mask_params"] = {"note": "the pasted masks, M_w = M"}
    io.write_json(data / "transforms.json", meta)


def variant(base: Path, kind: str) -> Path:
    """The dataset a row trains on: "plain" (base), "dpt" (a copy masked by the built-in DPT)
    or "gt" (a copy with the pasted masks); made once per `build_scene`, then reused by the
    other rows and seeds."""
    if kind == "plain":
        return base
    out = base.parent / f"{base.name}-{kind}"
    if (out / "transforms.json").is_file() and "mask_source" in io.read_json(out / "transforms.json"):
        return out
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(base, out)
    if kind == "dpt":
        from jaxnerf_grid.masks import write as masking

        masking.write_masks(out, source="dpt", progress=False)
    else:
        write_gt_masks(out)
    return out


# ------------------------------------------------------------------------------- scoring
def pasted_share_used(data: Path, weights: dict | None) -> float:
    """The mean training weight over every pasted pixel of the training photos (1 = training
    used them all). weights: {stem: [H, W]} the weights training applied; None = weight 1."""
    meta = io.read_json(data / "transforms.json")
    total, used = 0, 0.0
    for f in meta["frames"]:
        if f.get("split") != "train":
            continue
        m = io.read_distractor_mask(data / f["distractor_mask_path"])
        stem = Path(f["file_path"]).stem
        w = np.ones(m.shape, np.float64) if weights is None else np.asarray(weights[stem], np.float64)
        total += int(m.sum())
        used += float(w[m].sum())
    return used / total if total else float("nan")


def dataset_weights(data: Path, floor: float = 0.0) -> dict | None:
    """{stem: 1 - M_w} from a masked dataset (with train.mask_weight_floor applied), else None."""
    meta = io.read_json(data / "transforms.json")
    if "mask_source" not in meta:
        return None
    out = {}
    for f in meta["frames"]:
        w = io.read_exr(data / f["weight_path"])
        if floor > 0:
            w = np.where(io.read_mask(data / f["mask_path"]) > 0.5, np.minimum(w, 1.0 - floor), w)
        out[Path(f["file_path"]).stem] = w
    return out


def run_weights(run_dir: Path) -> dict | None:
    """The per-frame weights a robust run used ({stem: [H, W]} in [0, 1]): the 8-bit PNGs the
    trainer writes to RUN/weights/ (`train.write_robust_record`; pixels training never drew
    keep 1, so the share of pasted pixels used is an upper bound); None without them."""
    folder = Path(run_dir) / "weights"
    if not folder.is_dir():
        return None
    return {p.stem: _grey(io.read_image(p)) for p in folder.glob("*.png")} or None


def _grey(image: np.ndarray) -> np.ndarray:
    """[H, W] or [H, W, C] -> [H, W] (the first channel)."""
    return image[..., 0] if image.ndim == 3 else image


def row_overrides(row: str, seed: int, steps: int, sets: dict | None = None) -> dict:
    """The `ours` recipe (RECIPE) for a row; `sets`: the --set overrides (nested), applied to
    the robust rows only (the others do not read the evidence's settings)."""
    from jaxnerf_grid.config import recipes
    from jaxnerf_grid.config import schema as config_lib

    cfg = recipes.overrides(RECIPE)
    cfg["model"]["near"] = NEAR
    cfg["train"].update(ROW_TRAIN[row], seed=seed, max_steps=steps,
                        checkpoint_every=max(1, steps), log_every=max(1, min(50, steps)))
    if sets and row in ("robust", "dpt+robust"):
        cfg = config_lib.merge(cfg, sets)
    return cfg


def prior_data(base: Path, row: str, prior: str = "dpt") -> Path:
    """The dataset a row trains on (`variant`); for the dpt and dpt+robust rows `prior` (--prior)
    picks their masks: "dpt" (the built-in DPT's), "gt" (the pasted masks: in the dpt+robust row
    with train.robust.warmup=1 the evidence never applies, so the row is the ground-truth masks
    trained on patches) or a masked copy of the scene's dataset, a folder whose path may hold
    {scene} (e.g. one written by scripts/sweep_masks_offline.py)."""
    if row not in ("dpt", "dpt+robust") or prior == "dpt":
        return variant(base, ROW_DATA[row])
    if prior == "gt":
        return variant(base, "gt")
    try:
        folder = Path(prior.format(scene=base.name))
    except (KeyError, IndexError, ValueError) as err:
        raise DataError(f"--prior {prior!r}: {{scene}} is the only name it may hold ({err!r})") from None
    if not (folder / "transforms.json").is_file() or "mask_source" not in io.read_json(folder / "transforms.json"):
        raise DataError(f"{folder}: --prior names no masked dataset (a transforms.json with mask_source)")
    return folder


def run_row(base: Path, row: str, seed: int, steps: int, work: Path, reuse: bool = False,
            sets: dict | None = None, tag: str = "", prior: str = "dpt") -> dict | None:
    """Trains and scores one row and seed; None when this build's config lacks the row's keys.
    sets, tag, prior: --set's overrides, --tag (the run folder's suffix) and --prior
    (`prior_data`)."""
    from jaxnerf_grid.eval import evaluate
    from jaxnerf_grid.train import loop as train
    from jaxnerf_grid.train import runs

    overrides = row_overrides(row, seed, steps, sets)
    try:
        train.make_config("ours", overrides)
    except ConfigError as err:
        print(f"  skip {row}: {err}", flush=True)
        return None
    data = prior_data(base, row, prior)
    run_dir = work / "runs" / f"{base.name}-{row}-s{seed}{tag}"
    t = time.perf_counter()
    if reuse and _finished(run_dir, overrides):
        m = io.read_json(run_dir / "metrics.json")
    else:
        runs.train_run(str(data), "ours", run_dir, overrides, steps, overwrite=True, progress=False)
        m = evaluate.evaluate_run(run_dir, progress=False, distractor_views=0)
    if row in ("robust", "dpt+robust"):
        weights = run_weights(run_dir)
        used = pasted_share_used(data, weights) if weights is not None else None
    else:
        floor = overrides["train"].get("mask_weight_floor", 0.0)
        weights = dataset_weights(data, floor) if overrides["train"]["use_masks"] else None
        used = pasted_share_used(data, weights)
    return {"scene": base.name, "row": row, "seed": seed, "steps": steps, "psnr": m["mean"]["psnr"],
            "ssim": m["mean"]["ssim"], "pasted_used": used, "seconds": time.perf_counter() - t}


def _finished(run_dir: Path, overrides: dict) -> bool:
    """A run evaluated with these train settings (--reuse): its metrics.json exists and its
    config.json's train section agrees with `overrides`' on every key they set."""
    if not (run_dir / "metrics.json").is_file() or not (run_dir / "config.json").is_file():
        return False
    saved = io.read_json(run_dir / "config.json").get("train", {})
    return all(saved.get(k) == v for k, v in overrides["train"].items())


def summarise(results: list[dict]) -> list[dict]:
    """Per scene and row: mean and standard deviation over the seeds."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in results):
        for row in ROWS:
            rs = [r for r in results if r["scene"] == scene and r["row"] == row]
            if not rs:
                continue
            entry = {"scene": scene, "row": row, "seeds": len(rs)}
            for k in ("psnr", "ssim", "pasted_used"):
                v = [r[k] for r in rs if r[k] is not None]
                entry[k] = float(np.mean(v)) if v else None
                entry[k + "_std"] = float(np.std(v)) if len(v) > 1 else None
            out.append(entry)
    return out


def _cell(entry: dict, key: str, fmt: str) -> str:
    """A table cell: the mean (± the standard deviation over seeds), "n/a" when unmeasured."""
    if entry[key] is None:
        return "n/a"
    std = entry[key + "_std"]
    return fmt.format(entry[key]) + (f" ± {fmt.format(std)}" if std is not None else "")


def markdown(summary: list[dict], settings: dict) -> str:
    lines = ["# Pasted transients on real photos (Strecha)", "",
             "`python -m benchmarks.pasted_transients " + " ".join(settings["argv"]) + "`", "",
             "| scene | row | seeds | PSNR (dB) | SSIM | pasted pixels used |", "| --- | --- | --- | --- | --- | --- |"]
    for e in summary:
        lines.append(f"| {e['scene']} | {e['row']} | {e['seeds']} | {_cell(e, 'psnr', '{:.2f}')} "
                     f"| {_cell(e, 'ssim', '{:.4f}')} | {_cell(e, 'pasted_used', '{:.1%}')} |")
    lines += ["", f"Settings: {json.dumps({k: v for k, v in settings.items() if k != 'argv'})}", ""]
    return "\n".join(lines)


def shown_argv(argv: list[str], strecha: str) -> list[str]:
    """The command line as the results show it, naming no folder of this machine: the Strecha
    folder as STRECHA_DIR, paths inside the repository relative to it, other absolute paths
    (--work, --out elsewhere) by their last component."""
    out = []
    for a in argv:
        if a == strecha:
            a = "STRECHA_DIR"
        elif a.startswith(str(ROOT) + os.sep):
            a = a[len(str(ROOT)) + 1:]
        elif os.path.isabs(a):
            a = Path(a).name
        out.append(a)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.pasted_transients", description=__doc__.split("\n\n")[0])
    p.add_argument("strecha", help="the folder Benchmarking_Camera_Calibration_2008 (openMVG/SfM_quality_evaluation)")
    p.add_argument("--scenes", default="fountain-P11,Herz-Jesus-P25")
    p.add_argument("--rows", default=",".join(ROWS))
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=2400)
    p.add_argument("--long-side", type=int, default=480)
    p.add_argument("--photos", type=int, default=0, help="use the first N photos of each scene (0 = all)")
    p.add_argument("--test-every", type=int, default=4, help="every N-th photo is a clean test view")
    p.add_argument("--coverage", type=float, default=0.15,
                   help="share of each training photo covered by pasted sprites")
    p.add_argument("--reuse", action="store_true",
                   help="score a row's run again without training when it finished with the same settings")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a training setting of the robust rows (e.g. train.robust.spread=2), repeatable")
    p.add_argument("--tag", default="", help="suffix of the run folders (keeps runs with other --set apart)")
    p.add_argument("--prior", default="dpt",
                   help="the masks of the dpt and dpt+robust rows: dpt, gt, or a masked copy of the scene's dataset "
                        "(a folder; {scene} in it is the scene's name)")
    p.add_argument("--work", default=str(ROOT / "benchmarks/.cache/pasted_transients"))
    p.add_argument("--out", default=str(ROOT / "benchmarks/results/pasted_transients"))
    args = p.parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad:
        raise SystemExit(f"--rows: unknown {bad}; choose from {', '.join(ROWS)}")
    if args.test_every < 2 or args.long_side < 16 or not 0 <= args.coverage < 1:
        raise SystemExit("--test-every must be >= 2, --long-side >= 16, --coverage in [0, 1)")
    try:
        from jaxnerf_grid.config import run_config
        from jaxnerf_grid.config import schema as config_lib

        sets = config_lib.parse_sets(args.set, run_config.RunConfig) if args.set else None
    except ConfigError as err:
        raise SystemExit(f"--set: {err}") from None
    strecha = Path(args.strecha)
    if not strecha.is_dir():
        raise SystemExit(f"{strecha}: not a folder (see `python -m benchmarks.pasted_transients --help`)")
    seeds = [int(s) for s in args.seeds.split(",")]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    try:
        bank = synthetic_sprites(work)
        print(f"{len(bank)} distractor sprites from a synthetic high-clutter scene", flush=True)
        results = []
        for scene in [s.strip() for s in args.scenes.split(",") if s.strip()]:
            base = build_scene(strecha / scene, work / "data" / scene, bank, args.long_side, args.test_every,
                               args.coverage, seed=0, photos=args.photos)
            meta = io.read_json(base / "transforms.json")
            print(f"{scene}: {len(meta['frames'])} photos, pasted share "
                  f"{np.mean([f['pasted_share'] for f in meta['frames'] if f['split'] == 'train']):.1%}", flush=True)
            for row in rows:
                for seed in seeds:
                    r = run_row(base, row, seed, args.steps, work, args.reuse, sets, args.tag, args.prior)
                    if r is not None:
                        results.append(r)
                        print(f"  {scene} {row} seed {seed}: PSNR {r['psnr']:.2f} SSIM {r['ssim']:.4f} pasted used "
                              + ("n/a" if r["pasted_used"] is None else f"{r['pasted_used']:.1%}")
                              + f" ({r['seconds']:.0f} s)", flush=True)
    except (DataError, ConfigError) as err:
        raise SystemExit(str(err)) from None
    settings = {"argv": argv, "scenes": args.scenes, "rows": rows, "seeds": seeds, "steps": args.steps,
                "robust_sets": args.set, "prior": args.prior,
                "long_side": args.long_side, "photos": args.photos, "test_every": args.test_every,
                "coverage": args.coverage, "machine": platform.machine(), "python": platform.python_version()}
    summary = summarise(results)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    settings["argv"] = shown_argv(argv, args.strecha)
    io.write_json(out.with_suffix(".json"), {"settings": settings, "summary": summary, "runs": results})
    out.with_suffix(".md").write_text(markdown(summary, settings))
    print(markdown(summary, settings))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
