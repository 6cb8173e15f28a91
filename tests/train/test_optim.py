"""Tests for jaxnerf_grid.train.optim against independent references (torch.optim.Adam, numpy,
closed forms, numpy.linalg.lstsq)."""

import math
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnerf_grid.train import optim


def rosenbrock_jax(params):
    x = params["x"]
    y = params["y"]
    return jnp.sum((1.0 - x) ** 2 + 100.0 * (y - x**2) ** 2)


def rosenbrock_torch(x, y):
    return ((1.0 - x) ** 2 + 100.0 * (y - x**2) ** 2).sum()


X0 = np.array([-1.2, 0.5, 2.0], np.float32)
Y0 = np.array([1.0, -0.3, 3.5], np.float32)


def run_torch_adam(steps, lr, eps, lr_lambda=None, max_norm=0.0):
    torch = pytest.importorskip("torch")
    x = torch.tensor(X0, requires_grad=True)
    y = torch.tensor(Y0, requires_grad=True)
    opt = torch.optim.Adam([x, y], lr=lr, betas=(0.9, 0.999), eps=eps)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda) if lr_lambda else None
    for _ in range(steps):
        opt.zero_grad()
        rosenbrock_torch(x, y).backward()
        if max_norm > 0:
            torch.nn.utils.clip_grad_norm_([x, y], max_norm)
        opt.step()
        if sched:
            sched.step()
    return x.detach().numpy(), y.detach().numpy()


def test_adam_matches_torch_constant_lr():
    opt = optim.adam(0.01, eps=1e-8)
    params = {"x": jnp.asarray(X0), "y": jnp.asarray(Y0)}
    state = opt.init(params)

    @jax.jit
    def step(params, state):
        grads = jax.grad(rosenbrock_jax)(params)
        return optim.apply_gradients(opt, params, state, grads)

    for _ in range(50):
        params, state = step(params, state)
    tx, ty = run_torch_adam(50, 0.01, 1e-8)
    assert int(state.count) == 50
    np.testing.assert_allclose(np.asarray(params["x"]), tx, atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.asarray(params["y"]), ty, atol=1e-5, rtol=0)
    assert not np.allclose(tx, X0, atol=0.1)  # the comparison is not vacuous


def test_adam_schedule_and_clipping_match_torch_through_solver():
    lr_init, lr_final, warm, total = 0.02, 0.002, 10, 50
    sched = optim.make_lr_schedule(lr_init, lr_final, warm, total)
    opt = optim.adam(sched, eps=1e-6, max_grad_norm=5.0)
    solver = optim.make_solver(lambda p: (rosenbrock_jax(p), None), opt)
    params = {"x": jnp.asarray(X0), "y": jnp.asarray(Y0)}
    state = solver.init_state(params)
    step = jax.jit(lambda p, s: optim.guarded_update(solver, p, s))
    for _ in range(50):
        params, state, _, finite = step(params, state)
        assert bool(finite)

    def lam(i):  # the closed form, written independently of the code
        if i < warm:
            return 0.01 + 0.99 * i / warm
        u = min((i - warm) / (total - warm), 1.0)
        return math.exp((1 - u) * math.log(lr_init) + u * math.log(lr_final)) / lr_init

    tx, ty = run_torch_adam(50, lr_init, 1e-6, lr_lambda=lam, max_norm=5.0)
    np.testing.assert_allclose(np.asarray(params["x"]), tx, atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.asarray(params["y"]), ty, atol=1e-5, rtol=0)


