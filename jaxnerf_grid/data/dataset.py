"""The in-memory dataset every loader returns and the trainer consumes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from jaxnerf_grid.util.io import DataError

# A camera centre this many times farther from the median centre than the median camera is
# an error (a pose translated 1e30 away, a unit mix-up); real orbits and strips stay within ~3x.
CAMERA_OUTLIER_FACTOR = 1000.0


@dataclasses.dataclass
class Dataset:
    """Images and cameras of one scene, all frames (use `split` to select).

    images: [N, H, W, 3] float32 in [0, 1] (the training targets, cluttered for synthetic data)
    c2w: [N, 4, 4] float32 camera-to-world, OpenGL axes, normalised scene
    intrinsics: [N, 4] float32 (fx, fy, cx, cy) in pixels
    split: {"train": int indices, "test": int indices}
    near, far: metric ray-distance bounds in the normalised scene
    weights: optional [N, H, W] float32 loss weights 1 - M_w (None: all ones)
    masks: optional [N, H, W] float32 binary foreground masks M
    clean_images: optional [N, H, W, 3] ground-truth images without distractors
    depth: optional [N, H, W] float32 z-depth (normalised units)
    semantics: optional [N, H, W] uint8 class ids
    distractor_masks: optional [N, H, W] bool
    normalization: {"scale": float, "translation": [3]} metric -> normalised, plus an optional
        "rotation" [3][3] (x_norm = scale * R (x + translation); absent: the identity)
    frame_paths: image path of each frame (relative to root)
    """

    root: Path
    images: np.ndarray
    c2w: np.ndarray
    intrinsics: np.ndarray
    split: dict
    near: float
    far: float
    weights: np.ndarray | None = None
    masks: np.ndarray | None = None
    clean_images: np.ndarray | None = None
    depth: np.ndarray | None = None
    semantics: np.ndarray | None = None
    distractor_masks: np.ndarray | None = None
    normalization: dict = dataclasses.field(default_factory=lambda: {"scale": 1.0, "translation": [0.0, 0.0, 0.0]})
    frame_paths: list = dataclasses.field(default_factory=list)
    meta: dict = dataclasses.field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    def subset(self, indices) -> Dataset:
        """A new Dataset of the frames `indices` (split re-indexed to all of them as both)."""
        idx = np.asarray(indices, dtype=np.int64)
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return dataclasses.replace(
            self, images=self.images[idx], c2w=self.c2w[idx], intrinsics=self.intrinsics[idx],
            weights=pick(self.weights), masks=pick(self.masks), clean_images=pick(self.clean_images),
            depth=pick(self.depth), semantics=pick(self.semantics),
            distractor_masks=pick(self.distractor_masks),
            frame_paths=[self.frame_paths[i] for i in idx] if self.frame_paths else [],
            split={"train": np.arange(len(idx)), "test": np.arange(len(idx))},
        )


def check_camera_centres(ds: Dataset, factor: float = CAMERA_OUTLIER_FACTOR) -> None:
    """Raises DataError naming the frame whose camera centre (c2w[:3, 3]) lies more than `factor`
    times the median distance from the median centre (robust: one far camera cannot hide
    itself). Needs 3 or more frames and cameras that are not all at one point."""
    centres = np.asarray(ds.c2w, np.float64)[:, :3, 3]
    if len(centres) < 3:
        return
    dist = np.linalg.norm(centres - np.median(centres, axis=0), axis=-1)
    typical = float(np.median(dist))
    if not np.all(np.isfinite(dist)):
        bad = int(np.flatnonzero(~np.isfinite(dist))[0])
    elif dist.max() > factor * typical:  # typical 0: most cameras at one point, one elsewhere
        bad = int(np.argmax(dist))
    else:
        return
    name = ds.frame_paths[bad] if ds.frame_paths else f"frame {bad}"
    raise DataError(f"{Path(ds.root) / name}: its camera centre is {dist[bad]:.3g} units from the others' "
                    f"median (they lie within {typical:.3g}); check this frame's pose")
