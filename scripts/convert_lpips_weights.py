#!/usr/bin/env python
"""Convert the `lpips` package's AlexNet LPIPS (v0.1) into the .npz that
`jaxnerf_grid.eval.lpips.load_lpips` reads.

Run it once, on a machine that has torch, torchvision and the `lpips` package, with torchvision's
ImageNet AlexNet weights available (downloaded or already in the torch hub cache); the linear
layers come from the lpips wheel itself (lpips/weights/v0.1/alex.pth):

    python scripts/convert_lpips_weights.py lpips_alex_v0.1.npz

then pass that file to the metrics (e.g. `load_lpips("lpips_alex_v0.1.npz")`). The script checks
the conversion by comparing the torch and JAX distances on random image pairs.
Key layout of the output: see the docstring of `jaxnerf_grid/eval/lpips.py`.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

# index of each conv layer in torchvision's AlexNet `.features`
_FEATURE_INDEX_TO_CONV = {0: "conv1", 3: "conv2", 6: "conv3", 8: "conv4", 10: "conv5"}


def arrays_from_torch_lpips(model) -> dict[str, np.ndarray]:
    """Weights of an `lpips.LPIPS(net='alex', version='0.1')` module as the .npz key layout.

    The trunk lives in `net.slice{1..5}.{features index}.{weight,bias}`, the linear layers in
    `lin{0..4}.model.{0|1}.weight` (index 1 when a Dropout precedes the conv).
    """
    if getattr(model, "pnet_type", "alex") != "alex":
        raise ValueError(f"only the AlexNet LPIPS is supported, got net='{model.pnet_type}'")
    if getattr(model, "version", "0.1") != "0.1":
        raise ValueError(f"only LPIPS v0.1 is supported, got version {model.version}")
    from jaxnerf_grid.eval import lpips as jl

    state = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in model.state_dict().items()}
    out: dict[str, np.ndarray] = {}
    for key, value in state.items():
        m = re.fullmatch(r"net\.slice\d+\.(\d+)\.(weight|bias)", key)
        if m:
            out[f"{_FEATURE_INDEX_TO_CONV[int(m.group(1))]}.{m.group(2)}"] = value
            continue
        m = re.fullmatch(r"lin(\d+)\.model\.\d+\.weight", key)
        if m:
            out[f"lin{m.group(1)}.weight"] = value
    shift = state["scaling_layer.shift"].reshape(-1)
    scale = state["scaling_layer.scale"].reshape(-1)
    if not (np.allclose(shift, jl.SHIFT) and np.allclose(scale, jl.SCALE)):
        raise ValueError(f"unexpected LPIPS scaling layer: shift {shift}, scale {scale}")
    jl.params_from_arrays(out, "torch lpips model")  # validates keys and shapes
    return out


def check_conversion(model, params, sizes=((64, 64), (96, 128)), seed: int = 0) -> float:
    """Largest relative difference between torch and JAX distances on random pairs."""
    import torch

    from jaxnerf_grid.eval import lpips as jl

    rng = np.random.default_rng(seed)
    worst = 0.0
    for h, w in sizes:
        a = rng.random((2, h, w, 3), dtype=np.float32)
        b = np.clip(a + 0.2 * rng.standard_normal(a.shape).astype(np.float32), 0, 1)
        with torch.no_grad():
            ref = model(torch.from_numpy(a).permute(0, 3, 1, 2), torch.from_numpy(b).permute(0, 3, 1, 2),
                        normalize=True).reshape(-1).numpy()
        got = np.asarray(jl.lpips(params, a, b))
        worst = max(worst, float(np.max(np.abs(got - ref) / np.abs(ref))))
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="output .npz")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    if args.out.exists() and not args.overwrite:
        print(f"error: {args.out} exists (pass --overwrite)", file=sys.stderr)
        return 2
    from jaxnerf_grid.eval import lpips as jl

    try:  # needs torch, a working torchvision with the ImageNet AlexNet weights, and lpips
        import lpips

        model = lpips.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=False, verbose=False)
    except Exception as e:  # noqa: BLE001 - report any environment problem in one line
        print(f"error: cannot build lpips.LPIPS(net='alex') with pretrained AlexNet "
              f"(needs torch, torchvision and lpips): {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    arrays = arrays_from_torch_lpips(model)
    jl.save_lpips(args.out, arrays)
    worst = check_conversion(model, jl.load_lpips(args.out))
    print(f"wrote {args.out}; torch vs JAX max relative difference {worst:.2e}")
    if worst > 1e-4:
        print("error: conversion check failed", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.exit(main())