def test_lr_schedule_closed_form():
    lr_init, lr_final, warm, total = 5e-4, 5e-6, 100, 1100
    expected = {
        0: 5e-6,                       # 1 % of lr_init
        50: 5e-4 * (0.01 + 0.99 * 0.5),
        100: 5e-4,
        600: math.sqrt(5e-4 * 5e-6),   # half-way in log space: geometric mean
        1100: 5e-6,
        5000: 5e-6,
    }
    for step, value in expected.items():
        got = float(optim.lr_schedule(step, lr_init, lr_final, warm, total))
        assert got == pytest.approx(value, rel=1e-5), step
    jitted = jax.jit(lambda s: optim.lr_schedule(s, lr_init, lr_final, warm, total))
    assert float(jitted(600)) == pytest.approx(math.sqrt(5e-4 * 5e-6), rel=1e-5)
    # no warm-up: starts at lr_init
    assert float(optim.lr_schedule(0, 1e-3, 1e-5, 0, 100)) == pytest.approx(1e-3, rel=1e-6)
    assert float(optim.lr_schedule(50, 1e-3, 1e-5, 0, 100)) == pytest.approx(1e-4, rel=1e-5)


def test_clip_by_global_norm_vs_numpy():
    rng = np.random.default_rng(0)
    tree = {"a": rng.normal(size=(3, 4)).astype(np.float32), "b": [rng.normal(size=5).astype(np.float32)]}
    flat = np.concatenate([tree["a"].ravel(), tree["b"][0].ravel()])
    norm = np.sqrt(np.sum(flat.astype(np.float64) ** 2))
    for max_norm in (0.5 * norm, 2.0 * norm):
        clipped = optim.clip_by_global_norm(jax.tree_util.tree_map(jnp.asarray, tree), max_norm)
        scale = min(1.0, max_norm / norm)
        np.testing.assert_allclose(np.asarray(clipped["a"]), tree["a"] * scale, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(np.asarray(clipped["b"][0]), tree["b"][0] * scale, rtol=1e-6, atol=1e-7)
    same = optim.clip_by_global_norm(tree, 0.0)
    assert same is tree
    assert float(optim.global_norm(tree)) == pytest.approx(norm, rel=1e-6)


def poisoned_loss(params, target, poison):
    w = params["w"]
    return jnp.sum((w - target) ** 2) + poison, {"w0": w[0]}


def test_guarded_update_skips_nan_loss_and_applies_normal_step():
    solver = optim.make_solver(poisoned_loss, optim.adam(0.1))
    params = {"w": jnp.array([1.0, 2.0, 3.0])}
    target = jnp.zeros(3)
    state = solver.init_state(params, target, 0.0)
    step = jax.jit(lambda p, s, t, z: optim.guarded_update(solver, p, s, t, z))

    p1, s1, _, finite = step(params, state, target, jnp.float32(0.0))
    assert bool(finite)
    # first Adam step moves every coordinate by lr against the gradient sign
    np.testing.assert_allclose(np.asarray(p1["w"]), [0.9, 1.9, 2.9], atol=1e-6)
    assert int(s1.iter_num) == 1

    p2, s2, _, finite = step(p1, s1, target, jnp.float32(np.nan))
    assert not bool(finite)
    np.testing.assert_array_equal(np.asarray(p2["w"]), np.asarray(p1["w"]))
    for a, b in zip(jax.tree_util.tree_leaves(s2), jax.tree_util.tree_leaves(s1)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    p3, s3, _, finite = step(p2, s2, target, jnp.float32(0.0))
    assert bool(finite) and int(s3.iter_num) == 2 and int(s3.internal_state.count) == 2
    assert np.all(np.asarray(p3["w"]) < np.asarray(p2["w"]))


def test_guarded_update_skips_infinite_gradient_with_finite_loss():
    # sqrt at 0: loss 0, gradient +inf
    solver = optim.make_solver(lambda p: (jnp.sum(jnp.sqrt(p["w"])), None), optim.adam(0.1))
    params = {"w": jnp.array([0.0, 1.0])}
    state = solver.init_state(params)
    p1, s1, _, finite = optim.guarded_update(solver, params, state)
    assert not bool(finite)
    np.testing.assert_array_equal(np.asarray(p1["w"]), [0.0, 1.0])
    assert int(s1.internal_state.count) == 0


def test_guarded_apply():
    opt = optim.adam(0.1)
    params = {"w": jnp.array([1.0, -1.0])}
    state = opt.init(params)
    apply = jax.jit(lambda p, s, g, l: optim.guarded_apply(opt, p, s, g, l))
    p1, s1, finite = apply(params, state, {"w": jnp.array([1.0, jnp.nan])}, 1.0)
    assert not bool(finite)
    np.testing.assert_array_equal(np.asarray(p1["w"]), [1.0, -1.0])
    assert int(s1.count) == 0
    p2, s2, finite = apply(params, state, {"w": jnp.array([1.0, -2.0])}, jnp.inf)
    assert not bool(finite) and int(s2.count) == 0
    p3, s3, finite = apply(params, state, {"w": jnp.array([1.0, -2.0])}, 1.0)
    assert bool(finite) and int(s3.count) == 1
    np.testing.assert_allclose(np.asarray(p3["w"]), [0.9, -0.9], atol=1e-6)


def test_jaxopt_optax_solver_with_our_adam_solves_least_squares():
    import jaxopt

    assert "optax" not in sys.modules  # jaxopt + our adam, no optax involved
    rng = np.random.default_rng(1)
    a = rng.normal(size=(40, 4)).astype(np.float32)
    b = rng.normal(size=40).astype(np.float32)
    expected = np.linalg.lstsq(a.astype(np.float64), b.astype(np.float64), rcond=None)[0]

    def loss(w, a, b):
        return jnp.mean((a @ w - b) ** 2)

    solver = jaxopt.OptaxSolver(opt=optim.adam(0.05), fun=loss, maxiter=1500, tol=1e-6)
    w, state = solver.run(jnp.zeros(4), a, b)
    np.testing.assert_allclose(np.asarray(w), expected, atol=2e-4)
    assert "optax" not in sys.modules


@pytest.mark.skipif(jax.local_device_count() < 2, reason="needs 2 devices (XLA_FLAGS host device count)")
def test_pmap_step_matches_single_device_full_batch():
    n = 2
    rng = np.random.default_rng(2)
    a = rng.normal(size=(16, 3)).astype(np.float32)
    b = rng.normal(size=16).astype(np.float32)

    def loss(params, a, b):
        r = a @ params["w"] - b
        return jnp.mean(r**2), {"rmax": jnp.max(jnp.abs(r))}

    opt = optim.adam(0.05)
    params = {"w": jnp.zeros(3)}

    single = optim.make_solver(loss, opt)
    state = single.init_state(params, a, b)
    p_ref = params
    single_step = jax.jit(lambda p, s, a, b: optim.guarded_update(single, p, s, a, b))
    for _ in range(5):
        p_ref, state, _, _ = single_step(p_ref, state, a, b)

    rep = lambda t: jax.tree_util.tree_map(lambda x: jnp.stack([x] * n), t)  # noqa: E731
    a_s, b_s = a.reshape(n, -1, 3), b.reshape(n, -1)

    # gradients computed and pmean-ed by the caller, then guarded_apply
    def manual(p, s, a, b):
        (l, _), g = jax.value_and_grad(loss, has_aux=True)(p, a, b)
        l, g = jax.lax.pmean((l, g), "batch")
        return optim.guarded_apply(opt, p, s, g, l)

    step2 = jax.pmap(manual, axis_name="batch")
    p_r, s_r = rep(params), rep(opt.init(params))
    for _ in range(5):
        p_r, s_r, finite = step2(p_r, s_r, a_s, b_s)
    np.testing.assert_allclose(np.asarray(p_r["w"]), np.stack([p_ref["w"]] * n), atol=1e-6)


def lazy_adam_numpy(table, other, grads, lrs, b1, b2, eps):
    """Reference lazy Adam, row by row in float64: a row of `table` whose gradient is all zero
    keeps its moments and value; `other` (a dense leaf) takes plain Adam. Bias correction by the
    global step count. grads: [(g_table, g_other)] per step; lrs: the rate of each step."""
    table, other = table.astype(np.float64).copy(), other.astype(np.float64).copy()
    m, v = np.zeros_like(table), np.zeros_like(table)
    mo, vo = np.zeros_like(other), np.zeros_like(other)
    for t, ((g, go), lr) in enumerate(zip(grads, lrs), start=1):
        for r in range(table.shape[0]):
            if not np.any(g[r] != 0):
                continue
            m[r] = b1 * m[r] + (1 - b1) * g[r]
            v[r] = b2 * v[r] + (1 - b2) * g[r] ** 2
            table[r] -= lr * (m[r] / (1 - b1 ** t)) / (np.sqrt(v[r] / (1 - b2 ** t)) + eps)
        mo = b1 * mo + (1 - b1) * go
        vo = b2 * vo + (1 - b2) * go ** 2
        other -= lr * (mo / (1 - b1 ** t)) / (np.sqrt(vo / (1 - b2 ** t)) + eps)
    return table, other, m, v


def test_lazy_adam_matches_a_numpy_reference_on_touched_and_untouched_rows():
    rng = np.random.default_rng(3)
    table0 = rng.normal(size=(6, 2)).astype(np.float32)
    other0 = rng.normal(size=(3,)).astype(np.float32)
    # rows 0 and 5 never touched; row 2 only on step 1, then idle (dense Adam would keep moving it);
    # row 3 touched on steps 1 and 4; row 1 has one zero entry on step 2 (the row is still touched)
    touched = [[1, 2, 3, 4], [1, 4], [4], [1, 3, 4], [1, 4]]
    grads = []
    for rows in touched:
        g = np.zeros((6, 2), np.float32)
        g[rows] = rng.normal(size=(len(rows), 2))
        grads.append((g, rng.normal(size=(3,)).astype(np.float32)))
    grads[1][0][1, 0] = 0.0
    schedule = optim.make_lr_schedule(0.05, 0.01, 2, 5)
    opt = optim.adam(schedule, b1=0.9, b2=0.99, eps=1e-6, lazy_keys=("table",))
    params = {"grid": {"table": jnp.asarray(table0)}, "other": jnp.asarray(other0)}
    state = opt.init(params)
    step = jax.jit(lambda p, s, g: optim.apply_gradients(opt, p, s, g))
    for g, go in grads:
        params, state = step(params, state, {"grid": {"table": jnp.asarray(g)}, "other": jnp.asarray(go)})
    lrs = [float(schedule(k)) for k in range(len(grads))]
    table, other, m, v = lazy_adam_numpy(table0, other0, grads, lrs, 0.9, 0.99, 1e-6)
    np.testing.assert_allclose(np.asarray(params["grid"]["table"]), table, atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(params["other"]), other, atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(state.mu["grid"]["table"]), m, atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(state.nu["grid"]["table"]), v, atol=1e-7, rtol=0)
    np.testing.assert_array_equal(np.asarray(params["grid"]["table"])[[0, 5]], table0[[0, 5]])
    assert int(state.count) == len(grads)
    # not vacuous: dense Adam moves row 2 after its only gradient, lazy Adam does not
    dense = optim.adam(schedule, b1=0.9, b2=0.99, eps=1e-6)
    p_dense, s_dense = {"grid": {"table": jnp.asarray(table0)}, "other": jnp.asarray(other0)}, None
    s_dense = dense.init(p_dense)
    for g, go in grads:
        p_dense, s_dense = optim.apply_gradients(dense, p_dense, s_dense,
                                                 {"grid": {"table": jnp.asarray(g)}, "other": jnp.asarray(go)})
    assert abs(float(p_dense["grid"]["table"][2, 0]) - table[2, 0]) > 1e-3
    np.testing.assert_allclose(np.asarray(p_dense["other"]), other, atol=1e-6, rtol=0)


def test_touched_rows_marks_rows_with_any_nonzero_entry():
    g = jnp.asarray([[0.0, 0.0], [0.0, -1e-30], [2.0, 0.0]])
    np.testing.assert_array_equal(np.asarray(optim.touched_rows(g))[:, 0], [False, True, True])
    assert optim.touched_rows(jnp.zeros((4, 2, 3))).shape == (4, 1, 1)
