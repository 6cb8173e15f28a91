"""The conductors from the photos: wires detected in each photo, each span fitted as a 3-D catenary.

A conductor a few pixels wide or less is where volume rendering is weakest (the fused cloud has
no wire points), and where the photos themselves are strongest: in every photo it is a long,
thin, nearly straight ridge, and a catenary in 3-D has five parameters. All in the export's
frame and units (metres where the dataset has a scale), +z up (the frame's z; `up` otherwise).

* Detection (`ridge_map`, `detections`): scikit-image's Sato tubeness filter
  (`skimage.filters.sato`) for dark ridges (a wire is darker than the sky; over the ground it is
  often lost, the fit takes what the sky shows) at a scale of one pixel: a sub-pixel wire blurred
  by the lens and the pixel is a ridge of that width. Sato rather than Frangi (which divides by
  the blob measure and goes quiet on the faint, far part of a wire) or Meijering (normalised per
  image, so a photo without wires still fills with "ridges"); OpenCV's ximgproc line detectors
  give straight segments, and a span seen at low altitude is visibly curved. The detections are
  the ridge lines (non-maximum suppression across the ridge, hysteresis), in long straight pieces.
* Model (`curve_points`): a span leaves its attachment A = C + c e_across + z_A up (C: the
  tower's axis, c: the offset across the line, z_A: the height) along the horizontal direction
  e_line(psi), and hangs as the catenary
      z(s) = z_A + s sinhc(kappa s / 2) sinh(kappa s / 2 - beta),   beta = asinh(-m0)
  of the horizontal distance s (kappa = 1 / a the curvature, m0 the slope at A; the closed form
  a (cosh((s - x_v) / a) - cosh(x_v / a)) written so that kappa -> 0 is a straight line). The
  far tower lies outside the export: its attachment is taken at A's height (a level span), so
  the lowest point is at x_v = beta / kappa, the span 2 x_v and the sag (cosh(beta) - 1) / kappa.
* Finding the spans (`cross_section_peaks`): a vertical plane across the line at a station
  beyond the tower's box is gridded; each cell's support is the share of the photos that see it
  whose detections pass within `tol_px` of its projection. A wire crossing the plane is
  supported by nearly every photo; a point on one photo's wire lies off it in the others.
  Peaks above `min_support` seed one span each (the cross-arms' direction gives the line's).
* Fit (`fit_span`): robust least squares (`scipy.optimize.least_squares`, Cauchy loss) on the
  image distance from each projected sample of the curve to the nearest detection (a distance
  transform's nearest-pixel map: iterated closest points), the samples' range grown in steps
  from the station outwards so the sag is found before the far part is asked to match. The
  1-sigma uncertainties are sigma^2 (J^T J)^-1 over the inlier residuals (sigma^2 their mean
  square), propagated to every derived figure through its numerical Jacobian. A span is kept
  when at least `min_inlier_share` of its projected samples lie within 2 `tol_px` of a
  detection.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxnerf_grid.data.normalize import normalization_rotation
from jaxnerf_grid.export import to_metric64
from jaxnerf_grid.export.catenary import curve_points, derived, line_axes, sample_span

DEFAULT_SIGMAS = (1.0,)           # px: the ridge filter's scale (a sub-pixel wire, blurred by lens and pixel)
DEFAULT_THRESHOLD = 4.0           # detections: response above this many robust scales
DEFAULT_MIN_LENGTH = 12           # px: shorter thinned pieces are texture, not wires
PIECE = 32                        # px: the grid the detections are cut on before the straightness test
DEFAULT_TOL_PX = 1.5              # px: a projection this close to a detection lies on it
DEFAULT_MIN_SUPPORT = 0.5         # share of the photos seeing a cross-section cell that support it
DEFAULT_MIN_VIEWS = 6             # photos that must see a cell for it to count
DEFAULT_MIN_INLIER_SHARE = 0.5    # share of a fitted span's projections on a detection
SAMPLES = 100                     # samples along a span in the fit
BEHIND_PX = 50.0                  # px: the residual of a fixed observation whose point went behind the camera


# --- detection --------------------------------------------------------------------------------

def ridge_map(image: np.ndarray, sigmas=DEFAULT_SIGMAS) -> np.ndarray:
    """Ridge strength [H, W] of a photo [H, W, 3] (or [H, W]) in [0, 1]: Sato's tubeness of dark
    ridges (`skimage.filters.sato`, black_ridges) on the grey image. Dark only: a wire is darker
    than the sky behind it, and the bright-ridge map of a dark line has a side lobe either side
    of it (two false wires a pixel and a half away)."""
    from skimage.filters import sato

    grey = np.asarray(image, np.float64)
    if grey.ndim == 3:
        grey = grey[..., :3] @ np.array([0.299, 0.587, 0.114])
    return sato(grey, sigmas=sigmas, black_ridges=True, mode="reflect")


def ridge_normals(response: np.ndarray) -> tuple:
    """Per pixel of a ridge map [H, W]: (n_x, n_y) the unit normal across the ridge (the response's
    Hessian eigenvector of the largest |eigenvalue|, finite differences), the gradient (g_x, g_y)
    and the curvature n^T H n. Returns six [H, W] arrays (n_x, n_y, g_x, g_y, curvature)."""
    r = np.asarray(response, np.float64)
    gy, gx = np.gradient(r)
    hyy, hyx = np.gradient(gy)
    _, hxx = np.gradient(gx)
    mean, half = 0.5 * (hxx + hyy), np.sqrt(0.25 * (hxx - hyy) ** 2 + hyx ** 2)
    lam = np.where(np.abs(mean + half) >= np.abs(mean - half), mean + half, mean - half)
    nx, ny = hyx, lam - hxx
    flat = np.hypot(nx, ny) < 1e-12
    nx, ny = np.where(flat, lam - hyy, nx), np.where(flat, hyx, ny)
    flat = np.hypot(nx, ny) < 1e-12
    nx, ny = np.where(flat, 0.0, nx), np.where(flat, 1.0, ny)
    norm = np.hypot(nx, ny)
    nx, ny = nx / norm, ny / norm
    return nx, ny, gx, gy, hxx * nx * nx + 2 * hyx * nx * ny + hyy * ny * ny


def detections(response: np.ndarray, threshold: float = DEFAULT_THRESHOLD, floor: float = 0.01,
               min_length: int = DEFAULT_MIN_LENGTH, max_width_ratio: float = 0.2) -> np.ndarray:
    """The wire pixels [H, W] bool of a ridge map: its ridge lines (pixels at least as strong as
    their two neighbours across the ridge, `ridge_normals`: non-maximum suppression), linked by
    hysteresis (`skimage.filters.apply_hysteresis_threshold`: above median + threshold x the
    map's robust scale, 1.4826 MAD and at least `floor`, or above half of that and joined to
    such), cut on a grid of PIECE pixels and kept in 8-connected pieces that are long and
    straight (`skimage.measure.regionprops`: major axis >= min_length pixels, minor axis <=
    max_width_ratio of it): the ground's texture leaves dots and rings, a wire a line (a curved
    one straight over a piece)."""
    from scipy import ndimage
    from skimage.filters import apply_hysteresis_threshold
    from skimage.measure import label, regionprops

    r = np.asarray(response, np.float64)
    median = float(np.median(r))
    scale = max(1.4826 * float(np.median(np.abs(r - median))), floor)
    nx, ny, _, _, _ = ridge_normals(r)
    rows, cols = np.mgrid[0:r.shape[0], 0:r.shape[1]].astype(np.float64)
    ahead = ndimage.map_coordinates(r, [rows + ny, cols + nx], order=1, mode="nearest")
    behind = ndimage.map_coordinates(r, [rows - ny, cols - nx], order=1, mode="nearest")
    crest = np.where((r >= ahead) & (r >= behind), r, 0.0)
    lines = apply_hysteresis_threshold(crest, median + 0.5 * threshold * scale, median + threshold * scale)
    lines[::PIECE, :] = False          # pieces of at most PIECE pixels a side: a curve is straight over that
    lines[:, ::PIECE] = False
    labels = label(lines, connectivity=2)
    keep = np.zeros(labels.max() + 1, bool)
    for region in regionprops(labels):
        major = region.axis_major_length
        keep[region.label] = major >= min_length and region.axis_minor_length <= max_width_ratio * major
    return keep[labels]


def subpixel(response: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The wire's centre line at each detection, to a fraction of a pixel (Steger's ridge point):
    along the ridge's normal n (`ridge_normals`), the response's second-order maximum
    t = -(g . n) / (n^T H n), |t| <= 1 (else 0).
    response [H, W], mask [H, W] bool. Returns [D, 4] (u, v, n_u, n_v) in pixels (pixel centres at
    +0.5), D = mask.sum(), in the order of np.nonzero(mask)."""
    nx, ny, gx, gy, curv = (a[mask] for a in ridge_normals(response))
    rows, cols = np.nonzero(mask)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(gx * nx + gy * ny) / curv
    t = np.where(np.isfinite(t) & (np.abs(t) <= 1.0), t, 0.0)
    return np.stack([cols + 0.5 + t * nx, rows + 0.5 + t * ny, nx, ny], axis=1)


