"""Optimiser pieces for NeRF training, driven by jaxopt (no optax anywhere).

What is here:
  * `lr_schedule`: linear warm-up, then log-linear (exponential) decay (mip-NeRF style).
  * `clip_by_global_norm`, `global_norm`, `tree_all_finite`.
  * `adam`: an Adam `GradientTransformation` written in this project (dense, or lazy on the
    rows of the leaves it is told: `lazy_keys`, `lazy_rows`): a NamedTuple with
    `init(params) -> state` and `update(grads, state, params=None) -> (updates, state)`.
    jaxopt's `OptaxSolver` (jaxopt/_src/optax_wrapper.py) only ever calls
    `opt.init(params)` in `init_state` and `opt.update(grad, opt_state, params)` in `update`,
    then applies `params + updates` (cast to each param's dtype) itself, so it takes this
    object as its `opt`; jaxopt never imports optax (optax is not installed in the project's
    environment, and the tests check `"optax" not in sys.modules`).
  * Steps driven by jaxopt:
      - `make_solver(loss_fn, opt)`: a `jaxopt.OptaxSolver` whose `fun(params, *args)`
        returns `(loss, aux)`; `guarded_update(solver, params, state, *args)` does one
        `solver.update` and rolls it back when anything is non-finite
        (experiments/train_builtin_dpt.py steps this way).
      - `apply_gradients` / `guarded_apply`: the optimiser step for gradients the caller has
        already computed (and, under pmap, psum-ed over the devices: train.py's step); it
        still goes through `OptaxSolver.update`, fed by a `fun` that hands back the given
        gradients.

A skipped step leaves the optimiser state untouched, so Adam's step count (and therefore the
learning-rate schedule inside `adam`) does not advance on it; the trainer's own step does.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

with warnings.catch_warnings():  # jaxopt 0.8.x warns on import that it is unmaintained
    warnings.simplefilter("ignore", DeprecationWarning)
    import jaxopt
from jaxopt._src.optax_wrapper import OptaxState

logger = logging.getLogger(__name__)

Schedule = Callable[[jnp.ndarray], jnp.ndarray]

__all__ = [
    "AdamState",
    "GradientTransformation",
    "OptaxState",
    "adam",
    "apply_gradients",
    "clip_by_global_norm",
    "global_norm",
    "guarded_apply",
    "guarded_update",
    "lazy_rows",
    "log_nonfinite",
    "lr_schedule",
    "make_lr_schedule",
    "make_solver",
    "touched_rows",
    "tree_all_finite",
]


# --------------------------------------------------------------------------- schedule


def lr_schedule(step, lr_init: float, lr_final: float, warmup_steps: int, max_steps: int,
                warmup_start: float = 0.01) -> jnp.ndarray:
    """Learning rate at `step`: linear warm-up, then log-linear decay.

    For step < warmup_steps: `lr_init * (warmup_start + (1 - warmup_start) * step / warmup_steps)`,
    i.e. a straight line from `warmup_start * lr_init` (default 1 %) up to `lr_init`.
    From warmup_steps to max_steps: `exp(lerp(log lr_init, log lr_final, u))` with
    `u = (step - warmup_steps) / (max_steps - warmup_steps)`, clipped to [0, 1], so the rate
    is `lr_final` at and after max_steps (the exponential decay of mip-NeRF / NeRF).

    step: scalar (int or float, may be traced). Returns a float32 scalar. jit-safe.
    """
    if lr_init <= 0 or lr_final <= 0:
        raise ValueError(f"lr_schedule: lr_init ({lr_init}) and lr_final ({lr_final}) must be > 0")
    step = jnp.asarray(step, jnp.float32)
    warm = float(max(warmup_steps, 0))
    span = float(max(max_steps - max(warmup_steps, 0), 1))
    ramp = warmup_start + (1.0 - warmup_start) * step / max(warm, 1.0)
    u = jnp.clip((step - warm) / span, 0.0, 1.0)
    decayed = jnp.exp((1.0 - u) * jnp.log(jnp.float32(lr_init)) + u * jnp.log(jnp.float32(lr_final)))
    return jnp.where(step < warm, lr_init * ramp, decayed).astype(jnp.float32)


def make_lr_schedule(lr_init: float, lr_final: float, warmup_steps: int, max_steps: int,
                     warmup_start: float = 0.01) -> Schedule:
    """`lr_schedule` with its constants bound: returns `step -> lr` (for `adam`)."""
    lr_schedule(0, lr_init, lr_final, warmup_steps, max_steps, warmup_start)  # validate now

    def schedule(step):
        return lr_schedule(step, lr_init, lr_final, warmup_steps, max_steps, warmup_start)

    return schedule


# --------------------------------------------------------------------------- tree helpers


def _inexact_leaves(tree) -> list:
    return [x for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]


def global_norm(tree) -> jnp.ndarray:
    """L2 norm over every floating leaf of a pytree, as if concatenated. Returns float32 []."""
    leaves = _inexact_leaves(tree)
    if not leaves:
        return jnp.float32(0.0)
    return jnp.sqrt(sum(jnp.sum(jnp.square(jnp.asarray(x, jnp.float32))) for x in leaves))


def tree_all_finite(tree) -> jnp.ndarray:
    """True (bool []) when every floating leaf is free of NaN and inf. Integer leaves pass."""
    leaves = _inexact_leaves(tree)
    if not leaves:
        return jnp.bool_(True)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def _tree_select(pred, on_true, on_false):
    """Leafwise `jnp.where(pred, a, b)` over two pytrees of the same structure. pred: bool []."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b).astype(jnp.result_type(b)),
                                  on_true, on_false)


