"""Train the built-in DPT on the mixed data of `experiments/dpt_data.py` (synthetic frames of every
preset and clutter level, synthetic distractors pasted on real photos, static real photos with
empty masks), under a wall-time budget, keeping the best checkpoint on a validation set.

    python -m experiments.train_dpt_mix --cache CACHE.npz [--scenes DIR ...] [--real DIR ...]
        [--val-cache VAL.npz] [--arch base-like] [--max-side 160] [--minutes 6] [--steps 6000]
        [--batch 32] [--lr 1e-3] [--out DIR] [--log-dir DIR]

With --scenes (and optionally --real, folders of photos: never commit them) the cache is built
first (`dpt_data.build_cache`); without --real it is synthetic only. Without --val-cache the
validation frames are drawn once, with a fixed seed, from the training cache (augmented, with
their own pasting: a check of fit, not of generalisation).

Model (`ARCHS`): "small" is the shipped model's shape (patch 8, 4 layers of width 64, fusion 16);
"base-like" keeps DPT-base's structure (ViT encoder, readout "project", reassemble x4 / x2 / x1 /
x0.5 at four depths spread like DPT-base's 2, 5, 8, 11, four fusion stages) at 8 layers of width
128 (4 heads, MLP 512), neck widths 32 / 64 / 96 / 128 and fusion width 32: DPT-base's 12 x 768
would be 100+ M parameters, neither committable nor fast enough on the CPU.

Loss: class-weighted cross-entropy over the 9 synthetic classes where the class is known; on a
real photo's static pixels (class unknown) -log(1 - C), C the softmax mass on {person, vehicle,
bird}, so they may be any static class but not a transient; 0.5 * L1 on inverse depth where
depth is known (synthetic frames). Adam (`jaxnerf_grid.train.optim.adam`) at a rate the host sets per step:
warm-up, then log-linear decay along the larger of the step fraction and the time fraction.

Writes: the best checkpoint (float16, `dpt.save`) to --out; to --log-dir: train_log.json (the
loss curve, validation scores, step rate, settings), loss_curve.png and train.log.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from experiments import dpt_data, mask_scores
from jaxnerf_grid.masks.foreground import SYNTHETIC_DYNAMIC

ROOT = Path(__file__).resolve().parents[1]
ID2LABEL = ("sky", "tower", "conductor", "ground", "vegetation", "building", "person", "vehicle", "bird")


def arch_config(name: str, max_side: int):
    """The DPTConfig of an architecture name (module docstring), position embeddings at max_side."""
    from jaxnerf_grid.masks import dpt

    common = dict(layer_norm_eps=1e-6, patch_size=8, readout_type="project", reassemble_factors=(4, 2, 1, 0.5),
                  use_batch_norm_in_fusion_residual=False, use_auxiliary_head=False,
                  num_labels=dpt_data.NUM_CLASSES, heads=("segmentation", "depth"), id2label=ID2LABEL,
                  image_size=max_side - max_side % 8)
    if name == "small":
        return dpt.DPTConfig(hidden_size=64, num_hidden_layers=4, num_attention_heads=4, intermediate_size=128,
                             backbone_out_indices=(0, 1, 2, 3), neck_hidden_sizes=(16, 32, 48, 64),
                             fusion_hidden_size=16, **common)
    if name == "base-like":
        return dpt.DPTConfig(hidden_size=128, num_hidden_layers=8, num_attention_heads=4, intermediate_size=512,
                             backbone_out_indices=(1, 3, 5, 7), neck_hidden_sizes=(32, 64, 96, 128),
                             fusion_hidden_size=32, **common)
    raise SystemExit(f"--arch: unknown architecture {name!r}; choose small or base-like")


ARCHS = ("small", "base-like")


def class_weights(labels: np.ndarray) -> np.ndarray:
    """[NUM_CLASSES] float32 loss weights from the synthetic labels' frequencies: 1 / sqrt(freq),
    clipped to [1, 30], the most common class 1 (absent classes get the largest weight)."""
    freq = np.bincount(labels.ravel(), minlength=dpt_data.STATIC_UNKNOWN + 1)[:dpt_data.NUM_CLASSES]
    freq = freq.astype(np.float64) / max(freq.sum(), 1)
    w = np.clip(1.0 / np.sqrt(np.maximum(freq, 1e-4)), 1.0, 30.0)
    present = freq > 0
    return (w / (w[present].min() if present.any() else 1.0)).astype(np.float32)


def make_loss(weights: np.ndarray, cfg):
    """loss_fn(params, x [B, H, W, 3] normalised, y [B, H, W] int (0-8, or STATIC_UNKNOWN), inv [B, H, W],
    has_depth [B]) -> (loss, aux {ce, static, l1, acc}); module docstring."""
    import jax
    import jax.numpy as jnp

    from jaxnerf_grid.masks import dpt

    cw = jnp.asarray(np.append(weights, 1.0), jnp.float32)   # the unknown-static pixels weigh 1
    dyn = np.zeros(dpt_data.NUM_CLASSES, bool)
    dyn[list(dpt_data.DYNAMIC)] = True

    def loss_fn(params, x, y, inv, has_depth):
        out = dpt.forward(params, cfg, x)
        logits = out["logits"]
        lse = jax.nn.logsumexp(logits, axis=-1)
        known = y < dpt_data.NUM_CLASSES
        logp_y = jnp.take_along_axis(logits, jnp.minimum(y, dpt_data.NUM_CLASSES - 1)[..., None], -1)[..., 0] - lse
        log_static = jax.nn.logsumexp(jnp.where(dyn, -jnp.inf, logits), axis=-1) - lse   # log(1 - C)
        w = cw[y]
        nll = jnp.where(known, -logp_y, -log_static)
        loss_seg = jnp.sum(w * nll) / jnp.sum(w)
        ce = jnp.sum(jnp.where(known, w * nll, 0)) / jnp.maximum(jnp.sum(jnp.where(known, w, 0)), 1e-6)
        static = jnp.sum(jnp.where(known, 0, nll)) / jnp.maximum(jnp.sum(~known), 1)
        dmask = has_depth[:, None, None].astype(jnp.float32)
        l1 = jnp.sum(dmask * jnp.abs(out["depth"] - inv)) / jnp.maximum(jnp.sum(dmask) * x.shape[1] * x.shape[2], 1.0)
        acc = jnp.sum(known * (jnp.argmax(logits, -1) == y)) / jnp.maximum(jnp.sum(known), 1)
        return loss_seg + 0.5 * l1, {"ce": ce, "static": static, "l1": l1, "acc": acc}

    return loss_fn


def working_hw(height: int, width: int, max_side: int, patch: int) -> tuple[int, int]:
    """The training crop (h, w): the cache frames' aspect at the working size (`foreground.working_size`)."""
    from jaxnerf_grid.masks.foreground import working_size

    return working_size(height, width, max_side, 2 * patch)