def nearest_index(mask: np.ndarray) -> np.ndarray:
    """For every pixel, the index (in np.nonzero(mask) order) of its nearest detection
    (`scipy.ndimage.distance_transform_edt`'s nearest-pixel map). [H, W] int32; -1 without any."""
    from scipy import ndimage

    if not mask.any():
        return np.full(mask.shape, -1, np.int32)
    _, (rows, cols) = ndimage.distance_transform_edt(~mask, return_indices=True)
    ids = np.full(mask.shape, -1, np.int64)
    ids[mask] = np.arange(int(mask.sum()))
    return ids[rows, cols].astype(np.int32)


# --- cameras ----------------------------------------------------------------------------------

def metric_cameras(c2w: np.ndarray, normalization: dict | None) -> np.ndarray:
    """Camera-to-world [N, 4, 4] of the normalised scene -> the export's frame (x = R^T x_n / s - t:
    the centre mapped, the axes turned by R^T). Returns [N, 4, 4] float64."""
    c2w = np.asarray(c2w, np.float64).copy()
    rot = normalization_rotation(normalization or {})
    out = np.tile(np.eye(4), (len(c2w), 1, 1))
    out[:, :3, :3] = c2w[:, :3, :3] if rot is None else np.einsum("ij,njk->nik", rot.T, c2w[:, :3, :3])
    out[:, :3, 3] = to_metric64(c2w[:, :3, 3], normalization)
    return out


