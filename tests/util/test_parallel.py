"""A render sharded with pmap over the CPU devices equals the single-device result."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.nerf import coords
from jaxnerf_grid.nerf import volume as render
from jaxnerf_grid.nerf.samplers import s_space as sampling
from jaxnerf_grid.util import parallel


def toy_render(rays_o, rays_d, key_data):
    """A closed-form density field (a soft ball) rendered with the s-space sampler."""
    near = jnp.full(rays_o.shape[:-1], 0.2)
    far = jnp.full(rays_o.shape[:-1], 50.0)
    s_to_t = sampling.ray_warp("disparity", near[..., None], far[..., None])[1]
    t_edges = s_to_t(sampling.stratified_s(None, near.shape, 32))
    t_mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    points = rays_o[..., None, :] + t_mid[..., None] * rays_d[..., None, :]
    z = coords.contract(points, 2.0)
    density = 20.0 * jax.nn.sigmoid(10.0 * (0.6 - jnp.linalg.norm(z, axis=-1)))
    rgb = jax.nn.sigmoid(z)
    w = render.alpha_weights(density, t_edges, rays_d)
    out = render.composite(w, rgb, t_edges, background=1.0)
    return {"rgb": out["rgb"], "depth": out["depth"]}


def test_pmap_render_equals_single_device():
    if jax.local_device_count() < 2:
        pytest.skip("needs XLA_FLAGS=--xla_force_host_platform_device_count=2 (set by .ci/run)")
    rng = np.random.default_rng(0)
    origins = jnp.asarray(rng.normal(size=(37, 3)) * 0.1 + np.array([0, 0, 3.0]), jnp.float32)
    dirs = rng.normal(size=(37, 3)) * 0.2 + np.array([0, 0, -1.0])
    dirs = jnp.asarray(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True), jnp.float32)
    single = jax.jit(lambda o, d: toy_render(o, d, None))(origins, dirs)
    pmapped = jax.pmap(lambda batch: toy_render(batch[0], batch[1], None), devices=parallel.devices(2))
    sharded = parallel.run_sharded(pmapped, (origins, dirs), 2)  # 37 rows: padded to 38, trimmed
    for name in single:
        assert sharded[name].shape == single[name].shape
        np.testing.assert_allclose(np.asarray(sharded[name]), np.asarray(single[name]), rtol=1e-6, atol=1e-6)
    assert jax.local_device_count() == 2


def test_shard_unshard_round_trip_and_errors():
    x = jnp.arange(24.0).reshape(6, 4)
    np.testing.assert_array_equal(np.asarray(parallel.unshard(parallel.shard(x, 2))), np.asarray(x))
    with pytest.raises(ValueError, match="does not divide"):
        parallel.shard(jnp.ones((5, 2)), 2)


def test_replicate_feeds_pmap():
    n = jax.local_device_count()
    params = {"w": jnp.arange(3.0), "b": jnp.asarray(2.0)}
    rep = parallel.replicate(params, n)
    assert rep["w"].shape == (n, 3) and rep["b"].shape == (n,)
    out = jax.pmap(lambda p: p["w"] * p["b"])(rep)
    np.testing.assert_allclose(np.asarray(out), np.tile([0.0, 2.0, 4.0], (n, 1)))
    back = parallel.unreplicate(rep)
    np.testing.assert_array_equal(back["w"], [0.0, 1.0, 2.0])
    assert float(back["b"]) == 2.0


def test_pad_to_multiple_repeats_the_last_row():
    padded, count = parallel.pad_to_multiple(np.arange(10.0).reshape(5, 2), 4)
    assert count == 5 and padded.shape == (8, 2)
    np.testing.assert_array_equal(padded[5:], [[8.0, 9.0]] * 3)
    same, _ = parallel.pad_to_multiple(np.ones((4, 1)), 4)
    assert same.shape == (4, 1)
