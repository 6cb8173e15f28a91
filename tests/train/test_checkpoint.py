"""Tests for jaxnerf_grid.train.checkpoint: bit-exact round trip, keep-k, atomicity, corrupt
fallback, clear mismatch errors, and an exact resume of an Adam run."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.train import checkpoint as ckpt
from jaxnerf_grid.train import optim
from jaxnerf_grid.util.io import DataError


def make_state(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "params": {
            "mlp": [
                {"w": jnp.asarray(rng.normal(size=(4, 3)).astype(np.float32)),
                 "b": jnp.asarray(rng.normal(size=3).astype(np.float32))},
                {"w": jnp.asarray(rng.normal(size=(3, 1)).astype(np.float32))},
            ],
            "bf16": jnp.asarray(rng.normal(size=2).astype(np.float32)).astype(jnp.bfloat16),
        },
        "counts": jnp.asarray(rng.integers(-5, 5, size=6).astype(np.int32)),
        "rng": jax.random.PRNGKey(seed + 7),                       # raw uint32 [2]
        "typed_key": jax.random.split(jax.random.key(seed + 3), 3),  # typed keys [3]
        "step": jnp.asarray(1234, jnp.int32),
        "epoch": 5,                                                  # Python scalar
        "host": np.arange(3, dtype=np.float64) / 3.0,               # numpy leaf
    }


def assert_bit_equal(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        if hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            assert y.dtype == x.dtype
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def test_round_trip_bit_exact(tmp_path):
    state = make_state()
    path = ckpt.save_checkpoint(tmp_path, 1234, state)
    assert path == tmp_path / "checkpoints" / "ckpt_00001234.npz"
    template = make_state(seed=99)  # same structure, different values
    restored = ckpt.load_checkpoint(path, template)
    assert_bit_equal(restored, state)
    assert isinstance(restored["epoch"], int) and restored["epoch"] == 5
    assert isinstance(restored["host"], np.ndarray)
    assert isinstance(restored["params"]["mlp"][0]["w"], jax.Array)
    # the typed keys still work as keys, giving the same draws
    np.testing.assert_array_equal(np.asarray(jax.random.uniform(restored["typed_key"][1], (4,))),
                                  np.asarray(jax.random.uniform(state["typed_key"][1], (4,))))
    # an eval_shape template works too
    shapes = jax.eval_shape(lambda: {k: v for k, v in make_state().items() if k not in ("epoch", "host")})
    partial = {k: v for k, v in state.items() if k not in ("epoch", "host")}
    ckpt.save_checkpoint(tmp_path / "b", 3, partial)
    assert_bit_equal(ckpt.restore_latest(tmp_path / "b", shapes)[0], partial)


def test_keep_k_and_latest(tmp_path):
    state = {"w": jnp.zeros(3)}
    assert ckpt.latest_checkpoint(tmp_path) is None
    assert ckpt.restore_latest(tmp_path, state) is None
    for step in (10, 20, 30, 40, 50):
        ckpt.save_checkpoint(tmp_path, step, {"w": jnp.full(3, float(step))}, keep=2)
    names = sorted(os.listdir(tmp_path / "checkpoints"))
    assert names == ["ckpt_00000040.npz", "ckpt_00000050.npz"]
    assert ckpt.latest_checkpoint(tmp_path).name == "ckpt_00000050.npz"
    restored, step = ckpt.restore_latest(tmp_path, state)
    assert step == 50 and np.all(np.asarray(restored["w"]) == 50.0)
    ckpt.save_checkpoint(tmp_path, 60, state, keep=3)
    assert len(os.listdir(tmp_path / "checkpoints")) == 3


def test_crash_during_write_leaves_no_checkpoint_file(tmp_path, monkeypatch):
    ckpt.save_checkpoint(tmp_path, 1, {"w": jnp.ones(2)})

    def broken_writer(handle, arrays):
        handle.write(b"PK\x03\x04 partial zip bytes")
        raise OSError("disk full (simulated)")

    (tmp_path / "checkpoints" / ".ckpt_00000009.npz.abc.tmp").write_bytes(b"stale")  # a killed writer's
    monkeypatch.setattr(ckpt, "_write_npz", broken_writer)
    with pytest.raises(DataError, match=r"ckpt_00000002\.npz: cannot write \(disk full \(simulated\)\)"):
        ckpt.save_checkpoint(tmp_path, 2, {"w": jnp.ones(2)}, keep=1)  # the OSError names the file (io.naming_path)
    assert sorted(os.listdir(tmp_path / "checkpoints")) == ["ckpt_00000001.npz"]  # no temp left
    restored, step = ckpt.restore_latest(tmp_path, {"w": jnp.zeros(2)})
    assert step == 1


@pytest.mark.parametrize("damage", ["garbage", "truncate", "bitflip"])
def test_corrupt_newest_falls_back_with_warning(tmp_path, damage):
    for step in (1, 2):
        ckpt.save_checkpoint(tmp_path, step, {"w": jnp.arange(4, dtype=jnp.float32) + step})
    newest = ckpt.latest_checkpoint(tmp_path)
    raw = newest.read_bytes()
    if damage == "garbage":
        newest.write_bytes(b"this is not a zip file at all" * 10)
    elif damage == "truncate":
        newest.write_bytes(raw[: len(raw) // 2])
    else:  # one flipped bit inside the stored array data: caught by the zip member's CRC
        at = raw.index((np.arange(4, dtype=np.float32) + 2).tobytes()) + 5
        newest.write_bytes(raw[:at] + bytes([raw[at] ^ 0x01]) + raw[at + 1:])
    with pytest.raises(ckpt.CorruptCheckpointError, match="ckpt_00000002"):
        ckpt.load_checkpoint(newest, {"w": jnp.zeros(4)})
    with pytest.warns(RuntimeWarning, match="ckpt_00000002"):
        restored, step = ckpt.restore_latest(tmp_path, {"w": jnp.zeros(4)})
    assert step == 1 and np.array_equal(np.asarray(restored["w"]), np.arange(4) + 1.0)
    # all unreadable -> a clear error rather than a silent restart
    ckpt.checkpoint_path(tmp_path, 1).write_bytes(b"junk")
    with pytest.warns(RuntimeWarning), pytest.raises(ckpt.CorruptCheckpointError, match="no readable"):
        ckpt.restore_latest(tmp_path, {"w": jnp.zeros(4)})


def test_mismatch_errors_name_key_and_file(tmp_path):
    path = ckpt.save_checkpoint(tmp_path, 7, {"a": jnp.zeros(3), "b": jnp.zeros(2, jnp.int32),
                                              "k": jax.random.key(0)})
    good = {"a": jnp.zeros(3), "b": jnp.zeros(2, jnp.int32), "k": jax.random.key(1)}
    ckpt.load_checkpoint(path, good)
    cases = [
        ({**good, "a": jnp.zeros(4)}, r"\['a'\].*shape"),
        ({**good, "b": jnp.zeros(2, jnp.float32)}, r"\['b'\].*dtype"),
        ({**good, "k": jnp.zeros(2, jnp.uint32)}, r"\['k'\].*typed PRNG key"),
        ({"a": good["a"], "k": good["k"]}, r"not in the template: \['b'\]"),
        ({**good, "c": jnp.zeros(1)}, r"missing from the file: \['c'\]"),
    ]
    for template, pattern in cases:
        with pytest.raises(ckpt.CheckpointError, match=pattern) as info:
            ckpt.load_checkpoint(path, template)
        assert "ckpt_00000007.npz" in str(info.value)
    # a mismatch is not mistaken for corruption: restore_latest raises, no fallback
    with pytest.raises(ckpt.CheckpointError, match="shape"):
        ckpt.restore_latest(tmp_path, cases[0][0])


def test_exact_resume_of_adam_run(tmp_path):
    """10 steps straight == 5 steps, save, reload into a fresh template, 5 more steps."""
    opt = optim.adam(optim.make_lr_schedule(0.05, 0.005, 2, 10), max_grad_norm=1.0)

    def loss(params, key):
        x = jax.random.normal(key, (8, 3))
        return jnp.mean((x @ params["w"] - jnp.sin(x[:, 0])) ** 2)

    @jax.jit
    def step(state):
        key, sub = jax.random.split(state["key"])
        grads = jax.grad(loss)(state["params"], sub)
        params, opt_state = optim.apply_gradients(opt, state["params"], state["opt"], grads)
        return {"params": params, "opt": opt_state, "key": key, "step": state["step"] + 1}

    def fresh():
        params = {"w": jnp.zeros(3)}
        return {"params": params, "opt": opt.init(params), "key": jax.random.key(0),
                "step": jnp.zeros([], jnp.int32)}

    straight = fresh()
    for _ in range(10):
        straight = step(straight)

    state = fresh()
    for _ in range(5):
        state = step(state)
    ckpt.save_checkpoint(tmp_path, int(state["step"]), state)
    resumed, at = ckpt.restore_latest(tmp_path, fresh())
    assert at == 5
    for _ in range(5):
        resumed = step(resumed)
    assert_bit_equal(resumed, straight)
    assert not np.allclose(np.asarray(straight["params"]["w"]), 0.0)
