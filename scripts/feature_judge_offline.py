"""Can a per-pixel judge learned on image features find the transients the evidence misses?

On a trained `dpt+robust` run's training frames at a checkpoint (a synthetic scene with
distractor masks, e.g. Table 1's set B), the whole-frame rule (`refine.refined_weights`, strict
re-admission as the run resolved it) gives each pixel a label: ignored or used. A small MLP
(one hidden layer of 32, logistic loss, Adam, 1500 full-batch steps, in JAX) is fitted to
those labels, and again to the truth (the distractor masks: an oracle, the features' best
case), on per-pixel features:

    dpt      the built-in DPT's 9 class log-probabilities (`foreground.class_probabilities`)
    dpt+rgb  those, the colour, and its 5x5 mean and standard deviation
    rgb      the colour and its 5x5 mean and standard deviation

For each, at thresholds 0.5 / 0.7 / 0.9 on the judge's probability, the share of the distractor,
static and tower pixels it ignores alone and together with the rule (ignored by either), as
`scripts/refine_offline.py` prints them.

    python scripts/feature_judge_offline.py RUN STEP

docs/ROBUST.md ("A judge learned on features") quotes it. An experiment, not in the package.
"""

from __future__ import annotations

import sys

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from refine_offline import TOWER_CLASSES, rendered_run, shares  # scripts/ is sys.path[0] when run as a script

from jaxnerf_grid.masks import foreground as fg
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.train import refine


def local_stats(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[H, W, 3] -> (5x5 box mean, 5x5 standard deviation), each [H, W, 3]."""
    mean = cv2.blur(image, (5, 5))
    return mean, np.sqrt(np.maximum(cv2.blur(image * image, (5, 5)) - mean * mean, 0.0))


def fit_judge(features: np.ndarray, labels: np.ndarray, hidden: int = 32, steps: int = 1500,
              lr: float = 1e-2, seed: int = 0) -> np.ndarray:
    """features [T, H, W, D], labels [T, H, W] in {0, 1} -> the fitted MLP's probability [T, H, W]."""
    shape = labels.shape
    x = jnp.asarray(features.reshape(-1, features.shape[-1]))
    y = jnp.asarray(labels.reshape(-1), jnp.float32)
    x = (x - x.mean(0)) / (x.std(0) + 1e-6)
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    params = {"w1": jax.random.normal(k1, (x.shape[1], hidden)) / np.sqrt(x.shape[1]), "b1": jnp.zeros(hidden),
              "w2": jax.random.normal(k2, (hidden, 1)) / np.sqrt(hidden), "b2": jnp.zeros(1)}

    def logit(p):
        return (jax.nn.relu(x @ p["w1"] + p["b1"]) @ p["w2"] + p["b2"])[:, 0]

    def loss(p):
        z = logit(p)
        return jnp.mean(jax.nn.softplus(z) - y * z)

    grad = jax.jit(jax.grad(loss))
    m = jax.tree_util.tree_map(jnp.zeros_like, params)
    v = jax.tree_util.tree_map(jnp.zeros_like, params)
    for i in range(1, steps + 1):
        g = grad(params)
        m = jax.tree_util.tree_map(lambda a, b: 0.9 * a + 0.1 * b, m, g)
        v = jax.tree_util.tree_map(lambda a, b: 0.999 * a + 0.001 * b * b, v, g)
        first, second = 1 - 0.9 ** i, 1 - 0.999 ** i  # Adam's bias corrections
        params = jax.tree_util.tree_map(
            lambda a, b, c, f=first, s=second: a - lr * (b / f) / (jnp.sqrt(c / s) + 1e-8), params, m, v)
    return np.asarray(jax.nn.sigmoid(logit(params))).reshape(shape)


def main(argv: list[str]) -> int:
    cfg, ds, pool, ids, residual, confirmed = rendered_run(argv[0], int(argv[1]))
    rule = np.asarray(refine.refined_weights(residual, pool["weights"], cfg, confirmed))
    truth = np.asarray(ds.distractor_masks[ids], bool)
    tower = np.isin(np.asarray(ds.semantics[ids]), TOWER_CLASSES) & ~truth
    seg, _, wdir = masking.load_models(None, None)
    images = np.asarray(ds.images[ids], np.float32)
    log_probs = np.log(np.clip(np.stack([fg.class_probabilities(seg, im, masking.model_max_side(wdir))
                                         for im in images]), 1e-6, 1.0))
    stats = [local_stats(im) for im in images]
    colour = np.concatenate([images, np.stack([s[0] for s in stats]), np.stack([s[1] for s in stats])], -1)
    print(f"strict re-admission: {cfg.train.robust.strict_readmit}")
    print("DPT prior alone:", shares(pool["weights"], truth, tower))
    print("rule alone:", shares(rule, truth, tower))
    features = {"dpt": log_probs, "dpt+rgb": np.concatenate([log_probs, colour], -1), "rgb": colour}
    for name, x in features.items():
        for label_name, labels in (("rule's labels", rule < 0.5), ("truth (oracle)", truth)):
            judged = fit_judge(x, labels.astype(np.float32))
            for tau in (0.5, 0.7, 0.9):
                flagged = judged > tau
                print(f"{name} on the {label_name}, > {tau}: alone {shares(1.0 - flagged, truth, tower)} | "
                      f"with the rule {shares(np.where(flagged, 0.0, rule), truth, tower)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