def clip_by_global_norm(grads, max_norm: float):
    """Scales the whole gradient pytree by `min(1, max_norm / global_norm(grads))`.

    Same rule as `torch.nn.utils.clip_grad_norm_` (without its 1e-6). `max_norm <= 0`
    disables clipping and returns `grads` unchanged. A non-finite norm gives non-finite
    gradients, which the guards below then catch. Leaf dtypes are kept.
    """
    if max_norm is None or max_norm <= 0:
        return grads
    norm = global_norm(grads)
    scale = jnp.where(norm > max_norm, max_norm / jnp.where(norm > 0, norm, 1.0), 1.0)
    return jax.tree_util.tree_map(lambda g: (g * scale).astype(jnp.result_type(g)), grads)


# --------------------------------------------------------------------------- adam


class GradientTransformation(NamedTuple):
    """The optax protocol, without optax: `init(params) -> state`,
    `update(grads, state, params=None) -> (updates, new_state)`; apply as `params + updates`."""

    init: Callable[[Any], Any]
    update: Callable[..., tuple[Any, Any]]


class AdamState(NamedTuple):
    """count: int32 [] (steps taken so far); mu, nu: pytrees like params (1st / 2nd moments)."""

    count: jnp.ndarray
    mu: Any
    nu: Any


def adam(learning_rate: float | Schedule, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8,
         max_grad_norm: float = 0.0, lazy_keys: tuple[str, ...] = ()) -> GradientTransformation:
    """Adam (Kingma & Ba) with bias correction, optional global-norm clipping first.

    With t = count + 1 after the step and g the (clipped) gradient:
        mu = b1 * mu + (1 - b1) * g;  nu = b2 * nu + (1 - b2) * g**2
        update = -lr(count) * (mu / (1 - b1**t)) / (sqrt(nu / (1 - b2**t)) + eps)
    which is exactly `torch.optim.Adam`'s rule. `learning_rate` is a float or a schedule
    `step -> lr` evaluated at the count *before* the step (0 on the first step). NeRF uses
    eps in 1e-8 .. 1e-6. Moments have each parameter's dtype; count is int32.

    lazy_keys: dict keys (e.g. ("table",), the hash grids' tables) whose leaves get *lazy* Adam
    (`lazy_rows`): a row (`leaf[i]`) whose gradient is zero in every entry keeps its mu, nu
    and value; the other rows take the rule above. Bias correction uses the global count t,
    not a count per row (as TensorFlow's LazyAdam), so the state is the same as dense Adam's
    and a checkpoint of either loads in the other. How it differs from dense Adam: dense Adam
    keeps moving an untouched row by its decaying momentum (mu / sqrt(nu) of earlier steps)
    and decays its moments; lazy Adam freezes it until a batch touches it again, and a row
    touched again after k idle steps resumes with moments decayed by one step instead of k + 1.
    """
    if not callable(learning_rate):
        lr_value = float(learning_rate)
        learning_rate = lambda step: jnp.float32(lr_value)  # noqa: E731
    schedule = learning_rate

    def init(params) -> AdamState:
        zeros = lambda p: jnp.zeros_like(jnp.asarray(p))  # noqa: E731
        return AdamState(count=jnp.zeros([], jnp.int32),
                         mu=jax.tree_util.tree_map(zeros, params),
                         nu=jax.tree_util.tree_map(zeros, params))

    def update(grads, state: AdamState, params=None):
        del params
        grads = clip_by_global_norm(grads, max_grad_norm)
        mu = jax.tree_util.tree_map(lambda m, g: (b1 * m + (1.0 - b1) * g).astype(m.dtype), state.mu, grads)
        nu = jax.tree_util.tree_map(lambda v, g: (b2 * v + (1.0 - b2) * jnp.square(g)).astype(v.dtype),
                                    state.nu, grads)
        count = state.count + 1
        t = count.astype(jnp.float32)
        correction1 = 1.0 - jnp.power(jnp.float32(b1), t)
        correction2 = 1.0 - jnp.power(jnp.float32(b2), t)
        lr = jnp.asarray(schedule(state.count), jnp.float32)

        def step(m, v):
            m_hat = m / correction1
            v_hat = v / correction2
            return (-lr * m_hat / (jnp.sqrt(v_hat) + eps)).astype(m.dtype)

        updates = jax.tree_util.tree_map(step, mu, nu)
        if lazy_keys:
            zeros = jax.tree_util.tree_map(jnp.zeros_like, updates)
            updates, mu, nu = lazy_rows(grads, (updates, mu, nu), (zeros, state.mu, state.nu), lazy_keys)
        return updates, AdamState(count=count, mu=mu, nu=nu)

    return GradientTransformation(init=init, update=update)


