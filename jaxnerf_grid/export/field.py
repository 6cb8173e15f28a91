"""The trained field at arbitrary points of the (uncontracted) normalised scene, in chunks.

Points go through the model's own input map, `models.field_inputs` (the contraction of Eq. 9
when the model uses it, then the division by the encoding scale; docs/ARCHITECTURE.md, step 5),
evaluated at t = 0 of a ray starting at the point, then through `fields.apply` of the main
field: the one that renders the picture (`models.main_field`; never a proposal field). The
density is in the model's units: per unit length of the normalised scene.

Evaluation runs in chunks of one compiled shape (the last one padded), so memory is bounded by
the chunk, not by the number of points. NeRF-W: the transient head is ignored (static scene);
the colour uses the mean appearance embedding.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxnerf_grid.nerf import fields, models
from jaxnerf_grid.util import parallel

DEFAULT_CHUNK = 1 << 16


def _fn_for(params: dict, mcfg: models.ModelConfig, with_rgb: bool):
    """The jitted evaluation of the main field and its parameters and appearance input."""
    field_params, field_cfg = models.main_field(params, mcfg)
    fn = _compiled(mcfg, field_cfg, with_rgb)
    appearance = None
    if field_cfg.appearance_dim:
        appearance = jnp.mean(params["appearance"], axis=0) if "appearance" in params else \
            jnp.zeros((field_cfg.appearance_dim,), jnp.float32)
    return functools.partial(fn, field_params, appearance)


@functools.lru_cache(maxsize=16)
def _compiled(mcfg: models.ModelConfig, field_cfg: fields.FieldConfig, with_rgb: bool):
    def fn(field_params, appearance, points, viewdirs):
        zeros = jnp.zeros(points.shape[:-1] + (2,), points.dtype)
        x = models.field_inputs(mcfg, points, jnp.zeros_like(points), zeros)[..., 0, :]
        transient = (jnp.zeros(points.shape[:-1] + (field_cfg.transient_dim,), points.dtype)
                     if field_cfg.transient_dim else None)
        app = (jnp.broadcast_to(appearance, points.shape[:-1] + appearance.shape[-1:])
               if appearance is not None else None)
        out = fields.apply(field_params, field_cfg, x, viewdirs, app, transient)
        return {"sigma": out["sigma"], "rgb": out["rgb"]} if with_rgb else {"sigma": out["sigma"]}

    return jax.jit(fn)


def evaluate(params: dict, mcfg: models.ModelConfig, points: np.ndarray, viewdirs: np.ndarray | None = None,
             chunk: int = DEFAULT_CHUNK, progress=None) -> dict:
    """The main field at points [N, 3] (normalised scene, uncontracted), seen along viewdirs
    [N, 3] (unit; None: the density only, the directions are +z).

    progress: a bar with `update(n)` advanced by the points of each chunk, or None.
    Returns {"sigma": [N] float32} (+ "rgb": [N, 3] in (0, 1) with viewdirs), NumPy.
    """
    points = np.asarray(points, np.float32).reshape(-1, 3)
    with_rgb = viewdirs is not None
    dirs = (np.asarray(viewdirs, np.float32).reshape(-1, 3) if with_rgb
            else np.broadcast_to(np.array([0, 0, 1], np.float32), points.shape))
    fn = _fn_for(params, mcfg, with_rgb)
    count = len(points)
    chunk = int(max(1, chunk))          # one compiled shape: every call pads to it
    pieces: dict[str, list] = {"sigma": []} | ({"rgb": []} if with_rgb else {})
    for start in range(0, count, chunk):
        part_p, valid = parallel.pad_to_multiple(points[start:start + chunk], chunk)
        part_d, _ = parallel.pad_to_multiple(dirs[start:start + chunk], chunk)
        out = fn(jnp.asarray(part_p), jnp.asarray(part_d))
        for k in pieces:
            pieces[k].append(np.asarray(out[k])[:valid])
        if progress is not None:
            progress.update(valid)
    if not count:
        return {"sigma": np.zeros(0, np.float32)} | ({"rgb": np.zeros((0, 3), np.float32)} if with_rgb else {})
    return {k: np.concatenate(v).astype(np.float32) for k, v in pieces.items()}


def density_grid(params: dict, mcfg: models.ModelConfig, origin, h: float, shape, chunk: int = DEFAULT_CHUNK,
                 progress=None) -> np.ndarray:
    """The density at the nodes origin + h (i, j, k) of a grid of `shape` (export.mesh.grid_spec),
    evaluated slab by slab (memory: one slab of points at a time). Returns [nx, ny, nz] float32.
    """
    origin = np.asarray(origin, np.float64)
    nx, ny, nz = (int(s) for s in shape)
    out = np.zeros((nx, ny, nz), np.float32)
    ys, zs = origin[1] + h * np.arange(ny), origin[2] + h * np.arange(nz)
    yz = np.stack(np.meshgrid(ys, zs, indexing="ij"), axis=-1).reshape(-1, 2)
    slabs = max(1, chunk // max(ny * nz, 1))
    for i0 in range(0, nx, slabs):
        xs = origin[0] + h * np.arange(i0, min(i0 + slabs, nx))
        pts = np.concatenate([np.repeat(xs, len(yz))[:, None], np.tile(yz, (len(xs), 1))], axis=1)
        sigma = evaluate(params, mcfg, pts, chunk=chunk, progress=progress)["sigma"]
        out[i0:i0 + len(xs)] = sigma.reshape(len(xs), ny, nz)
    return out


def colours_from_cameras(params: dict, mcfg: models.ModelConfig, points: np.ndarray, camera_centres: np.ndarray,
                         k: int = 3, chunk: int = DEFAULT_CHUNK) -> np.ndarray:
    """Colours of points [N, 3] as the field shows them to the cameras: the mean of the field's
    colour seen from the k nearest camera centres ([C, 3]; direction = point - centre).
    Returns [N, 3] float32 in (0, 1)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    centres = np.asarray(camera_centres, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 3), np.float32)
    k = int(max(1, min(k, len(centres))))
    _, idx = cKDTree(centres).query(points, k=k)
    idx = np.asarray(idx).reshape(len(points), k)
    total = np.zeros((len(points), 3), np.float64)
    for j in range(k):
        d = points - centres[idx[:, j]]
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        total += evaluate(params, mcfg, points, d, chunk=chunk)["rgb"]
    return (total / k).astype(np.float32)