def project_all(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray):
    """Pinhole projection of points [M, 3] into N cameras (OpenGL axes, `export.fuse.project`):
    c2w [N, 4, 4], intrinsics [N, 4] (fx, fy, cx, cy). Returns (u [N, M], v [N, M], depth [N, M])."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    rot, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    cam = np.einsum("nmi,nij->nmj", p[None] - centre[:, None], rot)   # R^T (x - c)
    z = -cam[..., 2]
    safe = np.where(z > 1e-9, z, 1e-9)
    fx, fy, cx, cy = (intrinsics[:, k:k + 1].astype(np.float64) for k in range(4))
    with np.errstate(over="ignore", invalid="ignore"):
        u, v = cx + fx * cam[..., 0] / safe, cy - fy * cam[..., 1] / safe
    far = ~(np.isfinite(u) & np.isfinite(v))        # behind or on the camera's plane, flagged by z anyway
    return np.where(far, -1e9, u), np.where(far, -1e9, v), np.where(far, -1.0, z)


# --- the catenary -------------------------------------------------------------------------------

def _flat(fig: dict) -> np.ndarray:
    return np.concatenate([np.atleast_1d(np.asarray(fig[k], np.float64)) for k in FIGURES])


FIGURES = ("attachment", "far_attachment", "lowest_point", "catenary_parameter", "sag", "span", "lowest_station")


def derived_sigmas(theta, cov: np.ndarray, centre, up=(0.0, 0.0, 1.0)) -> dict:
    """1-sigma of each `derived` figure from theta's covariance [5, 5] (first-order propagation
    through a central-difference Jacobian). Returns the same keys ([3] for points)."""
    theta = np.asarray(theta, np.float64)
    base = _flat(derived(theta, centre, up))
    jac = np.zeros((len(base), len(theta)))
    for k in range(len(theta)):
        step = 1e-6 * max(abs(theta[k]), 1e-6) if k != 4 else 1e-4 * max(abs(theta[k]), 1e-9)
        hi, lo = theta.copy(), theta.copy()
        hi[k] += step
        lo[k] -= step
        jac[:, k] = (_flat(derived(hi, centre, up)) - _flat(derived(lo, centre, up))) / (2 * step)
    var = np.einsum("ik,kl,il->i", jac, cov, jac)
    sig = np.sqrt(np.maximum(var, 0.0))
    out: dict[str, Any] = {}
    i = 0
    for name in FIGURES:
        n = 3 if name in ("attachment", "far_attachment", "lowest_point") else 1
        out[name] = sig[i:i + n] if n == 3 else float(sig[i])
        i += n
    return out


# --- image residuals ------------------------------------------------------------------------------

class Views:
    """The photos as the fit sees them: c2w [N, 4, 4] and intrinsics [N, 4] in the export's frame,
    the detections masks [N, H, W] bool, each detection's sub-pixel centre and normal (`subpixel`
    of the photo's ridge response; without responses, the pixel's centre and a normal along the
    offset) and every pixel's nearest detection (`nearest_index`)."""

    def __init__(self, c2w: np.ndarray, intrinsics: np.ndarray, masks: np.ndarray, responses=None):
        self.c2w = np.asarray(c2w, np.float64)
        self.intrinsics = np.asarray(intrinsics, np.float64)
        self.masks = np.asarray(masks, bool)
        self.height, self.width = self.masks.shape[1:]
        tables, index, start = [], [], 0
        for i, m in enumerate(self.masks):
            if responses is None:
                rows, cols = np.nonzero(m)
                t = np.stack([cols + 0.5, rows + 0.5, np.full(len(rows), np.nan), np.full(len(rows), np.nan)], 1)
            else:
                t = subpixel(responses[i], m)
            near = nearest_index(m)
            index.append(np.where(near >= 0, near + start, -1).astype(np.int32))
            tables.append(t)
            start += len(t)
        self.table = np.concatenate(tables) if tables else np.zeros((0, 4))
        self.index = np.stack(index)
        self.has = self.masks.reshape(len(self.masks), -1).any(axis=1)

    def offsets(self, points: np.ndarray, switch_px: float = 3 * DEFAULT_TOL_PX, observed=None):
        """For points [M, 3]: (residual [N, M]: the signed distance from each projection to its nearest
        detection's line (along its normal) where that detection is within switch_px, the distance
        to it beyond; distance [N, M] to the nearest detection's centre; seen [N, M] bool (in
        front, inside the photo, the photo has detections)). Zero where not seen. With `observed`
        [N, M] bool (the pairs a fit holds fixed), those pairs keep their residual when the
        projection leaves the photo (measured from the nearest detection inside it), BEHIND_PX
        behind the camera: a curve cannot lower its cost by leaving the photos."""
        u, v, z = project_all(points, self.c2w, self.intrinsics)
        seen = np.asarray((z > 0) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
                          & np.asarray(self.has, bool)[:, None], bool)
        if observed is not None:
            seen = np.asarray(observed, bool)
        col = np.clip(np.floor(u), 0, self.width - 1).astype(np.int64)
        row = np.clip(np.floor(v), 0, self.height - 1).astype(np.int64)
        n = np.arange(len(self.c2w))[:, None]
        table = self.table if len(self.table) else np.full((1, 4), np.nan)  # no detection in any photo
        det = table[np.maximum(self.index[n, row, col], 0)]                      # [N, M, 4]
        du, dv = det[..., 0] - u, det[..., 1] - v
        dist = np.hypot(du, dv)
        along = du * det[..., 2] + dv * det[..., 3]
        residual = np.where(np.isfinite(along) & (dist <= switch_px), along, dist)
        residual = np.where(z > 0, residual, BEHIND_PX)
        dist = np.where(z > 0, dist, BEHIND_PX)
        return np.where(seen, residual, 0.0), np.where(seen, dist, 0.0), seen


