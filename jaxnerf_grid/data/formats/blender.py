"""Blender synthetic datasets: transforms_{train,val,test}.json, RGBA PNGs on a background."""

from __future__ import annotations

from pathlib import Path

from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.data.formats.frames import BLENDER_FAR, BLENDER_NEAR, Scene, check_split, scene_to_dataset
from jaxnerf_grid.data.formats.transforms_json import collect_json_frames
from jaxnerf_grid.util import io
from jaxnerf_grid.util.io import DataError


def load_blender(path, *, downscale: float = 1, load_extras: bool = True, **kwargs) -> Dataset:
    """Loads a Blender-synthetic folder; options as in `collect_blender`."""
    scene = collect_blender(path, load_extras=load_extras, **kwargs)
    return scene_to_dataset(scene, downscale=downscale, load_extras=load_extras)


def collect_blender(path, *, load_extras: bool = True, background=(1.0, 1.0, 1.0), normalize=None,
                    honour_exif: bool = True) -> Scene:
    """Collects a Blender-synthetic folder (transforms_train.json, transforms_val.json,
    transforms_test.json; `camera_angle_x`; file paths without extension; RGBA PNG composited
    over `background`). Split: the file each frame came from ("val" frames are kept as a
    "val" split and stand in for "test" when there is no test file)."""
    root = Path(path)
    entries: list = []
    split: dict = {}
    top = None
    for name in ("train", "val", "test"):
        json_path = root / f"transforms_{name}.json"
        if not json_path.is_file():
            continue
        data = io.read_json(json_path)
        frames = data.get("frames") if isinstance(data, dict) else None
        if not isinstance(frames, list) or not frames:
            raise DataError(f"{json_path}: no frames (empty split {name!r})")
        if top is None:
            top = dict(data)
        elif "camera_angle_x" in data and "camera_angle_x" not in top:
            top["camera_angle_x"] = data["camera_angle_x"]
        # camera_angle_x is per file in Blender data: copy it into frames so each file keeps its own.
        for fr in frames:
            fr = dict(fr)
            for key in ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h"):
                if key in data and key not in fr:
                    fr[key] = data[key]
            split.setdefault(name, []).append(len(entries))
            entries.append((json_path, fr))
    if top is None:
        raise DataError(f"{root}: no transforms_train.json / transforms_test.json (not a Blender folder)")
    if "train" not in split:
        raise DataError(f"{root / 'transforms_train.json'}: file not found (empty split 'train')")
    if "test" not in split and "val" in split:
        split["test"] = list(split["val"])
    split = check_split(split, root / "transforms_test.json")
    top.pop("frames", None)
    return collect_json_frames(entries, top, root / "transforms_train.json", root, load_extras=load_extras,
                         background=background, normalize=normalize, undistort=True,
                         honour_exif=honour_exif, split=split,
                         near_far_default=(BLENDER_NEAR, BLENDER_FAR), fmt="blender")
