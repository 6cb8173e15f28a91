"""Train the built-in DPT (small config, segmentation + depth heads) on synthetic training scenes
and evaluate its distractor masks on held-out scenes.

Usage:
  JAX_PLATFORMS=cpu python -m experiments.train_builtin_dpt --train DIR [DIR ...] --eval DIR [DIR ...]
      [--minutes 45] [--steps 1600] [--patch-size 8] [--init DIR] [--lr 2e-3]
      [--out jaxnerf_grid/masks/assets/dpt_builtin]
      [--results experiments/results/builtin_dpt]

Data: folders written by `jaxnerf-grid synth` (DATASET.md layout) with `semantic_file_path`
(classes 0 sky .. 8 bird) and `depth_file_path`. Training scenes must use seeds disjoint from
every evaluation scene (this project reserves seeds >= 7000 for the built-in model: 7001-7099
train, 7101+ held out). Every frame of a training scene is used (cluttered images).

Model: the same DPT code as the HF import (jaxnerf_grid.masks.dpt), a small config (patch 8, 4 ViT
layers of width 64, fusion width 16; patch 16 gave IoU 0.38 against patch 8's 0.52, see
experiments/results/builtin_dpt.md), segmentation head over the 9 synthetic classes and a depth
head regressing inverse depth (1 / z-depth in normalised units; sky -> 0). Input: images resized
to 128 x 160 (the working size of the 160 x 120 benchmark images). Loss: class-weighted
cross-entropy + 0.5 * L1 on inverse depth. Optimiser: Adam from jaxnerf_grid.train.optim driven by
jaxopt's OptaxSolver, random horizontal flips. Stops at --steps or --minutes, whichever first.

Evaluation (held-out scenes, full resolution, through the same path as `jaxnerf-grid mask`:
`foreground.predict_maps`, C = sum of softmax over {person, vehicle, bird}, M = [C > 0.5])
against the ground-truth distractor mask: IoU, precision, recall (pooled over all pixels of
all frames, and the mean per frame).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from experiments.mask_tower_overlap import visible_tower  # noqa: E402
from jaxnerf_grid.masks import dpt  # noqa: E402
from jaxnerf_grid.masks import foreground as fg
from jaxnerf_grid.masks.foreground import SYNTHETIC_DYNAMIC  # noqa: E402
from jaxnerf_grid.train import optim
from jaxnerf_grid.util import io

H, W = 128, 160
NUM_CLASSES = 9
CONFIG = dpt.DPTConfig(
    hidden_size=64, num_hidden_layers=4, num_attention_heads=4, intermediate_size=128, layer_norm_eps=1e-6,
    image_size=128, patch_size=8, backbone_out_indices=(0, 1, 2, 3), readout_type="project",
    reassemble_factors=(4, 2, 1, 0.5), neck_hidden_sizes=(16, 32, 48, 64), fusion_hidden_size=16,
    use_batch_norm_in_fusion_residual=False, use_auxiliary_head=False, num_labels=NUM_CLASSES,
    heads=("segmentation", "depth"),
    id2label=("sky", "tower", "conductor", "ground", "vegetation", "building", "person", "vehicle", "bird"))


def load_scene(root: Path):
    """-> images [N, H, W, 3], labels [N, H, W] int32, inverse depth [N, H, W] at the working size."""
    import cv2

    meta = io.read_json(root / "transforms.json")
    imgs, labels, invs = [], [], []
    for f in meta["frames"]:
        if "semantic_file_path" not in f:
            continue
        img = io.read_image(root / f["file_path"])
        sem = cv2.imread(str(root / f["semantic_file_path"]), cv2.IMREAD_UNCHANGED)
        depth = io.read_exr(root / f["depth_file_path"])
        inv = np.where(np.isfinite(depth) & (depth > 0), 1.0 / np.maximum(depth, 1e-6), 0.0)
        imgs.append(fg.resize_map(img, H, W))
        labels.append(cv2.resize(sem, (W, H), interpolation=cv2.INTER_NEAREST))
        invs.append(cv2.resize(inv.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR))
    return np.stack(imgs), np.stack(labels).astype(np.int32), np.stack(invs).astype(np.float32)


def make_loss(class_weights, cfg):
    cw = jnp.asarray(class_weights, jnp.float32)

    def loss_fn(params, x, labels, inv):
        out = dpt.forward(params, cfg, x)
        logp = jax.nn.log_softmax(out["logits"], axis=-1)
        onehot = jax.nn.one_hot(labels, NUM_CLASSES)
        w = cw[labels]
        ce = -jnp.sum(w * jnp.sum(onehot * logp, axis=-1)) / jnp.sum(w)
        l1 = jnp.mean(jnp.abs(out["depth"] - inv))
        acc = jnp.mean(jnp.argmax(logp, axis=-1) == labels)
        return ce + 0.5 * l1, {"ce": ce, "l1": l1, "acc": acc}

    return loss_fn


def count_scores(tp: float, fp: float, fn: float) -> dict:
    """{tp, fp, fn, iou, precision, recall} from pixel counts (of one frame or summed over many)."""
    return {"tp": tp, "fp": fp, "fn": fn,
            "iou": tp / max(tp + fp + fn, 1.0), "precision": tp / max(tp + fp, 1.0),
            "recall": tp / max(tp + fn, 1.0)}


def mask_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """`count_scores` of one predicted mask against its ground truth, both [H, W] bool."""
    return count_scores(float(np.sum(pred & gt)), float(np.sum(pred & ~gt)), float(np.sum(~pred & gt)))


def pooled_scores(totals: dict) -> dict:
    """IoU / precision / recall / tower_covered from pixel counts summed over frames
    ({tp, fp, fn, tower, tower_masked})."""
    return {**count_scores(totals["tp"], totals["fp"], totals["fn"]),
            "tower_covered": totals["tower_masked"] / max(totals["tower"], 1.0)}


def evaluate(model, roots, threshold=0.5, max_side=160, tiles=1) -> dict:
    """Masks M = [C > threshold] of held-out scenes against their ground truth: IoU, precision,
    recall pooled over all pixels (and per scene, `by_scene`) and as a mean per frame, and
    tower_covered (the share of the visible tower / conductor pixels that M covers: training
    signal the tower would lose). One DPT pass over every frame."""
    keys = ("tp", "fp", "fn", "tower", "tower_masked")
    by_scene, per_frame = {}, []
    for root in roots:
        totals = dict.fromkeys(keys, 0.0)
        meta = io.read_json(root / "transforms.json")
        frames = [f for f in meta["frames"] if "distractor_mask_path" in f]
        imgs = (io.read_image(root / f["file_path"]) for f in frames)
        for f, (prob, _inv) in zip(frames, fg.predict_maps(model, model, imgs, sorted(SYNTHETIC_DYNAMIC),
                                                           max_side=max_side, batch_size=8, tiles=tiles)):
            gt = io.read_distractor_mask(root / f["distractor_mask_path"])
            pred = np.asarray(fg.binary_mask(prob, threshold)).astype(bool)
            m = mask_metrics(pred, gt)
            per_frame.append(m)
            for k in ("tp", "fp", "fn"):
                totals[k] += m[k]
            if "semantic_file_path" in f:  # the visible tower pixels the mask takes from training
                semantic, _ = io.decode_raw(root / f["semantic_file_path"], "semantic map")
                tower = visible_tower(semantic, gt)
                totals["tower"] += float(tower.sum())
                totals["tower_masked"] += float((tower & pred).sum())
        by_scene[root.name] = totals
    pooled = pooled_scores({k: sum(t[k] for t in by_scene.values()) for k in keys})
    mean = {k: float(np.mean([m[k] for m in per_frame])) for k in ("iou", "precision", "recall")}
    return {"pooled": pooled, "mean_per_frame": mean, "num_frames": len(per_frame),
            "threshold": threshold, "max_side": max_side, "tiles": tiles,
            "by_scene": {name: pooled_scores(t) for name, t in by_scene.items()}}


def score_row(name: str, m: dict) -> str:
    """A markdown table row: name | IoU | precision | recall | tower covered."""
    return f"| {name} | {m['iou']:.3f} | {m['precision']:.3f} | {m['recall']:.3f} | {m['tower_covered']:.3f} |"


def evaluate_only(weights: Path, eval_roots: list[Path], eval_seeds: list, results: Path) -> int:
    """Scores a trained DPT on held-out scenes, pooled and per scene; writes results.json / .md."""
    model = dpt.load_pretrained(str(weights))
    metrics = evaluate(model, eval_roots)
    by_scene = metrics.pop("by_scene")
    result = {"weights": str(weights), "eval_seeds": eval_seeds, "metrics": metrics, "metrics_by_scene": by_scene}
    results.parent.mkdir(parents=True, exist_ok=True)
    results.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    rows = [("all", metrics["pooled"])] + list(by_scene.items())
    md = [f"# DPT masks of `{weights}` on held-out scenes (seeds {eval_seeds})", "",
          "| scenes | IoU | precision | recall | tower covered |", "|---|---|---|---|---|"]
    md += [score_row(name, m) for name, m in rows]
    results.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train", nargs="+", help="training scenes (required unless --eval-weights)")
    p.add_argument("--eval", nargs="+", required=True)
    p.add_argument("--eval-weights", metavar="DIR",
                   help="no training: evaluate the DPT in DIR (e.g. the shipped jaxnerf_grid/masks/assets/dpt_builtin) "
                        "on the --eval scenes and write --results")
    p.add_argument("--steps", type=int, default=1600, help="the learning-rate schedule spans these steps")
    p.add_argument("--minutes", type=float, default=45.0, help="stop early after this much training time")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--patch-size", type=int, default=CONFIG.patch_size,
                   help="ViT patch size (8: a 20x16 token grid at the working size; 16: 10x8, about 1/3 of the cost)")
    p.add_argument("--init", metavar="DIR", default=None,
                   help="start from the DPT in DIR (e.g. the shipped model, to fine-tune it on more scenes) "
                        "instead of a random initialisation; its config wins over --patch-size")
    p.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "jaxnerf_grid/masks/assets/dpt_builtin"))
    p.add_argument("--results", default=str(Path(__file__).resolve().parent / "results/builtin_dpt"))
    args = p.parse_args(argv)
    eval_roots = [Path(r) for r in args.eval]
    seeds = lambda roots: [io.read_json(r / "transforms.json").get("generator", {}).get("seed") for r in roots]  # noqa: E731
    if args.eval_weights:
        return evaluate_only(Path(args.eval_weights), eval_roots, seeds(eval_roots), Path(args.results))
    if not args.train:
        p.error("--train is required (or --eval-weights DIR to evaluate a trained model)")
    train_roots = [Path(r) for r in args.train]
    train_seeds = seeds(train_roots)
    if set(train_seeds) & {7101, 7102, 7103, 7104}:
        raise SystemExit(f"training seeds {train_seeds} include a held-out seed (7101+)")

    t_start = time.time()
    data = [load_scene(r) for r in train_roots]
    x_all = np.concatenate([d[0] for d in data])
    y_all = np.concatenate([d[1] for d in data])
    inv_all = np.concatenate([d[2] for d in data])
    freq = np.bincount(y_all.ravel(), minlength=NUM_CLASSES).astype(np.float64) / y_all.size
    class_weights = np.clip(1.0 / np.sqrt(np.maximum(freq, 1e-4)), 1.0, 30.0)
    class_weights /= class_weights[freq > 0].min()
    print(f"{len(x_all)} training images from seeds {train_seeds}; class freq {np.round(freq, 4).tolist()}")

    if args.init:
        model = dpt.load_pretrained(args.init)
        cfg = model.config
        if cfg.num_labels != NUM_CLASSES or "depth" not in cfg.heads:
            raise SystemExit(f"--init {args.init}: not a built-in-style DPT ({cfg.num_labels} labels, heads "
                             f"{cfg.heads}; need {NUM_CLASSES} labels and a depth head)")
    else:
        cfg = dataclasses.replace(CONFIG, patch_size=args.patch_size)
        model = dpt.init(args.seed, cfg)
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float32), model.params)
    opt = optim.adam(optim.make_lr_schedule(args.lr, args.lr * 0.03, warmup_steps=100, max_steps=args.steps),
                     max_grad_norm=1.0)
    solver = optim.make_solver(make_loss(class_weights, cfg), opt)
    rng = np.random.default_rng(args.seed)

    def batch():
        idx = rng.choice(len(x_all), args.batch, replace=False)
        x, y, inv = x_all[idx], y_all[idx], inv_all[idx]
        flip = rng.uniform(size=args.batch) < 0.5
        x = np.where(flip[:, None, None, None], x[:, :, ::-1], x)
        y = np.where(flip[:, None, None], y[:, :, ::-1], y)
        inv = np.where(flip[:, None, None], inv[:, :, ::-1], inv)
        return jnp.asarray(dpt.normalize(x)), jnp.asarray(y), jnp.asarray(inv)

    b = batch()
    state = solver.init_state(params, *b)
    step_fn = jax.jit(lambda prm, st, x, y, inv: optim.guarded_update(solver, prm, st, x, y, inv))
    log = []
    t_train = time.time()
    step = 0
    from tqdm import tqdm

    bar = tqdm(total=args.steps, desc="train builtin DPT")
    while step < args.steps and (time.time() - t_train) < args.minutes * 60:
        params, state, aux, finite = step_fn(params, state, *batch())
        step += 1
        bar.update(1)
        if step % 50 == 0 or step == 1:
            rec = {"step": step, "loss": float(state.value), **{k: float(v) for k, v in aux.items()},
                   "finite": bool(finite), "elapsed_s": time.time() - t_train}
            log.append(rec)
            bar.set_postfix(loss=f"{rec['loss']:.3f}", acc=f"{rec['acc']:.3f}")
    bar.close()
    train_s = time.time() - t_train
    trained = dpt.Model(cfg, jax.tree_util.tree_map(np.asarray, params))

    extra = {"dynamic_classes": sorted(SYNTHETIC_DYNAMIC), "trained_on_seeds": train_seeds, "init": args.init,
             "steps": step, "max_side": max(H, W),
             "note": "trained by experiments/train_builtin_dpt.py on synthetic tower scenes; "
                                    "inputs are resized to a working size with longest side ~160 px"}
    dpt.save(trained, args.out, dtype="float16", extra=extra)
    reloaded = dpt.load_pretrained(args.out)  # evaluate exactly what ships (float16 weights)
    for r in eval_roots:  # held-out scenes may still be rendering while training runs
        while not (r / "transforms.json").is_file():
            time.sleep(10)
    eval_seeds = seeds(eval_roots)
    if set(train_seeds) & set(eval_seeds):
        raise SystemExit(f"training seeds {train_seeds} overlap evaluation seeds {eval_seeds}")
    metrics = evaluate(reloaded, eval_roots)
    by_scene = metrics.pop("by_scene")
    by_scene = by_scene if len(eval_roots) > 1 else {}  # one scene: its row would repeat the pooled one
    size_bytes = sum(f.stat().st_size for f in Path(args.out).iterdir())
    result = {"train_seeds": train_seeds, "eval_seeds": eval_seeds, "init": args.init, "lr": args.lr,
              "num_train_images": int(len(x_all)),
              "steps": step, "batch": args.batch, "train_seconds": train_s,
              "total_seconds": time.time() - t_start, "weights_bytes": size_bytes,
              "num_params": int(sum(np.size(v) for v in jax.tree_util.tree_leaves(trained.params))),
              "config": {k: v for k, v in json.loads(json.dumps(dataclasses.asdict(cfg))).items()},
              "metrics": metrics, "metrics_by_scene": by_scene, "log": log}
    res = Path(args.results)
    res.parent.mkdir(parents=True, exist_ok=True)
    res.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    pm, mm = metrics["pooled"], metrics["mean_per_frame"]
    md = [
        "# Built-in DPT: distractor masks on held-out synthetic scenes",
        "",
        f"Trained by `experiments/train_builtin_dpt.py` on {len(x_all)} images from training seeds "
        f"{train_seeds}; evaluated on {metrics['num_frames']} frames of held-out seeds {eval_seeds} "
        f"(disjoint). {step} Adam steps (jaxopt OptaxSolver), batch {args.batch}, peak learning rate {args.lr:g}, "
        + (f"starting from the DPT in `{args.init}`, " if args.init else "from a random initialisation, ") +
        f"{train_s / 60:.1f} min of training on this CPU ({result['total_seconds'] / 60:.1f} min in all). "
        f"Weights: {result['num_params']} parameters, {size_bytes / 1e6:.2f} MB (float16) in "
        f"`{args.out}`; ViT patch size {cfg.patch_size}.",
        "",
        "Mask M = [C > 0.5], C = softmax mass on {person, vehicle, bird}, computed at a 160x128 working size "
        "and upsampled to 160x120, against the ground-truth distractor mask (bit 0):",
        "",
        "| | IoU | precision | recall | tower covered |",
        "|---|---|---|---|---|",
        score_row("pooled over all pixels", pm),
        f"| mean per frame | {mm['iou']:.3f} | {mm['precision']:.3f} | {mm['recall']:.3f} | |",
        *[score_row(f"{name} (pooled)", m) for name, m in by_scene.items()],
        "",
        f"Final training loss {log[-1]['loss']:.3f} (cross-entropy {log[-1]['ce']:.3f}, inverse-depth L1 "
        f"{log[-1]['l1']:.3f}, pixel accuracy {log[-1]['acc']:.3f} on the last batch).",
    ]
    res.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
