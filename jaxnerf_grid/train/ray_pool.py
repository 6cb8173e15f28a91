"""The ray pool of the plain training step (train.robust off): 8-bit frames split over the devices.

What the step draws from is the same as `train.build_pool`'s float32 pool (kept as the tests'
reference; the robust step's pool holds its frames and weights as below too, `lean_frames`): the
training pixels of loss weight > 0 in flat order (training frame, row, col), a batch of
`batch_rays` drawn uniformly (with replacement) from the state's key, the same global batch for
any device count. What is held differs:

* images as uint8 (value / 255, converted to float32 in the step: for 8-bit photos at their
  native size the same float32 as `io.read_image`; resized working frames are rounded to 8 bits,
  within 0.5 / 255), in the frame rows of a `working.frame_buffer` (aligned, spare frames) so the
  dataset's own uint8 array is handed to the devices without a copy where XLA can alias it (CPU);
* the loss weights as uint8 codes into a table of 256 float32 levels, exact: k / 255 when every
  weight is one (binary masks, 8-bit weight maps), else the distinct values when there are at
  most 256 (a mask floor: {0, 1 - floor, 1}); soft weights with more distinct values (depth-
  weighted EXR maps) are kept as float32 (4 bytes a pixel, exact); no weights at all (1 each)
  when the run uses none;
* no list of pixel ids: the k-th drawn pixel is found from per-row counts of drawn pixels
  (`row_start`, [T * H + 1], the row, then the k-th drawn column of that row), or directly when
  every pixel is drawn. Draws are int32; a pool of 2^31 pixels or more is refused in one line
  (`check_size`), never wrapped;
* the frames split over the n devices of the step in n consecutive groups of ceil(F / n) stored
  frames; for each ray of the global batch the device holding its frame looks its colour, weight
  (and, for masked frames, its column) up, the others give zeros, and one `psum` of [B, 5] int32
  gives every device the whole batch, of which it renders its share: the batch is the same
  integers for any device count, so 1 device and 2 devices train the same.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.config import schema as config_lib
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data import working
from jaxnerf_grid.data.dataset import Dataset
from jaxnerf_grid.nerf import rays as rays_lib
from jaxnerf_grid.train import error_map
from jaxnerf_grid.util import parallel
from jaxnerf_grid.util.io import DataError

MAX_PIXELS = 2 ** 31 - 1  # the draw and the row counts are int32 (JAX without x64)
LEVELS = 256
# byte k -> k / 255 as float32, computed as io.read_image does; a table, because XLA turns a
# division by 255 into a multiplication by its reciprocal, which differs in the last bit
BYTE_VALUES = np.arange(LEVELS, dtype=np.float32) / np.float32(255)


# --------------------------------------------------------------------------- loss weights


def frame_weights(raw: np.ndarray | None, mask: np.ndarray | None, use_masks: bool, floor: float,
                  shape: tuple[int, int]) -> np.ndarray:
    """One frame's loss weights (`train.loss_weights` for one frame): raw: [H, W] the dataset's
    1 - M_w or None, mask: [H, W] binary or None. Returns [H, W] float32 in [0, 1]."""
    if not use_masks or raw is None:
        return np.ones(shape, np.float32)
    w = np.clip(np.asarray(raw, np.float32), 0.0, 1.0)
    if floor > 0 and mask is not None:
        w = np.where(np.asarray(mask) > 0.5, np.minimum(w, 1.0 - floor), w)
    return w.astype(np.float32)


def weight_table(frames) -> np.ndarray | None:
    """The 256 float32 levels that code every weight of `frames` (an iterable of [H, W] float32)
    exactly: k / 255 when each weight is one, else the sorted distinct values (padded with the
    last); None when there are more than 256 distinct values (keep float32)."""
    k255 = BYTE_VALUES
    distinct: set | None = set()
    all_k255 = True
    for w in frames:
        if all_k255:
            codes = np.clip(np.rint(w * np.float32(255)), 0, 255).astype(np.uint8)
            all_k255 = bool(np.array_equal(k255[codes], w))
        if not all_k255 and distinct is not None:
            distinct.update(np.unique(w).tolist())
            if len(distinct) > LEVELS:
                distinct = None
    if all_k255:
        return k255
    if distinct is None:
        return None
    values = np.asarray(sorted(distinct), np.float32)
    return np.concatenate([values, np.full(LEVELS - values.size, values[-1], np.float32)])


def encode_weights(w: np.ndarray, table: np.ndarray) -> np.ndarray:
    """[H, W] float32 weights as uint8 codes into `table` (exact: each weight is a level)."""
    codes = np.searchsorted(table[:np.flatnonzero(table == table[-1])[0] + 1], w).astype(np.uint8)
    if not np.array_equal(table[codes], w):
        raise ValueError("encode_weights: a weight is not one of the table's levels")
    return codes


# --------------------------------------------------------------------------- the host pool


def check_size(pixels: int, root) -> None:
    """DataError (one line, naming the dataset) for a pool of MAX_PIXELS pixels or more."""
    if pixels > MAX_PIXELS:
        raise DataError(f"{root}: {pixels:,} training pixels; the ray draw counts them in 32 bits, at most "
                        f"{MAX_PIXELS:,}: lower train.max_side or train on fewer photos")


def _store_frames(images: np.ndarray, frames: np.ndarray, root) -> tuple[np.ndarray, np.ndarray]:
    """(frame rows [F, stride] uint8, store index [T] of `frames` in them): the dataset's own
    buffer when it is a `working.frame_buffer`, else a new one holding the frames (quantised)."""
    rows = working.frame_rows(images)
    if rows is not None:
        return rows, frames.astype(np.int32)
    _, h, w, _ = images.shape
    buffer = working.frame_buffer(frames.size, h, w)
    for k, f in enumerate(frames):
        if images.dtype != np.uint8 and not np.all(np.isfinite(images[f])):
            raise DataError(f"{root}: frame {int(f)} has non-finite pixel values")
        buffer[k] = working.to_uint8(images[f])
    rows = working.frame_rows(buffer)
    assert rows is not None  # a frame_buffer always has its rows
    return rows, np.arange(frames.size, dtype=np.int32)


def make_pool(images: np.ndarray, frames: np.ndarray, weights_of, c2w: np.ndarray, intrinsics: np.ndarray,
              image_index: np.ndarray, near: float, far: float, root) -> dict:
    """The host pool (see the module docstring).

    images: [N, H, W, 3] uint8 or float in [0, 1]; frames: [T] the training frames' indices into
    images; weights_of: k -> [H, W] float32 loss weights of training frame k, or None (every
    weight 1); c2w: [T, 4, 4]; intrinsics: [T, 4]; image_index: [T] dataset frame ids (the
    appearance embedding's). Returns {"rows": [F, S] uint8, "codes": [F, H*W] uint8 | absent,
    "weights32": [F, H*W] float32 | absent, "levels": [256] float32, "store": [T] int32,
    "frame": [T] int32, "c2w", "intrinsics", "row_start": [T*H + 1] int32 | absent (every pixel
    drawn), "grid": [H, W, 0] (its shape is the frames' size), "count": pixels drawn, "near", "far"}.
    """
    frames = np.asarray(frames, np.int64)
    _, h, w, _ = images.shape
    if working.frame_stride(h, w) > MAX_PIXELS:
        raise DataError(f"{root}: frames of {w}x{h} are too large for 32-bit pixel offsets")
    check_size(frames.size * h * w, root)
    rows, store = _store_frames(images, frames, root)
    pool = {"rows": rows, "store": store, "frame": np.asarray(image_index, np.int32),
            "c2w": np.asarray(c2w, np.float32), "intrinsics": np.asarray(intrinsics, np.float32),
            "grid": np.zeros((h, w, 0), np.uint8), "near": float(near), "far": float(far),
            "levels": np.ones(LEVELS, np.float32)}
    count = frames.size * h * w
    if weights_of is not None and all(np.all(weights_of(k) == 1.0) for k in range(frames.size)):
        weights_of = None  # every weight 1 (masks with nothing masked): nothing to hold per pixel
    if weights_of is not None:
        table = weight_table(weights_of(k) for k in range(frames.size))
        key = "codes" if table is not None else "weights32"
        held = np.zeros((rows.shape[0], h * w), np.uint8 if table is not None else np.float32)
        per_row = np.zeros(frames.size * h, np.int64)
        for k in range(frames.size):
            wk = weights_of(k)
            held[store[k]] = (encode_weights(wk, table) if table is not None else wk).reshape(-1)
            per_row[k * h:(k + 1) * h] = np.count_nonzero(wk > 0, axis=1)
        count = int(per_row.sum())
        pool[key] = held
        if table is not None:
            pool["levels"] = table
        if count < frames.size * h * w:  # some pixels are not drawn: find the k-th one through its row
            pool["row_start"] = np.concatenate([[0], np.cumsum(per_row)]).astype(np.int32)
    if count == 0:
        raise DataError(f"{root}: every training pixel has loss weight 0 (check the masks)")
    pool["count"] = count
    return pool


def build(dataset: Dataset, cfg) -> dict:
    """The host pool of a dataset's training frames for the plain step (`make_pool`): the loss
    weights of `train.loss_weights`, near / far of `config.near_far`. cfg: a RunConfig."""
    train_ids = np.asarray(dataset.split["train"], np.int64)
    if train_ids.size == 0:
        raise DataError(f"{dataset.root}: the dataset has no training frames")
    near, far = config_lib.near_far(cfg.model, dataset)
    if not 0 < near < far:
        raise ConfigError(f"near/far: need 0 < near < far, got {near}, {far}")
    t = cfg.train
    weights_of = None
    if t.use_masks and dataset.weights is not None:
        def weights_of(k):
            f = train_ids[k]
            return frame_weights(dataset.weights[f], None if dataset.masks is None else dataset.masks[f],
                                 True, t.mask_weight_floor, (dataset.height, dataset.width))
    return make_pool(dataset.images, train_ids, weights_of, dataset.c2w[train_ids], dataset.intrinsics[train_ids],
                     train_ids, near, far, dataset.root)


def from_host_pool(pool: dict, root="the run") -> dict:
    """The plain step's pool of a `train.build_pool`-style float pool (images [T, H, W, 3],
    weights [T, H, W], c2w, intrinsics, frame, near, far; the pixels drawn are its weights > 0,
    as `refine.frozen_pool` keeps them)."""
    weights = np.asarray(pool["weights"], np.float32)
    frames = np.arange(weights.shape[0])
    return make_pool(pool["images"], frames, lambda k: weights[k], pool["c2w"], pool["intrinsics"],
                     pool["frame"], pool["near"], pool["far"], root)


# --------------------------------------------------------------------------- on the devices

SHARDED = ("rows", "codes", "weights32")


def group_size(frames: int, n: int) -> int:
    """Stored frames per device: ceil(frames / n)."""
    return max(1, math.ceil(frames / n))


def _stored_frames(pool: dict) -> int:
    return int(pool["store"].max()) + 1


def shards(array: np.ndarray, n: int, per: int) -> list[np.ndarray]:
    """n consecutive groups of `per` rows of `array` ([F, ...]), views where F >= n * per (the
    spare frames), the last groups padded with zeros otherwise."""
    out = []
    for d in range(n):
        part = array[d * per:(d + 1) * per]
        if part.shape[0] < per:
            part = np.concatenate([part, np.zeros((per - part.shape[0],) + array.shape[1:], array.dtype)])
        out.append(part)
    return out


def upload(pool: dict, n: int) -> dict:
    """The host pool on the step's n devices: the frame rows, codes and float weights split in n
    groups (device d holds stored frames [d * g, (d + 1) * g), g = `group_size`; each process
    uploads its own devices' groups, without a copy where XLA aliases host memory), the rest
    replicated (parallel.replicate). Returns the pmap's pytree, every leaf [n, ...]."""
    devices = parallel.devices(n)
    per = group_size(_stored_frames(pool), n)
    sharding = jax.sharding.NamedSharding(jax.sharding.Mesh(np.asarray(devices), (parallel.AXIS,)),
                                          jax.sharding.PartitionSpec(parallel.AXIS))
    out = {}
    for key in SHARDED:
        if key not in pool:
            continue
        groups = shards(pool[key], n, per)
        local = [jax.device_put(groups[d][None], dev, may_alias=True)
                 for d, dev in enumerate(devices) if dev.process_index == jax.process_index()]
        out[key] = jax.make_array_from_single_device_arrays((n, per) + pool[key].shape[1:], sharding, local)
    small = {k: v for k, v in pool.items() if k not in SHARDED and k != "count"}
    out.update(parallel.replicate(small, n))
    return out


def pixel_ids(pool: dict, key, batch: int) -> jnp.ndarray:
    """The global batch's draws: [batch] int32 uniform in [0, pool count) from `key` (the same
    call as the float pool's draw of positions in its pixel list)."""
    h, w = pool["grid"].shape[:2]
    count = pool["frame"].shape[0] * h * w if "row_start" not in pool else pool["row_start"][-1]
    return jax.random.randint(key, (batch,), 0, count)


def locate(pool: dict, ids: jnp.ndarray):
    """Draws -> (training frame t [B], row [B], col [B] or None, offset [B] or None): with every
    pixel drawn, the flat (t, row, col) order; else the row from the per-row counts and the offset
    of the pixel among that row's drawn ones (its column is found where the frame is held)."""
    h, w = pool["grid"].shape[:2]
    if "row_start" not in pool:
        pix = ids % (h * w)
        return ids // (h * w), pix // w, pix % w, None
    g = jnp.searchsorted(pool["row_start"], ids, side="right").astype(jnp.int32) - 1
    return g // h, g % h, None, ids - pool["row_start"][g]


def _weight_rows(pool: dict, local, row, w: int):
    """[B, W] float32 weights of the rows (local stored frame, row) held on this device."""
    cols = row[:, None] * w + jnp.arange(w)[None, :]
    if "codes" in pool:
        return pool["levels"][pool["codes"][local[:, None], cols]]
    return pool["weights32"][local[:, None], cols]


def lookup(pool: dict, t, row, col, offset, axis: str = parallel.AXIS) -> dict:
    """The pixels of the global batch, assembled from the devices holding their frames: each
    device looks up those in its group of frames (zeros elsewhere) and one psum over `axis` sums
    the exact integers. col: [B] or None; offset: [B] (`locate`'s, -1 where col is given) or None.
    Returns {"col": [B] int32, "rgb": [B, 3] float32, "weight": [B] float32}."""
    h, w = pool["grid"].shape[:2]
    per = pool["rows"].shape[0]
    store = pool["store"][t]
    me = jax.lax.axis_index(axis)
    mine = store // per == me
    local = jnp.where(mine, store - me * per, 0)
    if offset is not None:  # the offset-th drawn pixel of the row: count the drawn ones along it
        drawn = (_weight_rows(pool, local, row, w) > 0).astype(jnp.int32)
        counted = jnp.sum(jnp.cumsum(drawn, axis=1) <= offset[:, None], axis=1).astype(jnp.int32)
        counted = jnp.minimum(counted, w - 1)
        col = counted if col is None else jnp.where(offset >= 0, counted, col)  # offset -1: col given
    pix = row * w + col
    rgb = pool["rows"][local[:, None], pix[:, None] * 3 + jnp.arange(3)[None, :]].astype(jnp.int32)
    parts = [rgb]
    if "codes" in pool:
        parts.append(pool["codes"][local, pix].astype(jnp.int32)[:, None])
    if offset is not None:
        parts.append(col[:, None])
    summed = jax.lax.psum(jnp.where(mine[:, None], jnp.concatenate(parts, axis=1), 0), axis)
    out = {"rgb": jnp.asarray(BYTE_VALUES)[summed[:, :3]], "col": summed[:, -1] if offset is not None else col}
    if "codes" in pool:
        out["weight"] = pool["levels"][summed[:, 3]]
    elif "weights32" in pool:
        out["weight"] = jax.lax.psum(jnp.where(mine, pool["weights32"][local, pix], 0.0), axis)
    else:
        out["weight"] = jnp.ones(t.shape, jnp.float32)
    return out


def draws(pool: dict, key, batch: int, errors=None, from_errors: int = 0, tile: int = 16):
    """The global batch's pixels (t, row, col or None, offset or None; `locate`'s): batch -
    from_errors drawn uniformly (`pixel_ids`), then from_errors from the error map `errors`
    ([tiles], error_map.py; its key folded off `key`), whose columns are known (offset -1)."""
    t, row, col, offset = locate(pool, pixel_ids(pool, key, batch - from_errors))
    if not from_errors:
        return t, row, col, offset
    h, w = pool["grid"].shape[:2]
    te, re, ce = error_map.draw(errors, jax.random.fold_in(key, error_map.ERROR_FOLD), from_errors, h, w, tile)
    if offset is None:
        return jnp.concatenate([t, te]), jnp.concatenate([row, re]), jnp.concatenate([col, ce]), None
    return (jnp.concatenate([t, te]), jnp.concatenate([row, re]),
            jnp.concatenate([jnp.zeros_like(offset), ce]), jnp.concatenate([offset, jnp.full_like(ce, -1)]))


def device_batch(pool: dict, key, batch: int, per_device: int, axis: str = parallel.AXIS, errors=None,
                 from_errors: int = 0, tile: int = 16) -> dict:
    """This device's share of the global batch drawn from `key` (`draws`, `lookup`): rays and
    targets, dict of [per_device, ...] (origins, directions, near, far, rgb, weight,
    image_index) as `train.gather_batch` gives them; with an error map (`errors`, from_errors >
    0) also "tiles": [batch] the whole batch's tile ids (error_map.tile_ids)."""
    t, row, col, offset = draws(pool, key, batch, errors, from_errors, tile)
    values = lookup(pool, t, row, col, offset, axis)
    tiles = None
    if from_errors:
        h, w = pool["grid"].shape[:2]
        tiles = error_map.tile_ids(t, row, values["col"], h, w, tile)
    start = jax.lax.axis_index(axis) * per_device

    def mine(x):
        return jax.lax.dynamic_slice_in_dim(x, start, per_device)

    t, row, c = mine(t), mine(row), mine(values["col"])
    intr = pool["intrinsics"][t]
    r = rays_lib.rays_for_pixels(pool["c2w"][t], intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3],
                                 c.astype(jnp.float32) + 0.5, row.astype(jnp.float32) + 0.5,
                                 pool["near"], pool["far"])
    out = {"origins": r.origins, "directions": r.directions, "near": r.near, "far": r.far,
           "rgb": mine(values["rgb"]), "weight": mine(values["weight"]), "image_index": pool["frame"][t]}
    if tiles is not None:
        out["tiles"] = tiles
    return out


def host_bytes(pool: dict) -> int:
    """Bytes of the pool's arrays (the frame rows counted once, whether shared or not)."""
    return int(sum(np.asarray(v).nbytes for v in pool.values() if isinstance(v, np.ndarray)))


# --------------------------------------------------------------------------- the robust step's pool
# The robust step draws patches over whole frames (flat ids frame * H * W + row * W + col, no
# list of them) from frames replicated on every device; held as below they take 4 bytes a pixel
# (8-bit frames, coded weights) instead of `train.build_pool`'s 20, and read the same float32.


def lean_frames(images: np.ndarray, weights: np.ndarray) -> dict:
    """The robust step's frames and weights as held: images [T, H, W, 3] uint8 kept as uint8
    (read through BYTE_VALUES: the float32 of `working.as_float`), others as float32; weights
    [T, H, W] float32 (T >= 1) as uint8 codes with their "levels" [256] float32 (`weight_table`), or as
    float32 when no table codes them. Returns {"images", "weights"[, "levels"]}."""
    images = np.asarray(images)
    out = {"images": images if images.dtype == np.uint8 else working.as_float(images)}
    weights = np.asarray(weights, np.float32)
    table = weight_table(weights)
    if table is None:
        out["weights"] = weights
    else:  # frame by frame: encode_weights' search holds 8 bytes a pixel while it runs
        out["weights"] = np.stack([encode_weights(w, table) for w in weights])
        out["levels"] = table
    return out


def byte_table(images) -> np.ndarray | None:
    """BYTE_VALUES ([256] float32) when `images` (NumPy or JAX, traced too) are uint8, else None."""
    return BYTE_VALUES if images.dtype == np.uint8 else None


def colours(images, *index):
    """images[index] as float32: uint8 frames through BYTE_VALUES (exact), float ones as held."""
    values = images[index]
    table = byte_table(images)
    return values if table is None else jnp.asarray(table)[values]


def weights_at(pool: dict, *index):
    """pool["weights"][index] as float32, decoded through pool["levels"] when coded."""
    values = pool["weights"][index]
    return pool["levels"][values] if "levels" in pool else values


def host_weights(pool: dict) -> np.ndarray:
    """A robust pool's weights [T, H, W] as float32 on the host (decoded when coded)."""
    if "levels" in pool:
        return np.asarray(pool["levels"], np.float32)[np.asarray(pool["weights"])]
    return np.asarray(pool["weights"], np.float32)
