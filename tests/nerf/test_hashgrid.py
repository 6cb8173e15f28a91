"""fields/hashgrid.py and fields/grid.py against a per-point loop written here from the
Instant-NGP paper (Müller et al. 2022, Sec. 3), and finite differences."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.nerf import fields, models, samplers
from jaxnerf_grid.nerf.fields import hashgrid

PRIMES = (1, 2654435761, 805459861)


def _resolutions(cfg):
    b = math.exp((math.log(cfg.max_resolution) - math.log(cfg.min_resolution)) / max(cfg.num_levels - 1, 1))
    return [int(math.floor(cfg.min_resolution * b ** level + 1e-6)) for level in range(cfg.num_levels)]


def _brute_encode(table, cfg, x):
    """One point at a time, one level at a time, one corner at a time."""
    size = 2 ** cfg.log2_table_size
    out = np.zeros((len(x), cfg.num_levels * cfg.features_per_level))
    offset = 0
    rows_all, weights_all = [], []
    for level, res in enumerate(_resolutions(cfg)):
        dense = (res + 1) ** 3 <= size
        rows_level = []
        weights_level = []
        for n, point in enumerate(x):
            u = np.clip((np.asarray(point, np.float64) + 1.0) / 2.0, 0.0, 1.0)
            p = u * res
            low = np.minimum(np.floor(p), res - 1).astype(np.int64)
            frac = p - low
            rows, ws = [], []
            for dz in (0, 1):
                for dy in (0, 1):
                    for dx in (0, 1):
                        v = low + np.array([dx, dy, dz])
                        if dense:
                            row = v[0] + v[1] * (res + 1) + v[2] * (res + 1) ** 2
                        else:
                            row = ((v[0] * PRIMES[0]) ^ (v[1] * PRIMES[1]) ^ (v[2] * PRIMES[2])) % 2 ** 32 % size
                        w = ((frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1])
                             * (frac[2] if dz else 1 - frac[2]))
                        rows.append(offset + row)
                        ws.append(w)
                        span = slice(level * cfg.features_per_level, (level + 1) * cfg.features_per_level)
                        out[n, span] += w * table[offset + row]
            rows_level.append(rows)
            weights_level.append(ws)
        rows_all.append(rows_level)
        weights_all.append(weights_level)
        offset += (res + 1) ** 3 if dense else size
    # [N, L, 8]
    return out, np.transpose(np.array(rows_all), (1, 0, 2)), np.transpose(np.array(weights_all), (1, 0, 2))


@pytest.mark.parametrize("cfg", [
    hashgrid.HashConfig(num_levels=4, features_per_level=2, log2_table_size=12, min_resolution=4, max_resolution=64),
    # a tiny table: every level but the first is hashed and collides
    hashgrid.HashConfig(num_levels=3, features_per_level=3, log2_table_size=6, min_resolution=2, max_resolution=40),
])
def test_encoding_matches_per_point_loop(cfg):
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.05, 1.05, (40, 3)).astype(np.float32)
    x[0] = [1.0, -1.0, 1.0]  # the corners of the cube
    x[1] = [-1.0, 1.0, 0.0]
    params = hashgrid.init(jax.random.PRNGKey(0), dataclasses.replace(cfg, init_scale=1.0))
    table = np.asarray(params["table"], np.float64)
    want, want_rows, want_w = _brute_encode(table, cfg, x)
    rows, w = hashgrid.corners(cfg, 0.5 * (jnp.asarray(x) + 1.0))
    np.testing.assert_array_equal(np.asarray(rows), want_rows)
    np.testing.assert_allclose(np.asarray(w), want_w, atol=1e-5)
    np.testing.assert_allclose(np.asarray(w).sum(-1), 1.0, atol=1e-6)
    got = hashgrid.encode(params, cfg, jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)


def test_dense_and_hashed_levels_and_table_layout():
    cfg = hashgrid.HashConfig(num_levels=3, features_per_level=2, log2_table_size=10, min_resolution=4,
                              max_resolution=16)
    lay = hashgrid.layout(cfg)
    assert lay.resolutions == (4, 8, 16)
    assert lay.dense == (True, True, False)          # 5^3, 9^3 = 729 <= 1024 < 17^3
    assert lay.sizes == (125, 729, 1024) and lay.offsets == (0, 125, 854)
    assert hashgrid.init(jax.random.PRNGKey(0), cfg)["table"].shape == (125 + 729 + 1024, 2)
    # dense levels give distinct vertices distinct rows; a tiny hashed table must collide
    verts = np.stack(np.meshgrid(*[np.arange(9) / 8.0] * 3, indexing="ij"), -1).reshape(-1, 3)
    rows, _ = hashgrid.corners(cfg, jnp.asarray(verts, jnp.float32))
    corner0 = np.asarray(rows)[:, 1, 0]
    assert len(np.unique(corner0)) == len(np.unique(np.minimum(np.floor(verts * 8), 7), axis=0))
    tiny = hashgrid.HashConfig(num_levels=1, log2_table_size=4, min_resolution=8, max_resolution=8)
    rows, _ = hashgrid.corners(tiny, jnp.asarray(verts, jnp.float32))
    assert np.asarray(rows).max() < 16


def test_encoding_gradient_matches_finite_differences():
    cfg = hashgrid.HashConfig(num_levels=3, features_per_level=2, log2_table_size=8, min_resolution=3,
                              max_resolution=12)
    params = hashgrid.init(jax.random.PRNGKey(1), dataclasses.replace(cfg, init_scale=0.5))
    x = jnp.asarray(np.random.default_rng(1).uniform(-0.9, 0.9, (7, 3)), jnp.float32)
    probe = jnp.asarray(np.random.default_rng(2).normal(size=(7, 6)), jnp.float32)
    f = lambda table, pts: jnp.sum(probe * hashgrid.encode({"table": table}, cfg, pts))  # noqa: E731
    g_table, g_x = jax.grad(f, argnums=(0, 1))(params["table"], x)
    table = np.asarray(params["table"], np.float64)
    # the encoding is linear in the table: d f / d table[r, c] by a central difference, on a few rows
    rows = np.unique(np.asarray(hashgrid.corners(cfg, 0.5 * (x + 1))[0]).reshape(-1))[:12]
    f64 = lambda t: float(f(jnp.asarray(t, jnp.float32), x))  # noqa: E731
    for r in rows:
        for c in range(2):
            step = np.zeros_like(table)
            step[r, c] = 1e-2
            fd = (f64(table + step) - f64(table - step)) / 2e-2
            np.testing.assert_allclose(float(g_table[r, c]), fd, rtol=2e-3, atol=2e-4)
    # in the point: piecewise trilinear, so finite differences inside a cell
    eps = 1e-3
    for i in range(3):
        dx = jnp.zeros_like(x).at[:, i].set(eps)
        fd = (f(params["table"], x + dx) - f(params["table"], x - dx)) / (2 * eps)
        np.testing.assert_allclose(float(jnp.sum(g_x[:, i])), float(fd), rtol=2e-2, atol=2e-3)


def test_computed_once_is_the_identity_bit_for_bit():
    # encode materialises its points through it (an XLA:CPU fusion fix): it must not move them.
    rng = np.random.default_rng(3)
    x = (rng.uniform(-1, 1, (5, 7, 3)) * 10.0 ** rng.integers(-30, 30, (5, 7, 3))).astype(np.float32)
    x[0, 0] = [0.0, -0.0, 1.0]
    np.testing.assert_array_equal(np.asarray(jax.jit(hashgrid.computed_once)(jnp.asarray(x))), x)


def _grid_cfg(**kw):
    base = dict(kind="grid", depth=1, width=16, view_depth=2, view_width=16, dir_max_deg=2,
                density_activation="exp", geo_features=7,
                grid=hashgrid.HashConfig(num_levels=3, features_per_level=2, log2_table_size=10, min_resolution=4,
                                         max_resolution=32))
    base.update(kw)
    return fields.grid.Config(**base)


def test_grid_field_matches_numpy_composition():
    cfg = _grid_cfg(appearance_dim=3, transient_dim=2, transient_depth=1, transient_width=8)
    params = fields.init(jax.random.PRNGKey(3), cfg)
    params["encoding"]["table"] = params["encoding"]["table"] * 1e3
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (5, 3)).astype(np.float32)
    d = rng.normal(size=(5, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    app, tr = rng.normal(size=3).astype(np.float32), rng.normal(size=2).astype(np.float32)
    out = fields.apply(params, cfg, jnp.asarray(x), jnp.asarray(d), jnp.asarray(app), jnp.asarray(tr))
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params)
    h, _, _ = _brute_encode(p["encoding"]["table"], cfg.grid, x)
    h = np.maximum(h @ p["trunk"][0]["w"] + p["trunk"][0]["b"], 0)
    raw = h @ p["density"]["w"] + p["density"]["b"]
    np.testing.assert_allclose(out["sigma"], np.exp(raw[:, 0] + cfg.density_bias), rtol=1e-4)
    enc_d = np.concatenate([np.sin(np.concatenate([d * 2.0 ** k for k in range(2)], -1)),
                            np.cos(np.concatenate([d * 2.0 ** k for k in range(2)], -1)), d], -1)
    v = np.concatenate([raw[:, 1:], enc_d, np.broadcast_to(app, (5, 3))], -1)
    for layer in p["view"]:
        v = np.maximum(v @ layer["w"] + layer["b"], 0)
    np.testing.assert_allclose(out["rgb"], 1 / (1 + np.exp(-(v @ p["rgb"]["w"] + p["rgb"]["b"]))), rtol=1e-4, atol=1e-6)
    t = np.maximum(np.concatenate([raw[:, 1:], np.broadcast_to(tr, (5, 2))], -1) @ p["transient"][0]["w"]
                   + p["transient"][0]["b"], 0)
    t = t @ p["transient_out"]["w"] + p["transient_out"]["b"]
    np.testing.assert_allclose(out["transient_sigma"], np.log1p(np.exp(t[:, 0])), rtol=1e-4)


@pytest.mark.parametrize("method", ["ours", "nerf", "nerfw"])
@pytest.mark.parametrize("sampler", ["hierarchical", "proposal"])
def test_every_method_runs_with_the_grid_field(method, sampler):
    chosen = (samplers.hierarchical.Config(samples=(8, 8)) if sampler == "hierarchical" else
              samplers.proposal.Config(samples=(12, 8), main_samples=8, field=_grid_cfg(width=8)))
    cfg = models.ModelConfig(**{**models.method_defaults(method), "field": _grid_cfg(), "sampler": chosen,
                                "num_images": 2})
    params = models.init(jax.random.PRNGKey(0), cfg)
    assert models.main_field(params, cfg)[1].kind == "grid"
    o = jnp.asarray([[0.0, -3.0, 0.5], [2.5, 0.0, 0.2]])
    d = -o / jnp.linalg.norm(o, axis=-1, keepdims=True)
    out = models.render_rays(params, cfg, o, d, jnp.full(2, 0.5), jnp.full(2, 8.0),
                             jax.random.split(jax.random.PRNGKey(1), 2), jnp.array([0, 1]))
    final = out["final"]
    assert final["rgb"].shape == (2, 3)
    assert final["s_edges"].shape == (2, 17 if sampler == "hierarchical" else 9)  # union of 8 + 8, or 8
    assert np.all(np.isfinite(np.asarray(final["rgb"])))
    if sampler == "proposal":
        assert [r["s_edges"].shape[-1] for r in out["levels"]] == [13, 9, 9]
    else:
        assert [r["s_edges"].shape[-1] for r in out["levels"]] == [9, 17]


def test_grid_config_errors():
    with pytest.raises(ConfigError, match="kind"):
        models.init(jax.random.PRNGKey(0), models.ModelConfig(field=_grid_cfg(kind="voxels")))
    with pytest.raises(ConfigError, match="min_resolution"):
        models.init(jax.random.PRNGKey(0), models.ModelConfig(
            field=_grid_cfg(grid=hashgrid.HashConfig(min_resolution=64, max_resolution=16))))
    with pytest.raises(ConfigError, match="sampler"):
        models.init(jax.random.PRNGKey(0), models.ModelConfig(sampler="uniform"))
