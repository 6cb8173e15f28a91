"""The whole chain from bare photos against the same run on the true poses (docs/POSES.md).

    python -m experiments.poses_chain [--clutter low] [--views 48] [--size 320x240] [--max-side N]
                                      [--steps N] [--cache DIR] [--results DIR]

1. A synthetic tower-small scene is rendered at --size (seed 0; its train and test views are
   the "photos", so a few of them hold passers-by, as a survey would).
2. Chain A, from the bare photos: `poses` (exhaustive, one camera) -> the demo
   (built-in DPT masks, the demo's recipe, evaluation), as `jaxnerf-grid poses` then
   `jaxnerf-grid demo --data` run it.
3. Chain B, the true poses: the same photos (scaled like A's with --max-side, by OpenCV area;
   as they are otherwise), the same registered subset in the same order (so the same test
   views: every 8th), the generator's own cameras and intrinsics -> the same demo.
Both are scored on the same test photos (whole-image PSNR; the photos are the targets, so the
test views that hold passers-by count them): A on its undistorted photos, B on the photos as
rendered (undistortion to PINHOLE may crop A's by a pixel or two). Writes
results/poses_chain.json and .md.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def true_pose_dataset(scene: Path, chain_a: Path, out: Path, size: tuple[int, int]) -> Path:
    """A dataset of scene's photos scaled to `size` with the true cameras, holding exactly the
    frames of chain_a's transforms.json, in its order."""
    from jaxnerf_grid.util import io

    w, h = size
    truth = io.read_json(scene / "transforms.json")
    by_name = {Path(f["file_path"]).name: f for f in truth["frames"]}
    found = io.read_json(chain_a / "transforms.json")
    sx, sy = w / truth["w"], h / truth["h"]
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    frames = []
    for f in found["frames"]:
        name = Path(f["file_path"]).name
        pixels = io.read_image(scene / by_name[name]["file_path"])
        io.write_png(out / "images" / name, io.resize(pixels, (w, h)))
        frames.append({"file_path": f"images/{name}", "transform_matrix": by_name[name]["transform_matrix"]})
    meta = {"fl_x": truth["fl_x"] * sx, "fl_y": truth["fl_y"] * sy, "cx": truth["cx"] * sx, "cy": truth["cy"] * sy,
            "w": w, "h": h, "camera_model": "PINHOLE", "near": truth["near"], "far": truth["far"],
            "scene_normalization": truth["scene_normalization"], "frames": frames}
    io.write_json(out / "transforms.json", meta)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clutter", default="low", choices=("none", "low", "medium", "high"))
    p.add_argument("--views", type=int, default=48, help="photos (train + test views of the synthetic scene)")
    p.add_argument("--size", default="320x240", help="photo size WxH")
    p.add_argument("--max-side", type=int, default=None,
                   help="poses --max-side (scales the photos before structure from motion; default: none)")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the demo's)")
    p.add_argument("--cache", default=str(ROOT / "experiments" / ".cache" / "poses_chain"))
    p.add_argument("--results", default=str(ROOT / "experiments" / "results"))
    args = p.parse_args(argv)
    from jaxnerf_grid import demo
    from jaxnerf_grid.capture.poses import poses_from_images
    from jaxnerf_grid.data.synthetic.generate import generate_scene
    from jaxnerf_grid.util import io

    w, h = (int(v) for v in args.size.lower().split("x"))
    cache = Path(args.cache)
    num_test = max(1, args.views // 6)
    scene = cache / f"scene_{args.clutter}_{args.views}_{w}x{h}"
    if not (scene / "transforms.json").is_file():
        generate_scene("tower-small", scene, seed=0, distractors=args.clutter, overwrite=True, progress=False,
                       width=w, height=h, num_train=args.views - num_test, num_test=num_test)
    photos = cache / "photos"
    shutil.rmtree(photos, ignore_errors=True)
    photos.mkdir(parents=True)
    for f in io.read_json(scene / "transforms.json")["frames"]:
        shutil.copy(scene / f["file_path"], photos / Path(f["file_path"]).name)
    shutil.rmtree(cache / "A", ignore_errors=True)  # masks of an earlier chain would be refused, not replaced
    t = time.perf_counter()
    summary = poses_from_images(photos, cache / "A", single_camera=True, max_side=args.max_side, overwrite=True,
                                progress=False)
    poses_s = time.perf_counter() - t
    top = io.read_json(cache / "A" / "transforms.json")
    size = (int(top["w"]), int(top["h"]))  # undistortion may crop a pixel or two
    true_pose_dataset(scene, cache / "A", cache / "B", (w, h) if args.max_side is None else size)
    rows = {}
    for name in ("A", "B"):
        shutil.rmtree(cache / f"run_{name}", ignore_errors=True)
        res = demo.run_demo(cache / name, cache / f"run_{name}", args.steps, overwrite=True, progress=False,
                            video_frames=0)
        rows[name] = {"psnr": res["metrics"]["mean"]["psnr"], "ssim": res["metrics"]["mean"]["ssim"],
                      "test_views": [v["name"] for v in res["metrics"]["per_view"]], "timings": res["timings"]}
        print(f"chain {name}: {demo.demo_summary(res)}", flush=True)
    diff = rows["A"]["psnr"] - rows["B"]["psnr"]
    payload = {"command": "python -m experiments.poses_chain " + " ".join(argv if argv is not None else
                                                                        __import__("sys").argv[1:]),
               "clutter": args.clutter, "photos": args.views, "photo_size": [w, h], "dataset_size": list(size),
               "steps": args.steps, "registered": summary["registered"], "unregistered": summary["unregistered"],
               "poses_seconds": poses_s, "relaxed_mapping": summary["relaxed_mapping"],
               "from_photos": rows["A"], "true_poses": rows["B"], "psnr_difference": diff}
    results = Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    io.write_json(results / "poses_chain.json", payload)
    md = ["# The whole chain from bare photos against the true poses", "",
          f"`{payload['command']}`", "",
          f"tower-small seed 0, {args.clutter} clutter, {args.views} photos at {w}x{h}; `poses` registered "
          f"{summary['registered']} of {args.views} in {poses_s:.0f} s "
          f"and undistorted them to {size[0]}x{size[1]}; both "
          f"chains then ran the demo's recipe ({'its steps' if args.steps is None else f'{args.steps} steps'}) on "
          f"those {summary['registered']} photos with the same {len(rows['A']['test_views'])} test views.", "",
          "| chain | test PSNR | SSIM |", "|---|---|---|",
          f"| from the photos (poses -> mask -> train -> eval) | {rows['A']['psnr']:.2f} | {rows['A']['ssim']:.3f} |",
          f"| true poses | {rows['B']['psnr']:.2f} | {rows['B']['ssim']:.3f} |", "",
          f"Difference (photos - true poses): {diff:+.2f} dB."]
    (results / "poses_chain.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
