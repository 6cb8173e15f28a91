"""The procedural power-grid tower benchmark: a scene we render ourselves, with ground truth.

A lattice transmission tower (legs, bracing, cross-arms, insulator strings) with catenary
conductors leaving the scene, a textured ground, a tree line and buildings at 100-500 m, a sky
with clouds, and per-view distractors (people, vehicles, birds) in the training views.
Rendering is exact ray-primitive intersection in NumPy (intersect.py) with a BVH, Lambertian
sun + sky shading with cast shadows, and supersampled antialiasing (shading.py).

Entry points: `generate.generate_scene(preset, out_dir, ...)` and `jaxnerf-grid synth`.
"""

from __future__ import annotations

CLASSES = ("sky", "tower", "conductor", "ground", "vegetation", "building", "person", "vehicle", "bird")
DISTRACTOR_CLASSES = ("person", "vehicle", "bird")

# Per-view target coverage of the distractor mask (fraction of training pixels), teleport mode.
DISTRACTOR_LEVELS = {
    "none": (0.0, 0.0),
    "low": (0.01, 0.045),
    "medium": (0.07, 0.17),
    "high": (0.22, 0.32),
}

# Orbits: (radius m, height m, share of the views); the low pass is an arc at low height.
_ORBITS = ((60.0, 12.0, 0.3), (52.0, 26.0, 0.3), (66.0, 40.0, 0.24))
_LOW_PASS = (42.0, 4.5, 0.16)

PRESETS = {
    # The CPU demo: tens of views at 160x120, a minute or less on 2 cores.
    "tower-small": dict(width=160, height=120, fov_deg=60.0, num_train=40, num_test=8,
                        supersample=2, distractors="medium", mode="teleport", shadows=True,
                        orbits=_ORBITS, low_pass=_LOW_PASS, trees=1.0, buildings=26),
    # 16:9 like the TTPLA photographs, larger.
    "ttpla-like": dict(width=640, height=360, fov_deg=65.0, num_train=90, num_test=12,
                       supersample=2, distractors="medium", mode="teleport", shadows=True,
                       orbits=_ORBITS, low_pass=_LOW_PASS, trees=1.3, buildings=34),
    # 3:2 like STN PLAD, larger, more clutter.
    "plad-like": dict(width=600, height=400, fov_deg=60.0, num_train=90, num_test=12,
                      supersample=2, distractors="high", mode="teleport", shadows=True,
                      orbits=_ORBITS, low_pass=_LOW_PASS, trees=1.3, buildings=40),
}

# Metric world -> normalised scene: x_norm = SCALE * (x + TRANSLATION) (tower inside the unit sphere).
NORMALIZATION = {"scale": 0.05, "translation": [0.0, 0.0, -15.0]}


def generate_scene(*args, **kwargs):
    """See `jaxnerf_grid.data.synthetic.generate.generate_scene` (imported lazily)."""
    from jaxnerf_grid.data.synthetic.generate import generate_scene as _generate

    return _generate(*args, **kwargs)