class Prefetcher:
    """Batches made by `workers` threads (numpy / OpenCV release the GIL) into a small queue."""

    def __init__(self, make, workers: int = 4, depth: int = 8):
        self.q, self.stop = queue.Queue(depth), threading.Event()
        self.threads = [threading.Thread(target=self._run, args=(make, i), daemon=True) for i in range(workers)]
        for t in self.threads:
            t.start()

    def _run(self, make, i):
        import cv2

        cv2.setNumThreads(1)   # parallel across batches, not inside one OpenCV call
        rng = np.random.default_rng([i, int(time.time() * 1e3) % 2**31])
        while not self.stop.is_set():
            b = make(rng)
            while not self.stop.is_set():
                try:
                    self.q.put(b, timeout=0.5)
                    break
                except queue.Full:
                    continue

    def get(self):
        return self.q.get()

    def close(self):
        self.stop.set()


_MASK_FNS: dict = {}


def _mask_fn(cfg):
    """A jitted (params, x [B, H, W, 3] in [0, 1]) -> (M, argmax class), one per config (compiled once)."""
    import jax

    from jaxnerf_grid.masks import dpt

    if cfg not in _MASK_FNS:
        def fwd(p, xb):
            logits = dpt.forward(p, cfg, dpt.normalize(xb))["logits"]
            c = jax.nn.softmax(logits, -1)[..., list(dpt_data.DYNAMIC)].sum(-1)
            return c > 0.5, logits.argmax(-1)
        _MASK_FNS[cfg] = jax.jit(fwd)
    return _MASK_FNS[cfg]