def touched_rows(grad: jnp.ndarray) -> jnp.ndarray:
    """grad: [R, ...] -> bool [R, 1, ...] (broadcastable against grad): True where any entry of
    the row is non-zero (a batch's gather reached it)."""
    touched = jnp.any(grad.reshape(grad.shape[0], -1) != 0, axis=1)
    return touched.reshape(grad.shape[:1] + (1,) * (grad.ndim - 1))


def lazy_rows(grads, new: tuple, old: tuple, keys: tuple[str, ...]) -> tuple:
    """Keeps, in the leaves under a dict key of `keys`, the old value of every row whose
    gradient is all zero.

    grads: the gradient pytree; new: a tuple of pytrees like grads (e.g. the step's updates,
    mu, nu); old: one pytree like grads per entry of `new`, the values kept where a row is
    untouched (zeros for the updates, the moments before the step). Leaves under other keys
    (and 0-d leaves) take `new` unchanged. Returns a tuple like `new`.
    """
    def lazy(path) -> bool:
        return any(isinstance(k, jax.tree_util.DictKey) and k.key in keys for k in path)

    flat, treedef = jax.tree_util.tree_flatten_with_path(grads)
    news = [treedef.flatten_up_to(tree) for tree in new]
    olds = [treedef.flatten_up_to(tree) for tree in old]
    out = [list(leaves) for leaves in news]
    for i, (path, g) in enumerate(flat):
        if lazy(path) and jnp.ndim(g) > 0:
            rows = touched_rows(g)
            for j in range(len(new)):
                out[j][i] = jnp.where(rows, news[j][i], olds[j][i]).astype(jnp.result_type(news[j][i]))
    return tuple(treedef.unflatten(leaves) for leaves in out)


