"""An analytic tower for tests: a field whose density and colour are known in closed
form, at a known metric scale, rotation and translation, usable wherever a trained field is.

The scene, in metres, in the tower's own frame (z up; `to_metric_frame` / `to_tower_frame` turn
it into the metric frame of the dataset, tilted by TILT, 20 degrees about x, as a COLMAP or
survey frame may be):

* the ground: the slab GROUND_Z - 2 <= z <= GROUND_Z;
* the tower's body: a square pillar, |x - cx| <= BODY_HALF, |y - cy| <= BODY_HALF,
  GROUND_Z <= z <= GROUND_Z + HEIGHT;
* one cross-arm: |x - cx| <= ARM_HALF_SPAN, |y - cy| <= ARM_HALF_WIDTH, ARM_LOW <= z <= ARM_HIGH.

NORMALIZATION maps the metric frame to the normalised scene the model sees (x_norm =
s R (x + t), R = TURN_Z TILT^T, TURN_Z a turn of 30 degrees about z, s = 0.05,
t = -TILT (cx, cy, GROUND_Z + 10)): there the tower stands upright (z_norm in [-0.5, 0.5])
around the origin, inside the unit sphere, and in metres its axis is TILT's z axis.

`apply(params, cfg, x, ...)` has the signature and outputs of `fields.apply`: x is the field's
input (the model's `field_inputs`: contracted, divided by the encoding scale). It undoes that
map from the constants in `params` (written here in closed form, not with `coords`), undoes the
normalisation to metres and returns SIGMA inside a solid, 0 outside; colour TOWER_RGB or
GROUND_RGB. The tests put it in place of `fields.apply` (monkeypatch), with `clear_compiled`
before and after.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

CENTRE = np.array([100.0, 200.0])      # the tower's axis, metres
GROUND_Z = 50.0
HEIGHT = 20.0
BODY_HALF = 2.0
ARM_HALF_SPAN, ARM_HALF_WIDTH = 6.0, 0.5
ARM_LOW, ARM_HIGH = GROUND_Z + 15.0, GROUND_Z + 16.0
SIGMA = 400.0                           # per normalised unit: opaque within a fraction of a bin
TOWER_RGB = (0.6, 0.5, 0.4)
GROUND_RGB = (0.2, 0.7, 0.3)
TURN, TILT_ANGLE = np.radians(30.0), np.radians(20.0)
TURN_Z = np.array([[np.cos(TURN), -np.sin(TURN), 0.0], [np.sin(TURN), np.cos(TURN), 0.0], [0.0, 0.0, 1.0]])
TILT = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(TILT_ANGLE), -np.sin(TILT_ANGLE)],
                 [0.0, np.sin(TILT_ANGLE), np.cos(TILT_ANGLE)]])
ROTATION = TURN_Z @ TILT.T
NORMALIZATION = {"scale": 0.05, "rotation": ROTATION.tolist(),
                 "translation": (-TILT @ [CENTRE[0], CENTRE[1], GROUND_Z + 10.0]).tolist()}


def to_metric_frame(p):
    """Tower-frame points [..., 3] -> the dataset's metric frame: TILT p."""
    return np.asarray(p, np.float64) @ TILT.T


def to_tower_frame(p):
    """Metric points [..., 3] -> the tower's frame: TILT^T p."""
    return np.asarray(p, np.float64) @ TILT


def boxes() -> list[tuple[np.ndarray, np.ndarray]]:
    """The tower's solids as boxes of its frame [(lo [3], hi [3])]: the body, the cross-arm."""
    cx, cy = CENTRE
    return [(np.array([cx - BODY_HALF, cy - BODY_HALF, GROUND_Z]), np.array([cx + BODY_HALF, cy + BODY_HALF,
                                                                               GROUND_Z + HEIGHT])),
            (np.array([cx - ARM_HALF_SPAN, cy - ARM_HALF_WIDTH, ARM_LOW]),
             np.array([cx + ARM_HALF_SPAN, cy + ARM_HALF_WIDTH, ARM_HIGH]))]


def params(mcfg) -> dict:
    """The parameters pytree of the analytic field for a model config (its input map's
    constants): {"contract_radius", "encoding_scale", "use_contraction", "scale", "rotation",
    "translation", "tilt"}; the same dict serves every pass."""
    enc = mcfg.encoding_scale if mcfg.encoding_scale > 0 else (mcfg.contract_radius if mcfg.use_contraction else 1.0)
    field = {"contract_radius": jnp.float32(mcfg.contract_radius), "encoding_scale": jnp.float32(enc),
             "use_contraction": jnp.float32(1.0 if mcfg.use_contraction else 0.0),
             "scale": jnp.float32(NORMALIZATION["scale"]), "rotation": jnp.asarray(ROTATION, jnp.float32),
             "translation": jnp.asarray(NORMALIZATION["translation"], jnp.float32),
             "tilt": jnp.asarray(TILT, jnp.float32)}
    return {"coarse": field, "fine": field}


def _uncontract(z, radius):
    """x with contract(x) = z: |x| = (R - 1) / (R - |z|) outside the unit ball, z inside."""
    norm = jnp.linalg.norm(z, axis=-1, keepdims=True)
    outside = (radius - 1.0) / jnp.maximum(radius - norm, 1e-6) / jnp.maximum(norm, 1e-12)
    return jnp.where(norm <= 1.0, z, z * outside)


