"""A triangle mesh from a sampled density: the grid, the threshold, marching cubes, floaters.

The grid (`grid_spec`): cubic voxels of side h = (longest side of the box) / resolution, the
nodes centred on the box, so the box's longest side has `resolution` voxels. The density is
sampled at the nodes.

The threshold (`density_threshold`): a ray crossing one voxel (length h) of constant density
sigma gets opacity 1 - exp(-sigma h) (`render.alpha_weights`). The surface is the level set
where that opacity is `opacity` (default 0.05):

    sigma_level = -ln(1 - opacity) / h        (= 0.0513 / h at the default; ln 2 / h at 0.5)

in the units of the density (per unit length of the normalised scene: the model's directions are
unit vectors there). A finer grid has a higher level. The default 5 % was chosen on the demo
run (docs/EXPORT.md, the sweep): the trained field is blurry across the lattice's thin members,
and the 50 % level keeps only their cores (a third of the tower within 0.4 m).

Marching cubes (`extract_mesh`): skimage's Lewiner variant on the node grid padded by one layer
of zero density, so every surface is closed where it meets the box; the normals point out of
the dense side (`gradient_direction="descent"`) and the faces are wound counter-clockwise seen
from outside (the orientation viewers derive face normals from; skimage's is the opposite).

Floaters (`remove_small_components`): the connected components of the mesh (faces sharing a
vertex) with fewer than `min_fraction` of all faces are dropped.
"""

from __future__ import annotations

import math

import numpy as np

DEFAULT_OPACITY = 0.05
DEFAULT_RESOLUTION = 256     # voxels along the box's longest side (`grid_spec`)
DEFAULT_MIN_COMPONENT_FRACTION = 0.002


def grid_spec(box_min, box_max, resolution: int) -> tuple[np.ndarray, float, tuple[int, int, int]]:
    """The sampling grid of a box. box_min, box_max: [3] with box_min < box_max.

    Returns (origin [3] = the first node, h = voxel side, shape (nx, ny, nz) = nodes per axis):
    node (i, j, k) is origin + h * (i, j, k); the nodes cover the box (centred on it) with
    ceil(extent / h) voxels per axis, `resolution` along the longest.
    """
    lo, hi = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    extent = hi - lo
    if resolution < 2 or not np.all(extent > 0):
        raise ValueError(f"grid_spec: need resolution >= 2 and a box of positive size, got {extent}, {resolution}")
    h = float(extent.max()) / int(resolution)
    voxels = np.maximum(np.ceil(extent / h - 1e-9).astype(int), 1)
    origin = 0.5 * (lo + hi) - 0.5 * h * voxels
    nx, ny, nz = (int(v) + 1 for v in voxels)
    return origin, h, (nx, ny, nz)


def grid_points(origin, h: float, shape) -> np.ndarray:
    """Node positions of a grid. Returns [nx, ny, nz, 3] float32 (ij indexing)."""
    axes = [np.asarray(origin, np.float64)[a] + h * np.arange(shape[a]) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).astype(np.float32)


def density_threshold(h: float, opacity: float = DEFAULT_OPACITY) -> float:
    """The density at which a ray crossing one voxel of side h gets `opacity` (0 < opacity < 1):
    -ln(1 - opacity) / h (module docstring)."""
    if not 0 < opacity < 1:
        raise ValueError(f"opacity must be in (0, 1), got {opacity}")
    return -math.log1p(-float(opacity)) / float(h)


def extract_mesh(density: np.ndarray, level: float, origin, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes of the level set density = level, closed at the grid's border.

    density: [nx, ny, nz] at the nodes origin + h * (i, j, k). Returns (vertices [V, 3] float64
    in the grid's coordinates, faces [F, 3] int64 counter-clockwise seen from outside, normals
    [V, 3] pointing out of the dense side); empty arrays when the density never exceeds `level`
    (a maximum exactly at `level` crosses nothing: skimage would raise).
    """
    from skimage import measure

    density = np.asarray(density, np.float32)
    if not np.isfinite(level) or not np.nanmax(density) > level:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    padded = np.pad(np.nan_to_num(density, nan=0.0, posinf=float(np.float32(3e38))), 1, constant_values=0.0)
    pad_level = min(float(level), float(np.finfo(np.float32).max))
    verts, faces, normals, _ = measure.marching_cubes(padded, level=pad_level, spacing=(h, h, h),
                                                      gradient_direction="descent", allow_degenerate=False)
    verts = verts.astype(np.float64) + (np.asarray(origin, np.float64) - h)
    return verts, faces[:, ::-1].astype(np.int64), normals.astype(np.float64)


def face_components(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Connected component of every face (faces sharing a vertex are connected).
    faces: [F, 3]. Returns labels [F] int (0 .. C - 1)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return np.zeros(0, np.int64)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(num_vertices, num_vertices))
    _, vertex_labels = connected_components(graph, directed=False)
    return vertex_labels[faces[:, 0]]


def remove_small_components(vertices: np.ndarray, faces: np.ndarray,
                            min_fraction: float = DEFAULT_MIN_COMPONENT_FRACTION,
                            extra: tuple = ()) -> tuple[np.ndarray, np.ndarray, tuple, dict]:
    """Drops the components with fewer than min_fraction * F faces (floaters).

    vertices [V, 3], faces [F, 3]; extra: per-vertex arrays ([V, ...]) filtered alike.
    Returns (vertices [V', 3], faces [F', 3] re-indexed, extra filtered, stats) with stats =
    {"components", "kept_components", "kept_face_fraction", "kept_vertex_fraction"}.
    """
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return vertices, faces, extra, {"components": 0, "kept_components": 0, "kept_face_fraction": 1.0,
                                        "kept_vertex_fraction": 1.0}
    labels = face_components(faces, len(vertices))
    counts = np.bincount(labels)
    keep_label = counts >= min_fraction * len(faces)
    keep_face = keep_label[labels]
    used = np.zeros(len(vertices), bool)
    used[faces[keep_face].ravel()] = True
    new_index = np.cumsum(used) - 1
    stats = {"components": int(len(counts)), "kept_components": int(keep_label.sum()),
             "kept_face_fraction": float(keep_face.mean()), "kept_vertex_fraction": float(used.mean())}
    return (vertices[used], new_index[faces[keep_face]], tuple(np.asarray(e)[used] for e in extra), stats)


def is_closed(faces: np.ndarray) -> bool:
    """True when every edge of the triangle mesh faces [F, 3] is shared by exactly two faces
    (a closed, edge-manifold surface); False for an empty mesh."""
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return False
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges.sort(axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))