def predict_masks(params, cfg, x: np.ndarray, batch: int = 16):
    """(M [N, H, W] bool = [C > 0.5], argmax class [N, H, W]) for images x [N, H, W, 3] in [0, 1]."""
    fwd = _mask_fn(cfg)
    ms, cs = [], []
    for i in range(0, len(x), batch):
        m, c = fwd(params, x[i:i + batch])
        ms.append(np.asarray(m)), cs.append(np.asarray(c))
    return np.concatenate(ms), np.concatenate(cs)


def val_scores(params, cfg, val: dict) -> dict:
    """`mask_scores.scores` of the model on the validation frames (unknown-static pixels count as not
    distractor), plus "static_share": the share of pixels masked on the empty real photos."""
    pred, cls = predict_masks(params, cfg, val["x"])
    total = None
    for p, y, c in zip(pred, val["y"], cls):
        total = mask_scores.add_counts(total, mask_scores.frame_counts(p, y, SYNTHETIC_DYNAMIC, c))
    s = mask_scores.scores(total)
    empty = val["kind"] == 2
    s["static_share"] = float(pred[empty].mean()) if empty.any() else None
    return s


def val_set(cache: dict, sprites, out_hw, n: int, seed: int = 12345) -> dict:
    """n validation frames drawn once from a cache with a fixed seed (`dpt_data.sample_batch`)."""
    return dpt_data.sample_batch(cache, sprites, n, out_hw, np.random.default_rng(seed))