# --------------------------------------------------------------------------- jaxopt-driven steps


def make_solver(loss_fn: Callable, opt: GradientTransformation, has_aux: bool = True,
                jit: bool = True) -> jaxopt.OptaxSolver:
    """A `jaxopt.OptaxSolver` stepping `opt` on `loss_fn(params, *args) -> (loss, aux)`
    (or just `loss` when has_aux=False). Start with `state = solver.init_state(params, *args)`
    (evaluates loss_fn once); step with `guarded_update` (or `solver.update`)."""
    return jaxopt.OptaxSolver(fun=loss_fn, opt=opt, has_aux=has_aux, jit=jit, maxiter=1)


def guarded_update(solver: jaxopt.OptaxSolver, params, state: OptaxState, *args, **kwargs):
    """One `solver.update` that is rolled back when it is not finite.

    finite = loss finite & gradient norm finite (jaxopt's `state.error` is the L2 norm of the
    gradient, non-finite iff some gradient is, or on overflow) & new params and new
    optimiser state finite. When not finite, the old params and state are returned
    (`jnp.where` over the pytrees, jit/pmap safe) and the caller should log the skip.

    Returns (params, state, aux, finite): aux is this step's aux (from the attempted step,
    even when skipped, for logging); finite: bool [].
    """
    new_params, new_state = solver.update(params, state, *args, **kwargs)
    finite = (jnp.all(jnp.isfinite(new_state.value)) & jnp.all(jnp.isfinite(new_state.error))
              & tree_all_finite(new_params) & tree_all_finite(new_state.internal_state))
    aux = new_state.aux
    out_params = _tree_select(finite, new_params, params)
    out_state = _tree_select(finite, new_state, state)
    return out_params, out_state, aux, finite


def _given_gradients(params, grads, loss):
    """jaxopt `fun` in value_and_grad form that hands back precomputed gradients."""
    del params
    return (loss, None), grads


def apply_gradients(opt: GradientTransformation, params, opt_state, grads, loss=0.0):
    """One optimiser step with gradients computed (and, under pmap, averaged) by the caller.

    Runs through `jaxopt.OptaxSolver.update` with a `fun` that returns the given gradients,
    so the arithmetic is jaxopt's (`params + opt.update(...)`, cast to each param's dtype).
    params, grads: same pytree; opt_state: `opt.init(params)`. Returns (params, opt_state).
    """
    solver = jaxopt.OptaxSolver(fun=_given_gradients, opt=opt, value_and_grad=True, has_aux=True,
                                jit=False, maxiter=1)
    loss = jnp.asarray(loss, jnp.float32)
    state = OptaxState(iter_num=jnp.zeros([], jnp.int32), value=loss, error=jnp.float32(0.0),
                       internal_state=opt_state, aux=None)
    params, state = solver.update(params, state, grads, loss)
    return params, state.internal_state


def guarded_apply(opt: GradientTransformation, params, opt_state, grads, loss):
    """`apply_gradients`, skipped when the loss, any gradient or any new param/state is
    non-finite. loss: scalar. Returns (params, opt_state, finite: bool [])."""
    new_params, new_opt_state = apply_gradients(opt, params, opt_state, grads, loss)
    finite = (jnp.all(jnp.isfinite(jnp.asarray(loss))) & tree_all_finite(grads)
              & tree_all_finite(new_params) & tree_all_finite(new_opt_state))
    return (_tree_select(finite, new_params, params), _tree_select(finite, new_opt_state, opt_state),
            finite)


def log_nonfinite(step: int, loss=None) -> None:
    """Logs (WARNING, logger `jaxnerf_grid.train.optim`) that the step was skipped as non-finite."""
    suffix = "" if loss is None else f" (loss={float(jnp.asarray(loss).reshape(-1)[0])})"
    logger.warning("step %d: non-finite loss or gradient, update skipped%s", step, suffix)
