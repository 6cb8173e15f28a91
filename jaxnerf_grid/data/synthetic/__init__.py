"""The procedural power-grid tower benchmark: a scene we render ourselves, with ground truth.

A lattice transmission tower (legs, bracing, cross-arms, insulator strings) with catenary
conductors leaving the scene, a textured ground, a tree line and buildings at 100-500 m, a sky
with clouds, and per-view distractors (people, vehicles, birds) in the training views.
Rendering is exact ray-primitive intersection in NumPy (intersect.py) with a BVH, Lambertian
sun + sky shading with cast shadows, and supersampled antialiasing (shading.py).

Entry points: `generate.generate_scene(preset, out_dir, ...)` and `jaxnerf-grid synth`.

World: metres, +z up, main tower base at the origin (about 30 m tall, 8 m base, cross-arms at
17.5 / 21.5 / 25.5 m), the line along +-y with neighbouring towers at +-320 m. The dataset is
normalised with x_norm = 0.05 * (x + (0, 0, -15)) (`NORMALIZATION`; the translation is metric),
so the tower sits inside the unit sphere; near = 0.5 and far = 40 (normalised, along unit rays).

What a dataset folder holds (docs/DATASET.md keys, plus the extras marked *):
  images/NAME.png        cluttered image (train), = clean image (test)
  clean/NAME.png         image without distractors
  depth/NAME.exr         z-depth along the camera's -z, normalised units, +inf on sky, of what
                         images/ shows (distractors included on train views)
  clean_depth/NAME.exr * (train) z-depth of the clean scene   -> "clean_depth_file_path"
  semantic/NAME.png      class ids (CLASSES order) of what images/ shows
  distractor/NAME.png    255 where any colour subsample of the pixel sees a distractor
  shadow/NAME.png      * 255 where (outside distractor/) a distractor's cast shadow darkens
                         the pixel                               -> "shadow_mask_path"
  tower.ply              60k points on the main tower's members (normalised units)
Semantic class and depth come from the ray through the pixel centre; colours average
`supersample`^2 subpixel rays in linear radiance. Outside distractor/ and shadow/ the cluttered
and clean images are bit-identical. Per frame "distractor_coverage" and "num_distractors"*;
top-level "generator" (preset, seed, level, mode, coverage mean/min/max, sun direction) and
"semantic_classes"*.
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
