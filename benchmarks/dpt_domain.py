"""Is the built-in DPT in its domain? Its masked share and confidence on real photos and on the
synthetic presets, and whether `mask`'s out-of-domain rule fires (docs/MASKS.md).

    python -m benchmarks.dpt_domain [--strecha STRECHA_DIR] [--photos DIR ...] [--no-skimage]
        [--no-synthetic] [--weights DIR ...] [--work benchmarks/.cache/dpt_domain]
        [--out benchmarks/results/dpt_domain]

Per photo set, every photo goes through the built-in DPT exactly as `jaxnerf-grid mask` runs it
(`foreground.predict_maps` at the model's working size, its own dynamic classes, T = 0.5):
the share of pixels in M per frame and the frame's confidence (the mean largest class
probability, `foreground.max_class_probability`); then `masking.domain_verdict` on the set.
--weights scores other DPT weights (native folders) beside or instead of the built-in model.
Sets: the Strecha scenes (STRECHA_DIR = Benchmarking_Camera_Calibration_2008 of
openMVG/SfM_quality_evaluation, photos shrunk to a long side of 640 first), scikit-image's
sample photos (shipped with the package), any other folder of photos (--photos: each folder one
set, named by the folder, shrunk like Strecha's), and small renders of the synthetic presets (16 + 2
views, seed 1, cached under --work) at each preset's clutter and at tower-small's none / high.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STRECHA_SCENES = ("fountain-P11", "Herz-Jesus-P25", "entry-P10", "castle-P19")
SKIMAGE_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "cat", "immunohistochemistry", "hubble_deep_field")
# (preset, clutter, width, height): the presets' own aspect, small
SYNTHETIC = (("tower-small", "none", 160, 120), ("tower-small", "medium", 160, 120), ("tower-small", "high", 160, 120),
             ("ttpla-like", "medium", 320, 180), ("plad-like", "high", 300, 200))


def _shrunk(image: np.ndarray, side: int = 640) -> np.ndarray:
    from jaxnerf_grid.masks.foreground import resize_map

    h, w = image.shape[:2]
    s = side / max(h, w)
    return resize_map(image, round(h * s), round(w * s)) if s < 1 else image


def measure(name: str, images, model) -> dict:
    """One photo set through the built-in DPT: per-frame shares and confidences, the verdict."""
    from jaxnerf_grid.masks import foreground as fg
    from jaxnerf_grid.masks import write as masking

    seg, wdir = model
    out = list(fg.predict_maps(seg, None, images, masking.default_classes(seg, wdir),
                               max_side=masking.model_max_side(wdir), batch_size=1, with_confidence=True))
    shares = [round(float(np.mean(fg.binary_mask(c, 0.5))), 4) for c, _, _ in out]
    conf = [round(k, 4) for _, _, k in out]
    verdict = masking.domain_verdict(shares, conf)
    return {"set": name, "shares": shares, "confidences": conf, "verdict": verdict,
            "min_share": min(shares), "max_share": max(shares), "min_confidence": min(conf),
            "max_confidence": max(conf)}


def photo_sets(args):
    from jaxnerf_grid.util import io

    if args.strecha:
        for scene in STRECHA_SCENES:
            photos = sorted((Path(args.strecha) / scene / "images").glob("*.jpg"))
            if photos:
                yield f"Strecha {scene}", "real", (_shrunk(io.read_image(p)) for p in photos)
    for folder in args.photos:
        photos = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        if not photos:
            raise SystemExit(f"--photos {folder}: no .jpg / .png photos")
        yield Path(folder).name, "real", (_shrunk(io.read_image(p)) for p in photos)
    if not args.no_skimage:
        from skimage import data as skdata

        yield "scikit-image samples", "real", (np.asarray(getattr(skdata, n)(), np.float32)[..., :3] / 255.0
                                               for n in SKIMAGE_PHOTOS)
    if not args.no_synthetic:
        from jaxnerf_grid.data.synthetic.generate import generate_scene

        for preset, clutter, w, h in SYNTHETIC:
            folder = Path(args.work) / "syn" / f"{preset}-{clutter}"
            if not (folder / "transforms.json").is_file():
                generate_scene(preset, folder, seed=1, distractors=clutter, overwrite=True, progress=False,
                               width=w, height=h, num_train=16, num_test=2)
            meta = io.read_json(folder / "transforms.json")
            yield (f"synthetic {preset} {clutter}", "synthetic",
                   (io.read_image(folder / f["file_path"]) for f in meta["frames"]))


def markdown(rows: list[dict], argv: list[str]) -> str:
    from jaxnerf_grid.masks import write as masking

    lines = ["# The built-in DPT in and out of its domain", "",
             "`python -m benchmarks.dpt_domain " + " ".join(argv) + "`", "",
             f"Rule: {rows[0]['verdict']['rule'] if rows else ''} (`masking.domain_verdict`).", "",
             ("| weights | photos | kind | frames | masked share: mean (min-max) | frames > "
              f"{masking.OOD_FRAME_SHARE:.0%} | confidence: mean (min-max) | out of domain |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        v = r["verdict"]
        lines.append(f"| {r.get('weights', 'built-in')} | {r['set']} | {r['kind']} | {v['frames']} | "
                     f"{v['mean_share']:.1%} ({r['min_share']:.1%}-"
                     f"{r['max_share']:.1%}) | {v['frames_mostly_masked']} | {v['mean_confidence']:.3f} "
                     f"({r['min_confidence']:.3f}-{r['max_confidence']:.3f}) | "
                     f"{'yes' if v['out_of_domain'] else 'no'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.dpt_domain", description=__doc__.split("\n\n")[0])
    p.add_argument("--strecha", default=None, help="the folder Benchmarking_Camera_Calibration_2008")
    p.add_argument("--photos", nargs="*", default=[], help="other folders of static real photos, one set each")
    p.add_argument("--weights", nargs="*", default=[None], help="DPT weight folders (default: the built-in model)")
    p.add_argument("--no-skimage", action="store_true")
    p.add_argument("--no-synthetic", action="store_true")
    p.add_argument("--work", default=str(ROOT / "benchmarks/.cache/dpt_domain"))
    p.add_argument("--out", default=str(ROOT / "benchmarks/results/dpt_domain"))
    args = p.parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    from jaxnerf_grid.masks import write as masking
    from jaxnerf_grid.util import io

    rows = []
    for weights in args.weights:
        seg, _, wdir = masking.load_models(weights, None)
        shown_weights = "built-in" if weights is None else "/".join(Path(weights).resolve().parts[-2:])
        for name, kind, images in photo_sets(args):
            r = measure(name, images, (seg, wdir))
            r["kind"], r["weights"] = kind, shown_weights
            rows.append(r)
            v = r["verdict"]
            print(f"{shown_weights} {name}: {v['frames']} frames, masked share mean {v['mean_share']:.1%} "
                  f"({r['min_share']:.1%}-{r['max_share']:.1%}), {v['frames_mostly_masked']} mostly masked, "
                  f"confidence {v['mean_confidence']:.3f}, out of domain: {v['out_of_domain']}", flush=True)
    # no folder of this machine in the results
    from benchmarks.pasted_transients import shown_argv

    shown = shown_argv(argv, args.strecha)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    io.write_json(out.with_suffix(".json"), {"argv": shown, "rows": rows})
    out.with_suffix(".md").write_text(markdown(rows, shown))
    print(markdown(rows, shown))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