def save_curve_png(log: list[dict], vals: list[dict], path: Path) -> None:
    """loss_curve.png: training loss (and its terms) against step; validation IoU on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    steps = [r["step"] for r in log]
    for k in ("loss", "ce", "static", "l1"):
        ax.plot(steps, [r[k] for r in log], label=k)
    ax.set_xlabel("step"), ax.set_ylabel("training loss"), ax.set_yscale("log")
    ax.legend(loc="upper left")
    if vals:
        ax2 = ax.twinx()
        ax2.plot([v["step"] for v in vals], [v["iou"] or 0 for v in vals], "k.-", label="val IoU")
        ax2.set_ylabel("validation IoU"), ax2.set_ylim(0, 1)
        ax2.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", required=True, help="the data cache .npz (built first when --scenes is given)")
    p.add_argument("--scenes", nargs="*", default=[], help="synth training scenes (seeds 7001-7099)")
    p.add_argument("--real", nargs="*", default=[], help="folders of static real photos (optional)")
    p.add_argument("--val-cache", default=None, help="a cache of held-out scenes / photos for the best checkpoint")
    p.add_argument("--arch", default="base-like", choices=ARCHS)
    p.add_argument("--init", default=None, help="start from the DPT in this folder instead of a random one")
    p.add_argument("--max-side", type=int, default=160, help="working size (longest side) of training and of `mask`")
    p.add_argument("--minutes", type=float, default=6.0, help="wall-time budget of the training loop")
    p.add_argument("--steps", type=int, default=20000, help="at most this many steps (the rate decays along the "
                   "larger of the step and the time fraction)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--val-every", type=float, default=30.0, help="seconds between validations")
    p.add_argument("--val-frames", type=int, default=96)
    p.add_argument("--workers", type=int, default=4, help="threads making batches")
    p.add_argument("--out", default=str(ROOT / "jaxnerf_grid/masks/assets/dpt_builtin"))
    p.add_argument("--log-dir", default="dpt_train_out")
    args = p.parse_args(argv)

    log_dir = Path(args.log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    log_file = open(log_dir / "train.log", "a")

    def say(msg: str) -> None:
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        log_file.write(line + "\n")
        log_file.flush()

    if args.scenes:
        say("building the data cache: " + json.dumps(dpt_data.build_cache(
            [Path(s) for s in args.scenes], [Path(d) for d in args.real], Path(args.cache))))
    elif args.real:
        raise SystemExit("--real needs --scenes (the cache is built from both); or build the cache with "
                         "python -m experiments.dpt_data")

    import jax
    import jax.numpy as jnp

    from jaxnerf_grid.masks import dpt
    from jaxnerf_grid.train import optim

    say(f"jax {jax.__version__}, devices {jax.devices()}")
    cache = dpt_data.load_cache(args.cache)
    sprites = dpt_data.unpack_sprites(cache)
    out_hw = working_hw(*cache["syn_x"].shape[1:3] if len(cache["syn_x"]) else cache["real_x"].shape[1:3],
                        args.max_side, 8)
    say(f"cache {args.cache}: {len(cache['syn_x'])} synthetic frames, {len(cache['real_x'])} real photos, "
        f"{len(sprites)} sprites; training crops {out_hw[0]}x{out_hw[1]}")
    if args.val_cache:
        vc = dpt_data.load_cache(args.val_cache)
        val = val_set(vc, dpt_data.unpack_sprites(vc) or sprites, out_hw, args.val_frames)
    else:
        val = val_set(cache, sprites, out_hw, args.val_frames)

    if args.init:
        model = dpt.load_pretrained(args.init)
        cfg = model.config
    else:
        cfg = arch_config(args.arch, args.max_side)
        model = dpt.init(args.seed, cfg)
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float32), model.params)
    num_params = int(sum(np.size(v) for v in jax.tree_util.tree_leaves(params)))
    weights = class_weights(cache["syn_y"])
    say(f"arch {args.arch if not args.init else args.init}: {num_params} parameters; class weights "
        f"{np.round(weights, 2).tolist()}")
    loss_fn = make_loss(weights, cfg)
    opt = optim.adam(1.0, max_grad_norm=1.0)   # unit rate: the host passes each step's rate (`lr_at`)
    opt_state = opt.init(params)

    def train_step(prm, st, lr, *b):
        """One Adam step at rate lr, rolled back when the loss or the new params are not finite."""
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(prm, *b)
        updates, new_st = opt.update(grads, st, prm)
        new_prm = jax.tree_util.tree_map(lambda v, u: v + lr * u, prm, updates)
        finite = jnp.isfinite(loss) & optim.tree_all_finite(new_prm)
        pick = lambda a, b: jax.tree_util.tree_map(lambda u, v: jnp.where(finite, u, v), a, b)  # noqa: E731
        return pick(new_prm, prm), pick(new_st, st), loss, aux, finite

    def make(rng):
        b = dpt_data.sample_batch(cache, sprites, args.batch, out_hw, rng)
        return dpt.normalize(b["x"]), b["y"].astype(np.int32), b["inv"], b["has_depth"]

    pre = Prefetcher(make, workers=args.workers)
    first = pre.get()
    step_fn = jax.jit(train_step)
    log, vals, best = [], [], {"iou": -1.0, "step": 0, "params": None}
    t_start = t0 = time.time()
    budget = args.minutes * 60.0
    step, skipped, s_rate = 0, 0, 0

    def save_best():
        extra = {"dynamic_classes": list(dpt_data.DYNAMIC), "max_side": args.max_side, "steps": step,
                 "best_step": best["step"], "arch": args.arch if not args.init else None,
                 "note": "trained by experiments/train_dpt_mix.py on synthetic tower scenes of every preset and "
                         "clutter level, synthetic distractors pasted on real photos and static real photos; inputs "
                         f"are resized to a working size with longest side ~{args.max_side} px"}
        dpt.save(dpt.Model(cfg, best["params"]), args.out, dtype="float16", extra=extra)

    def validate():
        s = val_scores(params, cfg, val)
        s["step"], s["elapsed_s"] = step, time.time() - t0
        vals.append(s)
        iou = s["iou"] or 0.0
        if iou > best["iou"]:
            best.update(iou=iou, step=step, params=jax.tree_util.tree_map(np.asarray, params))
            save_best()   # on disk at once: a run cut short by a timeout still leaves its best weights
        say(f"step {step}: val IoU {iou:.3f} precision {s['precision'] or 0:.3f} recall {s['recall'] or 0:.3f} "
            f"bird recall {s['class']['bird']['recall'] or 0:.3f} static share {s['static_share']}; "
            f"best {best['iou']:.3f} at step {best['step']}")

    def lr_at(step: int, now: float) -> float:
        """Warm-up over the first 3 %, then log-linear decay to 3 % of --lr, along the larger of the
        step fraction and the time fraction (the budget, not a step count, usually ends training)."""
        progress = max(step / args.steps, (now - t0) / budget) if budget > 0 else step / args.steps
        return float(optim.lr_schedule(1000.0 * min(progress, 1.0), args.lr, args.lr * 0.03, 30, 1000))

    say("compiling the training step")
    params, opt_state, loss, aux, finite = step_fn(params, opt_state, 0.0, *first)   # the compile, outside the budget
    jax.block_until_ready(params)
    step = 1
    t0 = last_val = t_rate = time.time()
    s_rate = 1
    say(f"compiled in {t0 - t_start:.0f} s; training for at most {budget:.0f} s")
    batch = pre.get()
    while step < args.steps and time.time() - t0 < budget:
        lr = lr_at(step, time.time())
        params, opt_state, loss, aux, finite = step_fn(params, opt_state, lr, *batch)
        batch = pre.get()
        step += 1
        if step % 25 == 0:
            finite = bool(finite)
            skipped += not finite
            now = time.time()
            rate = (step - s_rate) / max(now - t_rate, 1e-9)
            t_rate, s_rate = now, step
            rec = {"step": step, "loss": float(loss), **{k: float(v) for k, v in aux.items()},
                   "finite": finite, "lr": lr, "elapsed_s": now - t0, "steps_per_s": rate}
            log.append(rec)
            if step % 100 == 0 or step == 25:
                say(f"step {step}: loss {rec['loss']:.4f} (ce {rec['ce']:.3f}, static {rec['static']:.3f}, "
                    f"l1 {rec['l1']:.3f}, acc {rec['acc']:.3f}), lr {lr:.2e}, {rate:.2f} steps/s, "
                    f"{max(budget - (now - t0), 0):.0f} s of the budget left")
        if time.time() - last_val >= args.val_every and time.time() - t0 < budget:
            validate()
            last_val = time.time()
    pre.close()
    validate()
    train_s = time.time() - t0
    say(f"trained {step} steps in {train_s:.0f} s ({step / max(train_s, 1e-9):.2f} steps/s, batch {args.batch}); "
        f"{skipped} logged steps non-finite; best val IoU {best['iou']:.3f} at step {best['step']}")

    reloaded = dpt.load_pretrained(args.out)   # score exactly what ships (float16)
    as_f32 = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float32), reloaded.params)   # the compiled dtypes
    final = val_scores(as_f32, reloaded.config, val)
    size_bytes = sum(f.stat().st_size for f in Path(args.out).iterdir())
    say(f"saved {args.out} ({size_bytes / 1e6:.2f} MB): val IoU {final['iou'] or 0:.3f} (float16 weights)")
    result = {"settings": {k: v for k, v in vars(args).items()}, "devices": [str(d) for d in jax.devices()],
              "num_params": num_params, "weights_bytes": size_bytes, "steps": step, "train_seconds": train_s,
              "steps_per_s": step / max(train_s, 1e-9), "best_step": best["step"], "final_val": final,
              "config": json.loads(json.dumps(dataclasses.asdict(cfg))), "out_hw": list(out_hw),
              "cache": {"synthetic": int(len(cache["syn_x"])), "real": int(len(cache["real_x"])),
                        "sprites": len(sprites)},
              "log": log, "val": vals}
    (log_dir / "train_log.json").write_text(json.dumps(result, indent=1, default=str) + "\n")
    save_curve_png(log, vals, log_dir / "loss_curve.png")
    log_file.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