def to_metric(field_params, x):
    """The field's input x [..., 3] -> metric points [..., 3] (closed form of the input map and
    the normalisation record)."""
    z = x * field_params["encoding_scale"]
    scene = jnp.where(field_params["use_contraction"] > 0, _uncontract(z, field_params["contract_radius"]), z)
    return jnp.einsum("ji,...j->...i", field_params["rotation"], scene) / field_params["scale"] \
        - field_params["translation"]


def inside_tower(p):
    """Mask [...] of points p [..., 3] of the tower's frame inside a solid of the tower (jnp or np)."""
    xp = jnp if isinstance(p, jnp.ndarray) else np
    hit = xp.zeros(p.shape[:-1], bool)
    for lo, hi in boxes():
        hit = hit | xp.all((p >= lo) & (p <= hi), axis=-1)
    return hit


def apply(field_params, cfg, x, viewdirs=None, appearance=None, transient=None) -> dict:
    """`fields.apply` of the analytic scene (module docstring). x [..., 3] -> {"sigma" [...],
    "rgb" [..., 3]}."""
    p = to_metric(field_params, x) @ field_params["tilt"]        # the tower's frame: TILT^T p_metric
    tower = inside_tower(p)
    ground = (p[..., 2] <= GROUND_Z) & (p[..., 2] >= GROUND_Z - 2.0)
    sigma = jnp.where(tower | ground, SIGMA, 0.0)
    rgb = jnp.where(tower[..., None], jnp.asarray(TOWER_RGB), jnp.asarray(GROUND_RGB))
    return {"sigma": sigma, "rgb": jnp.broadcast_to(rgb, p.shape)}


def distance_to_tower_surface(p: np.ndarray) -> np.ndarray:
    """Distance of points p [N, 3] of the tower's frame to the surface of the union of its boxes
    (brute force over the boxes: outside, the nearest box; inside, the nearest face out)."""
    p = np.asarray(p, np.float64)
    outside = np.full(len(p), np.inf)
    depth_inside = np.zeros(len(p))
    for lo, hi in boxes():
        q = np.maximum(lo - p, p - hi)                       # > 0 beyond a face
        out = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.all(q <= 0, axis=1)
        outside = np.minimum(outside, np.where(inside, 0.0, out))
        depth_inside = np.maximum(depth_inside, np.where(inside, -np.max(q, axis=1), 0.0))
    return np.where(outside > 0, outside, depth_inside)


def surface_samples(spacing: float = 0.25) -> np.ndarray:
    """Points on the surface of the body's four sides and top (the tower's frame, metres),
    `spacing` apart. Returns [M, 3]."""
    cx, cy = CENTRE
    a = np.arange(-BODY_HALF, BODY_HALF + 1e-9, spacing)
    z = np.arange(GROUND_Z, GROUND_Z + HEIGHT + 1e-9, spacing)
    aa, zz = np.meshgrid(a, z, indexing="ij")
    aa, zz = aa.ravel(), zz.ravel()
    sides = [np.column_stack([cx + s * BODY_HALF + 0 * aa, cy + aa, zz]) for s in (-1, 1)]
    sides += [np.column_stack([cx + aa, cy + s * BODY_HALF + 0 * aa, zz]) for s in (-1, 1)]
    u, v = np.meshgrid(a, a, indexing="ij")
    top = np.column_stack([cx + u.ravel(), cy + v.ravel(), np.full(u.size, GROUND_Z + HEIGHT)])
    return np.unique(np.round(np.concatenate(sides + [top]), 9), axis=0)


def dataset(frames: int = 8, width: int = 40, height: int = 30):
    """Cameras on a ring (radius 2.2, 1.1 above the origin, looking at the tower's middle) of
    the normalised scene, with NORMALIZATION as the dataset's record (meta states it: metres).
    Images are blank: the field is analytic."""
    from pathlib import Path

    from jaxnerf_grid.data.dataset import Dataset
    from jaxnerf_grid.nerf import rays as rays_lib

    fx = 0.5 * width / np.tan(np.radians(25))
    c2w = [np.asarray(rays_lib.look_at([2.2 * np.cos(a), 2.2 * np.sin(a), 1.1], [0, 0, -0.2]))
           for a in 2 * np.pi * (np.arange(frames) + 0.25) / frames]
    return Dataset(root=Path("analytic"), images=np.zeros((frames, height, width, 3), np.float32),
                   c2w=np.asarray(c2w, np.float32),
                   intrinsics=np.tile(np.array([[fx, fx, width / 2, height / 2]], np.float32), (frames, 1)),
                   split={"train": np.arange(frames), "test": np.arange(0)}, near=0.5, far=4.5,
                   normalization={k: (np.asarray(v).tolist() if k != "scale" else v) for k, v in NORMALIZATION.items()},
                   meta={"scene_normalization": NORMALIZATION})


def clear_compiled() -> None:
    """Clears the compiled functions that may hold a field's apply (export's density, the views'
    renderers): call before putting `apply` in place and after taking it away."""
    from jaxnerf_grid.export import field as export_field
    from jaxnerf_grid.render import views

    export_field._compiled.cache_clear()
    views._render_chunk_fn.cache_clear()
    views._render_frame_fn.cache_clear()