def support(views: Views, points: np.ndarray, tol_px: float = DEFAULT_TOL_PX):
    """Per point [M, 3]: (the share of the photos seeing it whose nearest detection lies within
    tol_px of its projection [M], how many photos see it [M])."""
    _, dist, seen = views.offsets(points)
    near = seen & (dist <= tol_px)
    count = seen.sum(axis=0)
    return near.sum(axis=0) / np.maximum(count, 1), count


def cross_section_peaks(views: Views, centre, psi: float, station: float, across: tuple, heights: tuple,
                        step: float, up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX,
                        min_support: float = DEFAULT_MIN_SUPPORT, min_views: int = DEFAULT_MIN_VIEWS,
                        separation: float | None = None) -> np.ndarray:
    """Wires crossing the vertical plane at horizontal distance `station` along e_line(psi) from
    centre: the local maxima of `support` over the grid across [lo, hi] x heights [lo, hi] (step
    apart) holding >= min_support with >= min_views photos, at least `separation` (default
    4 steps) apart, strongest first. Returns [P, 3] (across offset, height, support)."""
    line, ax, u = line_axes(psi, up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u + station * line
    cs = np.arange(across[0], across[1] + 0.5 * step, step)
    zs = np.arange(heights[0], heights[1] + 0.5 * step, step)
    cc, zz = np.meshgrid(cs, zs, indexing="ij")
    pts = base[None] + cc.reshape(-1, 1) * ax[None] + zz.reshape(-1, 1) * u[None]
    share, count = support(views, pts, tol_px)
    share = np.where(count >= min_views, share, 0.0).reshape(cc.shape)
    from scipy import ndimage

    peak = (share >= min_support) & (share == ndimage.maximum_filter(share, size=3, mode="constant"))
    idx = np.argwhere(peak)
    order = np.argsort(-share[peak], kind="stable")
    sep = 4 * step if separation is None else separation
    kept: list = []
    for i, j in idx[order]:
        if all(math.hypot(cs[i] - c, zs[j] - z) >= sep for c, z, _ in kept):
            kept.append((float(cs[i]), float(zs[j]), float(share[i, j])))
    return np.asarray(kept, np.float64).reshape(-1, 3)


def _residuals(theta, views: Views, centre, s: np.ndarray, up, observed: np.ndarray) -> np.ndarray:
    """The image residuals [N K] of the span's samples at s [K] in the observed pairs [N, K]
    (`Views.offsets`)."""
    return views.offsets(curve_points(theta, centre, s, up), observed=observed)[0].ravel()


def _stations(theta, s_min: float, reach: float, count: int) -> np.ndarray:
    """count horizontal distances from s_min to s_min + reach, capped at the level span's far end."""
    _, _, _, m0, kappa = theta
    beta = math.asinh(-float(m0))
    end = s_min + reach
    if kappa > 0 and beta > 0:
        end = min(end, max(2 * beta / kappa, s_min + 1e-3 * reach + 1e-9))
    return np.linspace(s_min, end, count)


def fit_span(views: Views, theta0, centre, s_min: float, reaches, up=(0.0, 0.0, 1.0),
             tol_px: float = DEFAULT_TOL_PX, samples: int = SAMPLES, reject_below: float = 0.0,
             length_scale: float = 30.0) -> dict:
    """Robust fit of one span (module docstring) from theta0 = (c, z_a, psi, m0, kappa): least
    squares on the image offsets with a Cauchy loss of scale tol_px, the samples' reach from
    s_min grown through `reaches` (export units, increasing; the last one the whole span); with
    reject_below, the growing stops after the first reach when fewer than that share of the
    projections lie on a detection (the caller drops the fit); length_scale: the tower's height
    (the curvature is bounded by 0.3 / length_scale). The photos that see each sample at the
    start of a stage are held for that stage (`Views.offsets`' observed).
    Returns {"theta" [5], "cov" [5, 5], "sigma_px", "inlier_share", "residuals": inliers used,
    "seen": projections, "stations" [K] (the last stage's samples)}."""
    from scipy.optimize import least_squares

    theta = np.asarray(theta0, np.float64)
    # a >= 3 tower heights (kappa <= 0.3 / length_scale), slopes within 45 degrees: no overflow in cosh
    kmax = 0.3 / length_scale
    lower = np.array([-np.inf, -np.inf, -np.inf, -1.0, -kmax])
    upper = np.array([np.inf, np.inf, np.inf, 1.0, kmax])
    scale = np.array([1.0, 1.0, 0.01, 0.01, 1e-4])
    for k, reach in enumerate(reaches):
        s = _stations(theta, s_min, reach, samples)
        observed = views.offsets(curve_points(theta, centre, s, up))[2]     # held fixed through the stage
        if not observed.any():
            break
        res = least_squares(_residuals, theta, args=(views, centre, s, up, observed), loss="cauchy", f_scale=tol_px,
                            x_scale=scale, bounds=(lower, upper), method="trf", max_nfev=30 if k < len(reaches) - 1
                            else 60)
        theta = res.x
        if k == 0 and reject_below:   # a seed on no wire: not worth growing
            _, dist, seen = views.offsets(curve_points(theta, centre, s, up))
            if (seen & (dist <= 2 * tol_px)).sum() < reject_below * max(seen.sum(), 1):
                break
    s = _stations(theta, s_min, reaches[-1], samples)
    _, dist, seen = views.offsets(curve_points(theta, centre, s, up))
    inlier = seen & (dist <= 2 * tol_px)
    share = float(inlier.sum() / max(seen.sum(), 1))
    cov, sigma = _covariance(theta, views, centre, s, up, inlier)
    return {"theta": theta, "cov": cov, "sigma_px": sigma, "inlier_share": share,
            "residuals": int(inlier.sum()), "seen": int(seen.sum()), "stations": s}


def _covariance(theta, views: Views, centre, s, up, inlier: np.ndarray) -> tuple[np.ndarray, float]:
    """sigma^2 (J^T J)^-1 over the inlier residuals [N, K] (their nearest detections held fixed:
    a central-difference Jacobian of the residuals); sigma^2 their mean square over
    (inliers - 5) degrees of freedom."""
    theta = np.asarray(theta, np.float64)
    points = curve_points(theta, centre, s, up)
    u0, v0, _ = project_all(points, views.c2w, views.intrinsics)
    col = np.clip(np.floor(u0), 0, views.width - 1).astype(np.int64)
    row = np.clip(np.floor(v0), 0, views.height - 1).astype(np.int64)
    n = np.arange(len(views.c2w))[:, None]
    det = views.table[np.maximum(views.index[n, row, col], 0)][inlier]          # the fixed detections
    normal = np.where(np.isfinite(det[:, 2:]), det[:, 2:], 0.0)

    def along(t):
        u, v, _ = project_all(curve_points(t, centre, s, up), views.c2w, views.intrinsics)
        du, dv = det[:, 0] - u[inlier], det[:, 1] - v[inlier]
        has = np.any(normal != 0, axis=1)
        return np.where(has, du * normal[:, 0] + dv * normal[:, 1], np.hypot(du, dv))

    r = along(theta)
    jac = np.zeros((len(r), len(theta)))
    for k in range(len(theta)):
        step = 1e-6 * max(abs(theta[k]), 1.0) if k < 3 else 1e-7
        hi, lo = theta.copy(), theta.copy()
        hi[k] += step
        lo[k] -= step
        jac[:, k] = (along(hi) - along(lo)) / (2 * step)
    dof = len(r) - len(theta)
    if dof <= 0:
        return np.full((5, 5), np.inf), float("nan")
    sigma2 = float(r @ r) / dof
    try:
        cov = sigma2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        cov = np.full((5, 5), np.inf)
    return cov, math.sqrt(sigma2)


# --- the spans of a tower -------------------------------------------------------------------------

def reaches_from(first: float, last: float) -> list[float]:
    """The fit's growing sample ranges: first, 2 first, 4 first, ... up to and ending at last."""
    out = [float(first)]
    while out[-1] * 2 < last:
        out.append(out[-1] * 2)
    return out + [float(last)]


def find_spans(views: Views, centre, psi: float, half_length: float, heights: tuple, across: float,
               step: float, tower_height: float, up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX,
               min_support: float = DEFAULT_MIN_SUPPORT, min_views: int = DEFAULT_MIN_VIEWS,
               min_inlier_share: float = DEFAULT_MIN_INLIER_SHARE) -> list[dict]:
    """The spans leaving a tower on both sides of the line (module docstring).

    centre [3]: the tower's axis; psi: the line's azimuth (`line_axes`); half_length: the tower's
    box reaches this far along the line from the axis (the lattice is left out of the fit);
    heights (lo, hi): the cross-section's heights (along up, the frame's zero); across: its half
    width; step: its cell (about a pixel's footprint there; peaks 3 tol_px cells apart at
    least); tower_height: the scale of the
    station's margin and of the reach (30 tower heights).
    Returns [{"side": +1 | -1, "psi", "seed" (across, height, support), fit_span's keys}],
    the kept fits only (inlier share >= min_inlier_share, the attachment within the cross-section's
    window widened by the station's margin; one per wire)."""
    spans = []
    margin = 0.3 * tower_height
    for side in (1, -1):
        psi_side = psi if side == 1 else psi + math.pi
        station = half_length + margin
        peaks = cross_section_peaks(views, centre, psi_side, station, (-across, across), heights, step, up,
                                    tol_px, min_support, min_views, separation=3 * tol_px * step)
        fits: list[dict] = []
        for c, z, share in peaks:
            seed = curve_points((c, z, psi_side, 0.0, 0.0), centre, np.array([station]), up)[0]
            if any(np.linalg.norm(curve_points(f["theta"], centre, np.array([station]), up)[0] - seed) < 0.033 *
                   tower_height for f in fits):
                continue   # on a wire already fitted: the support is a ridge across the plane, not a point
            fit = fit_span(views, (c, z, psi_side, 0.0, 0.0), centre, half_length,
                           reaches_from(4 * margin, 30 * tower_height), up, tol_px, reject_below=min_inlier_share,
                           length_scale=tower_height)
            c_fit, z_fit = fit["theta"][0], fit["theta"][1]
            inside = abs(c_fit) <= across + margin and heights[0] - margin <= z_fit <= heights[1] + margin
            if fit["inlier_share"] >= min_inlier_share and inside:   # run off the searched window: not here
                fits.append({"side": side, "psi": psi_side, "seed": [float(c), float(z), float(share)], **fit})
        spans += _distinct(fits, centre, step * 4, up)
    return spans


def _distinct(fits: list[dict], centre, radius: float, up) -> list[dict]:
    """One fit per wire: of fits whose curves pass within `radius` of each other at the seed's
    station and 4 times as far, the one with the most inlier offsets."""
    kept: list[dict] = []
    for f in sorted(fits, key=lambda f: -f["residuals"]):
        s = np.array([f["stations"][0], f["stations"][0] * 4])
        p = curve_points(f["theta"], centre, s, up)
        if all(np.max(np.linalg.norm(p - curve_points(k["theta"], centre, s, up), axis=1)) > radius for k in kept):
            kept.append(f)
    return kept


def span_record(fit: dict, centre, up=(0.0, 0.0, 1.0)) -> dict:
    """measurements.json's record of a fitted span: every `derived` figure {"value", "sigma"}
    (points as [3] lists), the parameters, the fit's terms."""
    theta, cov = fit["theta"], fit["cov"]
    fig = derived(theta, centre, up)
    sig = derived_sigmas(theta, cov, centre, up) if np.all(np.isfinite(cov)) else None
    rec: dict[str, Any] = {}
    for k in FIGURES:
        v = fig[k]
        s = None if sig is None else sig[k]
        if np.ndim(v):
            finite = bool(np.all(np.isfinite(v)))
            rec[k] = {"value": [float(x) for x in v] if finite else None,
                      "sigma": [_num(x) for x in s] if finite and s is not None else None}
        else:
            rec[k] = {"value": _num(v), "sigma": None if s is None else _num(s)}
    rec.update({"side": int(fit["side"]), "theta": [float(v) for v in theta],
                "theta_names": ["across", "attachment_height", "azimuth", "slope_at_attachment", "curvature"],
                "sigma_px": _num(fit["sigma_px"]), "inlier_share": float(fit["inlier_share"]),
                "inliers": int(fit["residuals"]), "projections": int(fit["seen"]),
                "observed_stations": [float(fit["stations"][0]), float(fit["stations"][-1])],
                "centre": [float(v) for v in np.asarray(centre, np.float64)],
                "up": [float(v) for v in np.asarray(up, np.float64)], "level_span_assumed": True})
    return rec


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


# --- the picture ----------------------------------------------------------------------------------

COLOURS = ((1.0, 0.1, 0.1), (1.0, 0.8, 0.0), (0.1, 0.9, 0.2), (0.1, 0.6, 1.0), (1.0, 0.2, 1.0),
           (0.0, 0.9, 0.9), (1.0, 0.5, 0.0), (0.6, 0.3, 1.0))


def views_picture(images: np.ndarray, views: Views, spans: list[dict], centre, up=(0.0, 0.0, 1.0),
                  count: int = 4, min_width: int = 480) -> np.ndarray:
    """The fitted spans drawn on the `count` photos that see most of them (upscaled by an integer
    to at least min_width pixels wide), detections in dark red under them, photos in a 2-column
    grid. images [N, H, W, 3] in [0, 1] (the photos of `views`). Returns [H', W', 3] float32."""
    import cv2

    n, h, w = images.shape[:3]
    k = max(1, int(math.ceil(min_width / w)))
    curves = [sample_span(f["theta"], centre, 0.5, up) if math.isfinite(derived(f["theta"], centre, up)["span"])
              else curve_points(f["theta"], centre, f["stations"], up) for f in spans]
    seen = np.zeros(n)
    for pts in curves:
        u, v, z = project_all(pts, views.c2w, views.intrinsics)
        seen += ((z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)).sum(axis=1)
    order = np.argsort(-seen, kind="stable")[:count] if curves else np.arange(min(count, n))
    tiles = []
    for i in order:
        img = np.repeat(np.repeat(np.asarray(images[i], np.float32), k, 0), k, 1).copy()
        img[np.repeat(np.repeat(views.masks[i], k, 0), k, 1)] = (0.55, 0.0, 0.0)
        canvas = np.ascontiguousarray((img * 255).astype(np.uint8))
        for j, pts in enumerate(curves):
            u, v, z = project_all(pts, views.c2w[i:i + 1], views.intrinsics[i:i + 1])
            ok = z[0] > 0
            line = np.stack([u[0][ok], v[0][ok]], 1) * k
            colour = tuple(int(255 * c) for c in COLOURS[j % len(COLOURS)])
            cv2.polylines(canvas, [np.round(line * 16).astype(np.int32)], False, colour, 1, cv2.LINE_AA, shift=4)
        cv2.putText(canvas, f"photo {int(i)}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(canvas.astype(np.float32) / 255.0)
    while len(tiles) % 2:
        tiles.append(np.ones_like(tiles[0]))
    rows = [np.concatenate([a, np.ones((a.shape[0], 4, 3), np.float32), b], 1) for a, b in zip(tiles[::2], tiles[1::2])]
    gap = np.ones((4, rows[0].shape[1], 3), np.float32)
    return np.concatenate(sum(([r, gap] for r in rows), [])[:-1], 0)
