"""Camera poses for hand-made rigs."""

import numpy as np


def look_at(eye, target) -> np.ndarray:
    """OpenGL camera-to-world [4, 4] looking from `eye` at `target`, z up: -z towards the target,
    +x horizontal."""
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, np.cross(r, f), -f, eye
    return m
