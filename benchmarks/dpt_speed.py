"""Images/s of our JAX DPT vs transformers' torch DPT with identical weights, same CPU, 384x384.

Usage:
  JAX_PLATFORMS=cpu python -m benchmarks.dpt_speed [--arch base|large] [--task segmentation|depth]
      [--batch 1] [--iters 5] [--out benchmarks/results/dpt_speed.json]

A random-weight DPTForSemanticSegmentation (150 labels) or DPTForDepthEstimation is built with
transformers (arch "large" = Intel/dpt-large's shape: ViT-L/16, 24 layers; "base" = ViT-B/16,
12 layers, the DPTConfig default), saved in the HF layout, loaded with `dpt.load_pretrained`, and
both run on the same input. Timings exclude the first (compile / warm-up) call; the two
frameworks' calls are interleaved and the medians compared. The headline ratio is for what each
library does by default for the same returned output: HF's segmentation forward also runs the
auxiliary head and drops its output, ours skips it unless asked (`dpt.apply(..., auxiliary=True)`);
the ratio with that head run by both ("equal work") is reported too. Both frameworks
use every core of the machine (torch.set_num_threads(os.cpu_count())). Also records the max
difference between the two outputs and the machine's load average (the CI box is shared).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.modules.setdefault("torchvision", None)  # broken in the dev venv; transformers must not import it

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--arch", choices=["base", "large"], default="base")
    p.add_argument("--task", choices=["segmentation", "depth"], default="segmentation")
    p.add_argument("--size", type=int, default=384)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--iters", type=int, default=5)
    p.add_argument("--stages", action="store_true",
                   help="also time the encoder (ViT), the neck (reassemble + fusion) and the head separately")
    p.add_argument("--torch-device", default="cpu",
                   help="device for the torch reference: cpu, or cuda on a GPU machine (JAX then uses its default "
                        "backend, the GPU; timings synchronise both)")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "dpt_speed.json"))
    args = p.parse_args(argv)

    import jax
    import torch
    import transformers

    from jaxnerf_grid.masks import dpt

    torch.set_num_threads(os.cpu_count() or 1)
    kw = dict(num_labels=150)
    if args.arch == "large":
        kw.update(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, intermediate_size=4096,
                  backbone_out_indices=[5, 11, 17, 23], neck_hidden_sizes=[256, 512, 1024, 1024])
    cfg = transformers.DPTConfig(**kw)
    cls = transformers.DPTForSemanticSegmentation if args.task == "segmentation" else transformers.DPTForDepthEstimation
    torch.manual_seed(0)
    ref = cls(cfg).eval()
    with tempfile.TemporaryDirectory() as tmp:
        ref.save_pretrained(tmp)
        model = dpt.load_pretrained(tmp)

    x = np.random.default_rng(0).uniform(-1, 1, (args.batch, args.size, args.size, 3)).astype(np.float32)
    device = torch.device(args.torch_device)
    ref = ref.to(device)
    xt = torch.from_numpy(x).permute(0, 3, 1, 2).contiguous().to(device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    key = "logits_raw" if args.task == "segmentation" else "depth_raw"

    def run_torch():
        with torch.inference_mode():
            out = ref(pixel_values=xt)
        sync()
        return out.logits if args.task == "segmentation" else out.predicted_depth

    def run_jax():
        return jax.block_until_ready(dpt.apply(model, x)[key])

    def run_jax_aux():  # HF's forward also runs the auxiliary head (and drops it): the same work
        return jax.block_until_ready(dpt.apply(model, x, auxiliary=True)[key])

    equal_work = args.task == "segmentation" and cfg.use_auxiliary_head
    t0 = time.perf_counter()
    run_jax()
    compile_s = time.perf_counter() - t0
    if equal_work:
        run_jax_aux()
    run_torch()  # warm-up
    runs = [(run_jax, []), (run_torch, [])] + ([(run_jax_aux, [])] if equal_work else [])
    for _ in range(args.iters):  # interleaved, so all see the same (shared-machine) load
        for fn, acc in runs:
            t = time.perf_counter()
            fn()
            acc.append(time.perf_counter() - t)
    jax_all, torch_all = runs[0][1], runs[1][1]
    jax_s, torch_s = float(np.median(jax_all)), float(np.median(torch_all))
    a = np.asarray(run_jax())
    b = run_torch().cpu().numpy()
    b = b.transpose(0, 2, 3, 1) if b.ndim == 4 else b
    result = {
        "arch": args.arch, "task": args.task, "size": args.size, "batch": args.batch, "iters": args.iters,
        "jax_images_per_s": args.batch / jax_s, "torch_images_per_s": args.batch / torch_s,
        "ratio_jax_over_torch": torch_s / jax_s,
        # each torch call over the JAX call just before it: less sensitive to the shared machine's drift
        "ratio_median_of_pairs": float(np.median(np.asarray(torch_all) / np.asarray(jax_all))),
        "jax_skips_auxiliary_head": equal_work,
        "jax_median_s": jax_s, "torch_median_s": torch_s, "jax_times_s": jax_all, "torch_times_s": torch_all,
        "jax_first_call_s_incl_compile": compile_s,
        "max_abs_diff": float(np.max(np.abs(a - b))), "max_abs_ref": float(np.max(np.abs(b))),
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "loadavg_after": os.getloadavg(), "jax": jax.__version__, "torch": torch.__version__,
        "transformers": transformers.__version__, "torch_threads": torch.get_num_threads(),
        "torch_device": str(device), "jax_backend": jax.default_backend(),
        "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
    }
    if equal_work:
        aux_s = float(np.median(runs[2][1]))
        result.update(jax_with_aux_median_s=aux_s, jax_with_aux_times_s=runs[2][1],
                      ratio_equal_work=torch_s / aux_s)
    if args.stages:
        result["stages_s"] = stage_times(ref, model, x, xt, args.task, args.iters, sync)
        for name, t in result["stages_s"].items():
            print(f"  {name}: JAX {t['jax']:.3f} s, torch {t['torch']:.3f} s, ratio {t['torch'] / t['jax']:.2f}x")
    print(f"DPT-{args.arch} {args.task} {args.size}x{args.size} batch {args.batch}: "
          f"JAX {result['jax_images_per_s']:.3f} img/s, torch {result['torch_images_per_s']:.3f} img/s, "
          f"ratio {result['ratio_jax_over_torch']:.2f}x "
          f"(median of paired calls {result['ratio_median_of_pairs']:.2f}x; "
          f"goal >= 1.5x); max |diff| {result['max_abs_diff']:.2e}; "
          f"load avg {result['loadavg_after'][0]:.1f}")
    if equal_work:
        print(f"  (ours skips the auxiliary head, whose output HF computes and drops; with it, as equal work: "
              f"JAX {args.batch / result['jax_with_aux_median_s']:.3f} img/s, ratio {result['ratio_equal_work']:.2f}x)")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


def encoder_matmuls_only(params: dict, cfg, pixel_values) -> list:
    """Our ViT encoder with only its matmuls: the per-block linear layers and the two attention
    products, without softmax, GELU or LayerNorm (a timing lower bound; the numbers are meaningless)."""
    from jaxnerf_grid.masks.dpt import ops as layers
    from jaxnerf_grid.masks.dpt import vit

    x = vit.embed(params, cfg, pixel_values)
    b, n, d = x.shape
    heads = cfg.num_attention_heads
    split = lambda t: t.reshape(b, n, heads, d // heads).transpose(0, 2, 1, 3)  # noqa: E731
    outs = []
    for i, p in enumerate(params["blocks"][: max(cfg.backbone_out_indices) + 1]):
        q, k, v = (split(layers.linear(p[name], x)) for name in "qkv")
        attended = ((q @ k.swapaxes(-1, -2)) @ v).transpose(0, 2, 1, 3).reshape(b, n, d)
        x = x + layers.linear(p["o"], attended)
        x = x + layers.linear(p["fc2"], layers.linear(p["fc1"], x))
        if i in cfg.backbone_out_indices:
            outs.append(x)
    return outs


def stage_times(ref, model, x, xt, task: str, iters: int, sync=lambda: None) -> dict:
    """Median seconds per stage, {stage: {"jax": s, "torch": s}}, the two frameworks interleaved.
    Stages: encoder (embeddings + ViT blocks), encoder_matmuls_only (ours only; its torch column is
    torch's whole encoder), neck (reassemble + fusion), head. (Our neck stops
    before the last fusion stage's x2 upsampling, which our head folds into its first conv;
    HF's neck includes it.)"""
    import jax
    import torch

    from jaxnerf_grid.masks.dpt import fusion, heads, reassemble, vit

    cfg = model.config
    p = model.params
    gh, gw = x.shape[1] // cfg.patch_size, x.shape[2] // cfg.patch_size
    head_name, head_fn = ("segmentation", heads.segmentation) if task == "segmentation" else ("depth", heads.depth)
    enc = jax.jit(lambda q, v: vit.apply(q, cfg, v))
    neck = jax.jit(lambda q, h: fusion.apply(q["fusion"], reassemble.apply(q["reassemble"], cfg, h, gh, gw)))
    head = jax.jit(lambda q, f: head_fn(q, f))
    hidden = enc(p["vit"], x)
    fused = neck(p, hidden)[cfg.head_in_index]
    with torch.inference_mode():
        hs = ref.dpt(xt, output_hidden_states=True).hidden_states
        t_hidden = [hs[i + 1] for i in cfg.backbone_out_indices]
        t_fused = ref.neck(list(t_hidden), gh, gw)
    t_head = ref.head
    enc_mm = jax.jit(lambda q, v: encoder_matmuls_only(q, cfg, v))
    pairs = {
        "encoder": (lambda: enc(p["vit"], x), lambda: ref.dpt(xt, output_hidden_states=True)),
        # a lower bound for our encoder: the same matmuls with softmax, GELU and LayerNorm removed
        # (its "torch" column is torch's whole encoder again)
        "encoder_matmuls_only": (lambda: enc_mm(p["vit"], x), lambda: ref.dpt(xt, output_hidden_states=True)),
        "neck": (lambda: neck(p, hidden), lambda: ref.neck(list(t_hidden), gh, gw)),
        "head": (lambda: head(p[head_name], fused), lambda: t_head(t_fused)),
    }
    out = {}
    for name, (fj, ft) in pairs.items():
        tj, tt = [], []
        jax.block_until_ready(fj())
        for _ in range(max(iters, 3)):
            t = time.perf_counter()
            jax.block_until_ready(fj())
            tj.append(time.perf_counter() - t)
            with torch.inference_mode():
                t = time.perf_counter()
                ft()
                sync()
                tt.append(time.perf_counter() - t)
        out[name] = {"jax": float(np.median(tj)), "torch": float(np.median(tt))}
    return out


if __name__ == "__main__":
    sys.exit(main())
