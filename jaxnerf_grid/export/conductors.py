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
* Seeds (`cross_section_peaks`): a vertical plane across the line at a station
  beyond the tower's box is gridded; each cell's support is the share of the photos that see it
  whose detections pass within `tol_px` of its projection. A wire crossing the plane is
  supported by nearly every photo; a point on one photo's wire lies off it in the others.
  Peaks above `min_support` seed one span each (the cross-arms' direction gives the line's);
  with the cross-arms' tips given, each tip's window below it (`seed_peaks`) and the earth
  wires' window above the arms (`earth_window`) at `min_support`, the rest of the plane at
  `DEFAULT_PEAK_SUPPORT`.
* Track (`track_span`, what `find_spans` uses): each seed followed outwards station by station,
  at each the best cell of a small grid across the predicted curve by `gated_support` (detections
  near the projection AND running along it), the curve refitted every few stations
  (`fit_profile`: the catenary parameter bounded to plausible values, or fixed by the slope and a
  given span length); wires that only borrow another wire's detections dropped
  (`shared_evidence`, `borrowers_dropped`); a track is judged on the stations tried up to its
  last one found (`_enough`: the misses that end every track left out). An unrefined span's 1-sigma figures
  (`combined_covariance`): the height, slope and curvature from the profile fit through the
  stations' heights (with a span length, the curvature moves with the slope), the across offset
  and azimuth from the image residuals. A cross-arm window's track that loses its wire at the
  track's support is retried at `DEFAULT_WINDOW_SUPPORT` (a low wire over the ground); that track
  and the earth window's are kept at `DEFAULT_WINDOW_SHARE` of their stations found; a window's
  wire attached more than `MAX_INSULATOR` tower heights below the lowest tip is not kept (a phase
  wire hangs from a tip by its insulator). Each wire as it is returned must rest on
  `MIN_EFFECTIVE_PHOTOS` photos (`single_view_dropped`, `effective_photos`): any curve in the plane
  through one photo's centre and a wire lies on that wire's detections in that photo.
* Refinement (`refine_span`): a station's cell is good to a pixel, and a pixel at 80 m is a
  milliradian of azimuth, decimetres at the far tower. Each kept wire is refined on the
  detections' sub-pixel centres (the along-normal offsets of the pairs that support it, clear of
  the other wires: `near_other_wires`); then the wires of a side share the variance-weighted
  median of their azimuths (`side_azimuth`: parallel wires to the same next tower), each turned
  to it about the middle of its track (`turned`) and refined again with it held; without a span
  length, once more with the span the side's wires share: the level span its phase wires' slope
  gives at the curvature they share with those across the tower (`phase_curvature`,
  `slope_span`: one tension either side of a suspension clamp), or the median of the side's
  wires' own where one side has no phase wire (`side_span`). A refined span's 1-sigma
  figures: its image residuals' covariance, the shared azimuth's sigma in place of its own.
* Across the tower: one conductor passes one suspension clamp, a span either side. A phase wire
  whose own slope ran off takes its attachment from its span across the tower when that one's
  agreed with its side (`clamped`); without a span length, a lone earth wire of a side takes the
  curvature of the earth wires across the tower (the same horizontal tension either side:
  `_lone_earth_shared`), each with the shared figure's sigma.
* Fit (`fit_span`, a library function the track replaced in `find_spans`):
  robust least squares (`scipy.optimize.least_squares`, Cauchy loss) on the
  image distance from each projected sample of the curve to the nearest detection (a distance
  transform's nearest-pixel map: iterated closest points), the samples' range grown in steps
  from the station outwards so the sag is found before the far part is asked to match. The
  1-sigma uncertainties are sigma^2 (J^T J)^-1 over the inlier residuals (sigma^2 their mean
  square; `fit_covariance`: a parameter the residuals do not fix is undetermined, an infinite
  sigma, and the record's sigmas None), propagated to every derived figure through its
  numerical Jacobian. A span is kept
  when at least `min_inlier_share` of its projected samples lie within 2 `tol_px` of a
  detection.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxnerf_grid.data.normalize import normalization_rotation
from jaxnerf_grid.export import catenary, to_metric64
from jaxnerf_grid.export.catenary import curve_points, derived, line_axes, sample_span

DEFAULT_SIGMAS = (1.0,)           # px: the ridge filter's scale (a sub-pixel wire, blurred by lens and pixel)
DEFAULT_THRESHOLD = 3.0           # detections: response above this many robust scales (at 4 the wires over ground fade)
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
    cam = (p[None] - centre[:, None]) @ rot   # R^T (x - c); matmul, not einsum: 10-40x faster here
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


def level_kappa(m0: float, span_length: float) -> float:
    """The curvature of a level span of that length leaving its attachment at slope m0:
    2 asinh(-m0) / L (0 for a wire that does not fall from its attachment)."""
    return 2.0 * math.asinh(max(-m0, 0.0)) / span_length


def _covariance(theta, views: Views, centre, s, up, inlier: np.ndarray,
                span_length: float | None = None) -> tuple[np.ndarray, float]:
    """sigma^2 (J^T J)^-1 over the inlier residuals [N, K] (their nearest detections held fixed:
    a central-difference Jacobian of the residuals); sigma^2 their mean square over
    (inliers - free parameters) degrees of freedom. With span_length L (a level span of that
    length: kappa = 2 asinh(-m0) / L, `fit_profile`) the four free parameters (c, z_a, psi, m0)
    have the covariance, mapped to theta's [5, 5] through d kappa / d m0 = -2 / (L sqrt(1 + m0^2)):
    the curvature moves with the slope, and the span stays L."""
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

    if span_length:
        def full(q):       # theta of the four free parameters
            return np.append(q, level_kappa(float(q[3]), span_length))
        m0 = float(theta[3])
        mapping = np.vstack([np.eye(4), [0.0, 0.0, 0.0, -2.0 / (span_length * math.sqrt(1.0 + m0 * m0))
                                         if m0 < 0 else 0.0]])
    else:
        def full(q):
            return q
        mapping = np.eye(5)
    free = theta[:mapping.shape[1]].copy()
    r = along(full(free))
    jac = np.zeros((len(r), len(free)))
    for k in range(len(free)):
        step = 1e-6 * max(abs(free[k]), 1.0) if k < 3 else 1e-7
        hi, lo = free.copy(), free.copy()
        hi[k] += step
        lo[k] -= step
        jac[:, k] = (along(full(hi)) - along(full(lo))) / (2 * step)
    dof = len(r) - len(free)
    if dof <= 0:
        return np.full((5, 5), np.inf), float("nan")
    return fit_covariance(jac, r, mapping), math.sqrt(float(r @ r) / dof)


UNDETERMINED_RCOND = 1e-9   # J^T J's eigenvalues (unit columns) under this share of the largest: not fixed


def fit_covariance(jac: np.ndarray, residuals: np.ndarray, jmap: np.ndarray | None = None,
                   rcond: float = UNDETERMINED_RCOND) -> np.ndarray:
    """A least-squares fit's covariance sigma^2 (J^T J)^-1 (jac [R, P] at the solution, residuals
    [R], sigma^2 = r.r / max(R - P, 1)) mapped to the figures jmap [Q, P] derives from the
    parameters (d figure / d parameter; None: the parameters themselves). Returns [Q, Q].
    A parameter the residuals do not fix (in a direction of J^T J, its columns scaled to unit
    norm, whose eigenvalue is under rcond of the largest: heights all at one distance leave the
    slope and the curvature free) is undetermined: an infinite variance, no covariance with the
    others; so is every figure that depends on it. The rest is the pseudo-inverse's, finite: the
    plain inverse of a nearly singular J^T J is round-off (variances of 1e13, negative ones) and
    its failure an infinite matrix that a map with zeros turns into NaN."""
    jac = np.asarray(jac, np.float64)
    r = np.asarray(residuals, np.float64)
    n_par = jac.shape[1]
    jmap = np.eye(n_par) if jmap is None else np.asarray(jmap, np.float64)
    sigma2 = float(r @ r) / max(len(r) - n_par, 1)
    norm = np.linalg.norm(jac, axis=0)
    scale = np.where(norm > 0, 1.0 / np.where(norm > 0, norm, 1.0), 0.0)   # unit columns: units compared on one scale
    lam, vec = np.linalg.eigh((jac * scale).T @ (jac * scale))
    fixed = lam > rcond * max(float(lam.max(initial=0.0)), 1e-300)
    undetermined = (norm == 0) | (np.linalg.norm(vec[:, ~fixed], axis=1) > 1e-6)
    inv = (vec[:, fixed] / lam[fixed]) @ vec[:, fixed].T
    cov_x = sigma2 * scale[:, None] * inv * scale[None, :]
    cov_x[undetermined, :], cov_x[:, undetermined] = 0.0, 0.0
    out = jmap @ cov_x @ jmap.T
    lost = np.any((jmap[:, undetermined] != 0), axis=1)
    out[lost, :], out[:, lost] = 0.0, 0.0
    out[lost, lost] = np.inf
    return out


# --- the guided track ------------------------------------------------------------------------------

DEFAULT_MAX_ANGLE = 25.0          # degrees: a detection supports a curve when its ridge runs this close to the curve's
TRACK_MAX_TURN = 0.002            # rad: the azimuth a track may correct (`track_span`'s max_turn)
DEFAULT_TRACK_SUPPORT = 0.3       # share of the photos seeing a station's best cell that support it
DEFAULT_WINDOW_SUPPORT = 0.25     # the track from a cross-arm window's peak (a wire hangs there)
DEFAULT_WINDOW_SHARE = 0.4        # the share of its stations tried (to its last found) that track, or one from
                                  # the earth wires' window, must find
DEFAULT_PEAK_SUPPORT = 0.45       # the cross-section's peaks outside the cross-arms' windows, where those are given
MIN_CATENARY_PARAMETER = 10.0     # tower heights: the plausible catenary parameter's floor (kappa <= 1 / (10 h))
MAX_CATENARY_PARAMETER = 300.0    # tower heights: its ceiling (a 30 m tower's wire tighter than a = 9 km is not hung)
MIN_EFFECTIVE_PHOTOS = 3.0        # photos a curve's support rests on (`effective_photos`): any two image curves
                                  # triangulate to some 3-D curve, a third photo is the first that can disagree
MAX_INSULATOR = 0.15              # tower heights: a suspension string's longest drop below its cross-arm's tip (the
#                                   generated towers' 2.6 m on 30.4 m is 0.09; the windows reach 0.25 for the fall
#                                   to the station)


def gated_support(views: Views, points: np.ndarray, tangents: np.ndarray, tol_px: float = DEFAULT_TOL_PX,
                  max_angle: float = DEFAULT_MAX_ANGLE, with_detections: bool = False) -> tuple:
    """Per point [M, 3] with the curve's direction there tangents [M, 3]: (the share of the photos
    seeing it whose nearest detection lies within tol_px of its projection AND runs along the
    projected curve (the detection's normal within max_angle degrees of the projected normal)
    [M], how many photos see it [M]). The ground's texture (dots, rings, blobs) has ridges of every
    direction; a wire's detections run along its projection. with_detections: also (ok [N, M] bool:
    the supporting pairs, det [N, M, 2]: their detections' (u, v))."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    t = np.asarray(tangents, np.float64).reshape(-1, 3)
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    u, v, z = project_all(p, views.c2w, views.intrinsics)
    eps = 1e-3 * np.maximum(np.abs(z), 1e-6)                          # [N, M]: a short step along the curve
    du, dv = _projected_direction(views, p, t, eps)
    has = np.asarray(views.has, dtype=np.bool_).reshape(-1, 1)           # [N, 1]
    seen = (z > 0) & (u >= 0) & (u < views.width) & (v >= 0) & (v < views.height) & has
    col = np.clip(np.floor(u), 0, views.width - 1).astype(np.int64)
    row = np.clip(np.floor(v), 0, views.height - 1).astype(np.int64)
    n = np.arange(len(views.c2w))[:, None]
    table = views.table if len(views.table) else np.full((1, 4), np.nan)
    det = table[np.maximum(views.index[n, row, col], 0)]               # [N, M, 4]
    near = np.hypot(det[..., 0] - u, det[..., 1] - v) <= tol_px
    across = np.abs(det[..., 2] * du + det[..., 3] * dv)              # |n_det . t_proj|: 0 along the curve
    along = np.where(np.isfinite(across), across <= math.sin(math.radians(max_angle)), True)
    ok = seen & near & along & (views.index[n, row, col] >= 0)
    count = seen.sum(axis=0)
    if with_detections:
        return ok.sum(axis=0) / np.maximum(count, 1), count, ok, det[..., :2]
    return ok.sum(axis=0) / np.maximum(count, 1), count


def _projected_direction(views: Views, points: np.ndarray, tangents: np.ndarray, eps: np.ndarray):
    """The unit image direction [N, M] (du, dv) of the curve through points [M, 3] along tangents
    [M, 3] (unit) in each photo, a finite step eps [N, M] (export units) along it."""
    rot, centre = views.c2w[:, :3, :3], views.c2w[:, :3, 3]
    cam = (points[None] - centre[:, None]) @ rot
    dcam = tangents[None] @ rot
    fx, fy = views.intrinsics[:, 0:1], views.intrinsics[:, 1:2]
    z0 = np.maximum(-cam[..., 2], 1e-9)
    z1 = np.maximum(-(cam[..., 2] + eps * dcam[..., 2]), 1e-9)
    du = fx * ((cam[..., 0] + eps * dcam[..., 0]) / z1 - cam[..., 0] / z0)
    dv = -fy * ((cam[..., 1] + eps * dcam[..., 1]) / z1 - cam[..., 1] / z0)
    norm = np.maximum(np.hypot(du, dv), 1e-12)
    return du / norm, dv / norm


def fit_profile(s: np.ndarray, z: np.ndarray, weight: np.ndarray, kappa_max: float, span_length: float | None = None,
                tol: float = 0.1, kappa_min: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The catenary's vertical profile through tracked heights z [K] at horizontal distances s [K]
    (weights [K]): (z_a, m0, kappa) minimising the Cauchy-robust (scale tol) weighted residuals
    z_a + sag_profile(s, m0, kappa) - z, kappa within [kappa_min, kappa_max]. With span_length L (the
    distance to the next tower, level span): kappa = 2 asinh(-m0) / L, only (z_a, m0) free.
    Fewer than 3 heights or under tol of curvature over their reach: a straight line.
    Returns (params [3], cov [3, 3] of (z_a, m0, kappa))."""
    from scipy.optimize import least_squares

    s, z, w = (np.asarray(a, np.float64) for a in (s, z, weight))
    sw = np.sqrt(w / max(float(w.mean()), 1e-12))
    a_mat = np.stack([np.ones_like(s), s], 1) * sw[:, None]
    line = np.linalg.lstsq(a_mat, z * sw, rcond=None)[0]
    if len(s) < 4:
        return np.array([line[0], line[1], 0.0]), np.diag([np.inf, np.inf, np.inf])

    def kappa_of(m0):
        return level_kappa(m0, span_length)

    if span_length:
        def res(p):
            return sw * (p[0] + catenary.sag_profile(s, p[1], kappa_of(p[1])) - z)
        x0 = np.array([line[0], min(line[1], -1e-4)])
        out = least_squares(res, x0, loss="cauchy", f_scale=tol, bounds=([-np.inf, -1.0], [np.inf, 0.0]))
        params = np.array([out.x[0], out.x[1], kappa_of(out.x[1])])
        jmap = np.array([[1.0, 0.0], [0.0, 1.0],
                         [0.0, -2.0 / (span_length * math.sqrt(1.0 + out.x[1] ** 2))]])
    else:
        def res(p):
            return sw * (p[0] + catenary.sag_profile(s, p[1], p[2]) - z)
        x0 = np.array([line[0], line[1], 0.5 * (kappa_min + kappa_max)])
        out = least_squares(res, x0, loss="cauchy", f_scale=tol, x_scale=[1.0, 0.01, 0.1 * kappa_max],
                            bounds=([-np.inf, -1.0, kappa_min], [np.inf, 1.0, kappa_max]))
        params, jmap = out.x, np.eye(3)
    return params, fit_covariance(out.jac, out.fun, jmap)


def plateau_centre(share: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> tuple[float, float]:
    """The centre (x, y) of the best cells of a support grid share [X, Y] over xs [X] x ys [Y]:
    the centroid of the 4-connected cells holding the maximum around the first of them.
    The support counts photos, so a wire's maximum is a plateau as wide as the tolerance band
    (3 px across a 1.5 px tol): the first cell of it sits at its low corner, a pixel's footprint
    off the wire, and a footprint grows with the distance (an azimuth's worth of bias)."""
    from scipy import ndimage

    top = share >= share.max()
    labels, _ = ndimage.label(top)
    i, j = np.unravel_index(int(np.argmax(share)), share.shape)
    rows, cols = np.nonzero(labels == labels[i, j])
    return float(np.mean(xs[rows])), float(np.mean(ys[cols]))


def _footprint(views: Views, points: np.ndarray, fallback: float) -> np.ndarray:
    """Per point [M, 3]: the median over the photos seeing it of its depth / focal length (a
    pixel's size there, export units) [M]; `fallback` where none sees it."""
    u, v, z = project_all(points, views.c2w, views.intrinsics)
    seen = (z > 0) & (u >= 0) & (u < views.width) & (v >= 0) & (v < views.height)
    fp = np.where(seen, z / views.intrinsics[:, :1], np.nan)
    with np.errstate(all="ignore"):
        out = np.nanmedian(np.where(seen.any(axis=0)[None], fp, fallback), axis=0)
    return np.where(np.isfinite(out), out, fallback)


def track_span(views: Views, centre, psi: float, c0: float, z0: float, s_start: float, s_end: float,
               fallback_px: float, length_scale: float, up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX,
               min_share: float = DEFAULT_TRACK_SUPPORT, min_views: int = DEFAULT_MIN_VIEWS,
               span_length: float | None = None, chunk: int = 6, max_misses: int = 12,
               max_turn: float = TRACK_MAX_TURN) -> dict:
    """Follow a wire from a seed (across offset c0, height z0 at horizontal distance s_start along
    e_line(psi) from centre) outwards to s_end: stations every length_scale / 15; at each one the
    cell of a small grid across the predicted curve (across x height, half a pixel's footprint
    apart, 4 footprints wide, the height window widening with the distance from the last station
    found) with the highest `gated_support`; a station is found when that support reaches
    min_share of >= min_views photos. After each `chunk` stations the curve is refitted (across:
    a line c0 + g s, i.e. the azimuth corrected by atan g; height: `fit_profile`, the catenary
    parameter at least MIN_CATENARY_PARAMETER length_scales, or the level span of span_length).
    Stops after max_misses stations in a row not found (or seen by too few photos). max_turn: the
    azimuth's correction is at most atan(max_turn) (the line's direction comes from the tower).
    Returns {"theta" [5] (c, z_a, psi, m0, kappa), "profile_cov" [3, 3], "found" [F, 3] (s, c, z of
    the stations found), "tried": stations tried while seen, "tried_to_reach": those up to the last
    found (the misses that end the track left out), "reach": the last station found}."""
    kappa_max = 1.0 / (MIN_CATENARY_PARAMETER * length_scale)
    kappa_min = 1.0 / (MAX_CATENARY_PARAMETER * length_scale)
    line, across, u = line_axes(psi, up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u
    ds = length_scale / 15.0
    lateral = np.array([c0, 0.0])          # c(s) = lateral[0] + lateral[1] (s - s_start)
    profile, pcov = np.array([z0, 0.0, 0.0]), np.diag([np.inf] * 3)
    found: list = []
    tried, misses, s_last, tried_last = 0, 0, s_start, 0
    s = s_start
    while s <= s_end and misses < max_misses:
        st = s + ds * np.arange(chunk)
        st = st[st <= s_end]
        if not len(st):
            break
        c_pred = lateral[0] + lateral[1] * (st - s_start)
        z_pred = profile[0] + catenary.sag_profile(st, profile[1], profile[2])
        slope = np.gradient(z_pred, st) if len(st) > 1 else np.full(len(st), profile[1])
        pts = base[None] + c_pred[:, None] * across + st[:, None] * line + z_pred[:, None] * u
        fp = _footprint(views, pts, fallback_px)
        for k in range(len(st)):
            half_c = 4.0 * fp[k]
            half_z = 4.0 * fp[k] + 0.03 * (st[k] - s_last)
            dc = np.arange(-half_c, half_c + 1e-9, 0.5 * fp[k])
            dz = np.arange(-half_z, half_z + 1e-9, 0.5 * fp[k])
            cc, zz = np.meshgrid(dc, dz, indexing="ij")
            cells = pts[k][None] + cc.reshape(-1, 1) * across + zz.reshape(-1, 1) * u
            tangent = line + slope[k] * u
            share, count = gated_support(views, cells, np.tile(tangent, (len(cells), 1)), tol_px)
            share = np.where(count >= min_views, share, 0.0)
            if not (count >= min_views).any():
                misses += 1
                continue
            tried += 1
            best = int(np.argmax(share))
            if share[best] >= min_share:
                c_best, z_best = plateau_centre(share.reshape(cc.shape), dc, dz)
                found.append((st[k], c_pred[k] + c_best, z_pred[k] + z_best, share[best]))
                misses, s_last, tried_last = 0, st[k], tried
            else:
                misses += 1
        if found:
            f = np.asarray(found)
            w = f[:, 3]
            if len(f) >= 4 and f[-1, 0] - f[0, 0] > 4 * ds:
                lateral = np.polyfit(f[:, 0] - s_start, f[:, 1], 1, w=np.sqrt(w))[::-1]
                lateral[1] = float(np.clip(lateral[1], -max_turn, max_turn))
            else:
                lateral = np.array([np.average(f[:, 1], weights=w), 0.0])
            profile, pcov = fit_profile(f[:, 0], f[:, 2], w, kappa_max, span_length, float(np.median(fp)),
                                        kappa_min)
        s = st[-1] + ds
    g = float(lateral[1])
    c_axis = float(lateral[0] - g * s_start)        # across offset extrapolated to the axis plane
    theta = np.array([c_axis * math.cos(math.atan(g)), profile[0], psi + math.atan(g), profile[1], profile[2]])
    return {"theta": theta, "profile_cov": pcov, "found": np.asarray(found, np.float64).reshape(-1, 4),
            "tried": tried, "tried_to_reach": tried_last, "reach": float(s_last)}


def curve_tangents(theta, centre, s: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The span's direction [K, 3] (not unit) at horizontal distances s [K]: e_line + z'(s) up."""
    line, _, u = catenary.line_axes(float(theta[2]), up)
    h = 1e-3
    slope = (catenary.sag_profile(np.asarray(s, np.float64) + h, theta[3], theta[4])
             - catenary.sag_profile(np.asarray(s, np.float64) - h, theta[3], theta[4])) / (2 * h)
    return line[None] + slope[:, None] * u[None]


def _polyline_in(drawn: list, i: int) -> np.ndarray:
    """The projected samples [Q, 2] in front of photo i of the curves `drawn` (each `project_all`'s
    (u, v, z) [N, S]); one point far off when none is in front, so a nearest-point query finds nothing near."""
    pieces = [np.stack([uu[i], vv[i]], 1)[zz[i] > 0] for uu, vv, zz in drawn]
    return np.concatenate([q for q in pieces if len(q)] or [np.full((1, 2), 1e12)])


def near_other_wires(views: Views, points: np.ndarray, others, centre, reach: float, up=(0.0, 0.0, 1.0),
                     radius_px: float = 3 * DEFAULT_TOL_PX) -> np.ndarray:
    """[N, M] bool: the photos in which point m [M, 3] projects within radius_px of another wire's
    projection (others: thetas [5], each drawn from its attachment to `reach`, 400 samples)."""
    from scipy.spatial import cKDTree

    u, v, z = project_all(points, views.c2w, views.intrinsics)
    out = np.zeros(u.shape, bool)
    s_far = np.linspace(0.0, reach, 400)
    drawn = [project_all(curve_points(t, centre, s_far, up), views.c2w, views.intrinsics) for t in others]
    for i in range(len(views.c2w)):
        poly = _polyline_in(drawn, i)
        d, _ = cKDTree(poly).query(np.stack([u[i], v[i]], 1))
        out[i] = (d <= radius_px + 0.5 * _sample_gap(poly)) & (z[i] > 0)
    return out


def _pair_residuals(q, views: Views, full, centre, s: np.ndarray, up, pairs: np.ndarray) -> np.ndarray:
    """The offsets [P] (`Views.offsets`) of the curve full(q) at s [K] in the (photo, station) pairs [N, K]."""
    return views.offsets(curve_points(full(q), centre, s, up), observed=pairs)[0][pairs]


SETTLE_REACH = 0.033     # tower heights: the attachment scan's half window (`_distinct`'s radius: one wire)
RESCAN_CAP = 0.1        # tower heights: the joint scan after the shared sag reaches at most this far (`rescanned`)
SETTLE_GAIN = 0.05       # share of the photos: a scanned attachment must gain this much support to move


def station_samples(s_from: float, s_to: float, samples: int = 60) -> np.ndarray:
    """[samples] stations from s_from to s_to, at least 1 mm long (a track of one station)."""
    return np.linspace(s_from, max(s_to, s_from + 1e-3), samples)


def track_samples(f: dict, samples: int = 60) -> np.ndarray:
    """`station_samples` over a record's track: from its first station tried to its last found."""
    return station_samples(float(f["track"][0, 0]), float(f["stations"][-1]), samples)


def curve_support(views: Views, theta, centre, s: np.ndarray, up=(0.0, 0.0, 1.0),
                  tol_px: float = DEFAULT_TOL_PX) -> float:
    """The mean over stations s [K] of the curve theta's `gated_support`: the share of the photos
    seeing each station whose detection lies on the projected curve and runs along it."""
    share, _ = gated_support(views, curve_points(theta, centre, s, up), curve_tangents(theta, centre, s, up), tol_px)
    return float(np.mean(share))


def scan_moves(offsets: np.ndarray, joint: bool) -> list[tuple]:
    """The attachment scan's candidate moves, in order, for offsets [N]: each a tuple of (index of
    theta, offset from theta's own value) set together. joint: every cell of the grid (across 0,
    height 1), across the outer loop; else height then across (index 1, then 0), each over the
    offsets, twice."""
    if joint:
        return [((0, dc), (1, dz)) for dc in offsets for dz in offsets]
    return [((k, d),) for _ in range(2) for k in (1, 0) for d in offsets]


def scan_attachment(views: Views, theta, centre, s_from: float, s_to: float, reach: float, step: float,
                    up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX, gain: float = SETTLE_GAIN,
                    samples: int = 60, joint: bool = False) -> tuple[np.ndarray, bool, float]:
    """theta [5] with its attachment moved to the offset within +-reach (a grid of `step`) where
    `curve_support` over `samples` stations from s_from to s_to is highest, when that gains more
    than `gain` over theta's own; else theta. joint False: height then across offset (twice), each
    move from theta's own value with the other at the best so far (`settled`); joint True: the
    cells of the joint (across, height) grid about theta (`rescanned`); `scan_moves` lists them.
    Returns (theta [5], moved, its `curve_support` over those stations)."""
    theta = np.asarray(theta, np.float64)
    s = station_samples(s_from, s_to, samples)
    offsets = np.arange(-reach, reach + 0.5 * step, step)
    own = curve_support(views, theta, centre, s, up, tol_px)
    best, best_share = theta.copy(), own
    for move in scan_moves(offsets, joint):
        t = (theta if joint else best).copy()
        for k, d in move:
            t[k] = theta[k] + d
        share = curve_support(views, t, centre, s, up, tol_px)
        if share > best_share:
            best, best_share = t, share
    if best_share > own + gain:
        return best, True, best_share
    return theta, False, own


def settled(views: Views, theta, centre, s_from: float, s_to: float, reach: float, step: float,
            up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX, gain: float = SETTLE_GAIN,
            samples: int = 60) -> tuple[np.ndarray, bool]:
    """theta [5] with its attachment moved, height then across offset (twice), to the offset within
    +-reach (a grid of `step`) where `curve_support` from s_from to s_to is highest, when that
    gains more than `gain` over theta's own; else theta (`scan_attachment`, alternating). The
    refinement's pairs are gated within tol_px of the curve: a curve that ended a few pixels off
    its wire over the far part has no pairs on it left to pull it back (on the 640x480 scene a
    phase wire's attachment stayed 0.52 m high, its support 0.07 there and 0.21 at 0.5 m lower).
    Returns (theta, moved)."""
    theta, moved, _ = scan_attachment(views, theta, centre, s_from, s_to, reach, step, up, tol_px, gain, samples)
    return theta, moved


def refine_span(views: Views, theta, centre, s_from: float, s_to: float, up=(0.0, 0.0, 1.0),
                tol_px: float = DEFAULT_TOL_PX, span_length: float | None = None, free=(0, 1, 2, 3),
                samples: int = 60, rounds: int = 3, max_turn: float = 0.01, loss_px: float = 0.5,
                others=(), clear_px: float = 3 * DEFAULT_TOL_PX, kappa_bounds: tuple = (0.0, 1.0)) -> np.ndarray:
    """theta [5] of a tracked span refined on the detections' sub-pixel centres: least squares
    (Cauchy, scale loss_px) of the signed distances along each detection's normal (`Views.offsets`)
    at `samples` stations from s_from to s_to, over the (photo, station) pairs whose nearest
    detection supports the curve (`gated_support`: within tol_px and running along it), the pairs
    chosen again each round. free: the indices of theta fitted (with span_length the curvature
    follows the slope, kappa = 2 asinh(-m0) / L; else kappa is free when 4 is in free); the azimuth
    within max_turn (rad) of theta's. The track's stations sit on a grid of half a pixel's
    footprint and a station's support is a plateau a few pixels wide: its centre is good to a
    pixel, and a pixel at 80 m is a milliradian of azimuth (decimetres at the far end); the
    detections' centres are good to a tenth of one. others: the thetas [5] of the other wires
    found; a pair whose projection lies within clear_px of one of theirs is left out
    (`near_other_wires`: the photos looking along the line see the wires converge, and the
    nearest detection there may be the neighbour's). kappa_bounds: the curvature's (lo, hi) when
    it is fitted. Returns theta [5]."""
    from scipy.optimize import least_squares

    theta = np.asarray(theta, np.float64).copy()
    free = list(free)
    s = station_samples(s_from, s_to, samples)
    psi0 = float(theta[2])

    def full(q):
        t = theta.copy()
        t[free] = q
        if span_length:
            t[4] = level_kappa(float(t[3]), span_length)
        return t

    lower = np.array([{2: psi0 - max_turn, 3: -1.0, 4: kappa_bounds[0]}.get(k, -np.inf) for k in free])
    upper = np.array([{2: psi0 + max_turn, 3: 0.0 if span_length else 1.0, 4: kappa_bounds[1]}.get(k, np.inf)
                      for k in free])
    scale = np.array([{2: 1e-3, 3: 1e-3, 4: 1e-5}.get(k, 0.05) for k in free])
    for _ in range(rounds):
        pts = curve_points(theta, centre, s, up)
        _, _, ok, _ = gated_support(views, pts, curve_tangents(theta, centre, s, up), tol_px, with_detections=True)
        if len(others):
            ok &= ~near_other_wires(views, pts, others, centre, 1.2 * float(s[-1]), up, clear_px)
        if ok.sum() <= len(free):
            break
        x0 = np.clip(theta[free], lower + 1e-12, upper - 1e-12)
        res = least_squares(_pair_residuals, x0, args=(views, full, centre, s, up, ok), loss="cauchy",
                            f_scale=loss_px, x_scale=scale, bounds=(lower, upper), method="trf", max_nfev=40)
        theta = full(res.x)
    return theta


# --- the spans of a tower -------------------------------------------------------------------------

def reaches_from(first: float, last: float) -> list[float]:
    """The fit's growing sample ranges: first, 2 first, 4 first, ... up to and ending at last."""
    out = [float(first)]
    while out[-1] * 2 < last:
        out.append(out[-1] * 2)
    return out + [float(last)]


def find_spans(views: Views, centre, psi: float, half_length: float, heights: tuple, across: float,
               step: float, tower_height: float, up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX,
               min_support: float = DEFAULT_TRACK_SUPPORT, min_views: int = DEFAULT_MIN_VIEWS,
               min_inlier_share: float = DEFAULT_MIN_INLIER_SHARE, seeds=(), span_length: float | None = None,
               min_found: int = 10, max_shared: float = 0.5, seed_window: tuple | None = None,
               peak_support: float = DEFAULT_PEAK_SUPPORT, window_support: float = DEFAULT_WINDOW_SUPPORT,
               window_share: float = DEFAULT_WINDOW_SHARE, max_insulator: float = MAX_INSULATOR,
               refine: bool = True,
               shared_azimuth: bool = True, shared_span: bool = True, shared_sag: bool = True,
               settle: bool = True, top_window: bool = True, shared_curvature: bool = True,
               min_photos: float = MIN_EFFECTIVE_PHOTOS, next_tower=None,
               side_turns: tuple[float, float] = (0.0, 0.0)) -> list[dict]:
    """The spans leaving a tower on both sides of the line (module docstring).

    centre [3]: the tower's axis; psi: the line's azimuth (`line_axes`); half_length: the tower's
    box reaches this far along the line from the axis (the lattice is left out of the fit);
    heights (lo, hi): the cross-section's heights (along up, the frame's zero); across: its half
    width; step: its cell (about a pixel's footprint there; peaks 3 tol_px cells apart at
    least); tower_height: the scale of the station's margin, of the track's stations and of the
    reach (30 tower heights); seeds [(c, z)]: attachment points (across offset, height: the
    cross-arms' tips) tried first, on both sides; seed_window (half width across, depth below,
    height above; None: the seeds are the attachments themselves): each seed stands for the
    window of the cross-section around it, where the wire hangs from a tip by an insulator of
    unknown length, and the window's peaks of `support` >= min_support are tried (`seed_peaks`);
    span_length: the distance to the next towers (a level span of that length, `fit_profile`),
    None: the catenary parameter free; peak_support: with seeds and a seed_window, the
    cross-section's peaks outside the windows need this support (the windows' peaks and the
    track min_support): a wire hangs below a cross-arm's tip or at the top of the tower, and a
    weak peak elsewhere is as often the ground's texture lined up (a path along the line).
    Each seed (the given ones, then the cross-section's peaks of `support` >= min_support) is
    followed outwards (`track_span`); a wire is kept when at least min_found stations and
    min_inlier_share of those tried were found, its attachment within the cross-section's window
    widened by the station's margin; one per wire (`_distinct`); strongest first (the sum of its
    stations' support), a wire is dropped when more than max_shared of its support lies on the
    wires kept before it (`shared_evidence`), then when more than that lies on all the others
    (`borrowers_dropped`). window_support: a window's track that loses its wire at min_support is
    retried at this support; window_share: that track, and one from the earth wires' window, is
    kept when it found this share of the stations it tried (min_inlier_share for the others).
    max_insulator (tower heights): a wire from a cross-arm's window is kept when its attachment
    lies at most this far below the lowest tip (a phase wire hangs from a tip by its insulator;
    the window reaches further down for the wire's fall to the station).
    refine: each candidate refined on the sub-pixel detections (`refine_span`), each kept wire
    again clear of the others; shared_azimuth: then the side's
    wires turned to one azimuth (`side_azimuth`, `turned`) and refined with it held; shared_span:
    without span_length, then refined with one level span the side's wires share: with
    shared_curvature and phase wires ("from_arm") on both sides, the span the side's phase wires'
    slope gives at the curvature pooled over both sides' phase wires (`phase_curvature`,
    `_span_from_curvature`: one tension either side of a suspension clamp; with next_tower, the
    sides' spans and that curvature from the next towers where the photos see them,
    `side_lengths`), else the median of the side's wires' own (`side_span`, from two wires);
    shared_sag: then the side's wires hung in the cross-arms' windows (the phase conductors: one
    conductor strung to one tension on one span hangs to one sag) refined with one slope at the
    attachment (`side_slope`; with a level span of one length that is one sag), from 3 such wires
    on a side (`_shared_sag`; a wire whose own slope ran off first pivoted and rescanned:
    `pivoted`, `rescanned`); the others (the earth wires above the arms) keep their own;
    top_window: with seeds and a seed_window, the earth wires' window (`earth_window`) searched at
    min_support after the arms' windows (its wires are not "from_arm"; "from_top" says so);
    settle: last, each wire whose attachment, scanned within SETTLE_REACH tower heights, gains
    support there is moved and its attachment refined again (`settled`, `_settled`), and of wires
    that then lie on one another the one whose curve gathers the most support is kept. With seeds
    and a seed_window, of the wires hung from one tip only the best supported is kept
    (`one_per_tip`: one insulator string a phase conductor). side_turns (rad, side +1's and side
    -1's): each side searched along its azimuth turned by this (`turned_search`). Then a
    wire whose support rests on fewer than min_photos photos is dropped (`single_view_dropped`,
    `effective_photos`: one photo's plane of sight through a wire holds any curve). With
    shared_sag, after both sides: a wire whose own slope ran off takes the attachment of its span
    across the tower through the same clamp when that one's agreed with its side (`clamped`);
    without span_length, a lone earth wire of a side takes the curvature of the earth wires across
    the tower (`_lone_earth_shared`).
    Returns [{"side": +1 | -1, "psi", "seed" (across, height, support), "from_arm", "theta", "cov"
    (`combined_covariance`), "image_cov" (`_covariance`), "sigma_px", "inlier_share", "residuals",
    "seen", "stations", "track" [F, 4], "span_length", "profile_cov", with shared_span
    "span_length_shared" (L, sigma) and, the curvature pooled, "curvature_across" (kappa, sigma) and
    "next_tower" (the side's next tower found, None where not),
    with shared_sag on the arms' wires "slope_shared" (m0, sigma)
    and "slope_own", where they apply "clamp_shared" and "curvature_shared" (kappa, sigma)}]."""
    spans = []
    sides: dict[int, list[dict]] = {}
    margin = 0.3 * tower_height
    station = half_length + margin
    # the refinement fits the curvature too unless the span length ties it to the slope
    free = (0, 1, 2, 3) if span_length else (0, 1, 2, 3, 4)
    kappa_bounds = (1.0 / (MAX_CATENARY_PARAMETER * tower_height), 1.0 / (MIN_CATENARY_PARAMETER * tower_height))
    # a phase wire hangs from a cross-arm's tip by its insulator: a window's curve attached further
    # below every tip is not hung there (the window's depth is the fall to the station)
    windowed = seed_window is not None and len(seeds) > 0
    hung_floor = min(float(z) for _, z in seeds) - max_insulator * tower_height if windowed else -math.inf
    for side, turn in zip((1, -1), side_turns):
        psi_side = (psi if side == 1 else psi + math.pi) + float(turn)
        peaks = cross_section_peaks(views, centre, psi_side, station, (-across, across), heights, step, up,
                                    tol_px, max(min_support, peak_support) if windowed else min_support, min_views,
                                    separation=3 * tol_px * step)
        if seed_window is None:
            given = [(float(c) * side, float(z), float("nan")) for c, z in seeds]   # across flips with the side
        else:
            given = seed_peaks(views, centre, psi_side, station, [(float(c) * side, float(z)) for c, z in seeds],
                               seed_window, step, up, tol_px, min_support, min_views)
        top: list[tuple] = []
        if top_window and seed_window is not None and len(seeds) > 0:
            top = [tuple(float(v) for v in p) for p in
                   cross_section_peaks(views, centre, psi_side, station, *earth_window(seeds, seed_window, heights),
                                       step, up, tol_px, min_support, min_views, separation=3 * tol_px * step)]
        fits: list[dict] = []
        for k_seed, (c, z, share) in enumerate(given + top + [tuple(p) for p in peaks]):
            in_window = seed_window is not None and k_seed < len(given)
            in_top = len(given) <= k_seed < len(given) + len(top)
            seed = curve_points((c, z, psi_side, 0.0, 0.0), centre, np.array([station]), up)[0]
            if any(np.linalg.norm(curve_points(f["theta"], centre, np.array([station]), up)[0] - seed) < 0.033 *
                   tower_height for f in fits):
                continue   # on a wire already fitted: the support is a ridge across the plane, not a point
            track = {**track_span(views, centre, psi_side, c, z, station, 30 * tower_height, step, tower_height, up,
                                  tol_px, min_support, min_views, span_length), "min_share": min_support}
            if in_window and not _enough(track, min_found, min_inlier_share) and window_support < min_support:
                # a wire hangs below every cross-arm tip: one over the ground, its detections broken by
                # the texture, is followed at a lower support when the usual one loses it
                track = {**track_span(views, centre, psi_side, c, z, station, 30 * tower_height, step, tower_height,
                                      up, tol_px, window_support, min_views, span_length), "min_share": window_support}
            # a window where a wire hangs (a cross-arm's, retried lower; the earth wires'): its track is
            # judged at window_share, the low wires' and earth wires' support broken over half their stations
            expected = in_top or (in_window and track["min_share"] < min_support)
            if not _enough(track, min_found, window_share if expected else min_inlier_share):
                continue
            theta = track["theta"]
            if refine:
                theta = refine_span(views, theta, centre, float(track["found"][0, 0]), track["reach"], up, tol_px,
                                    span_length, free=free, kappa_bounds=kappa_bounds)
            fit = _finish(views, theta, centre, half_length, track["reach"], up, tol_px,
                          span_length=span_length)
            c_fit, z_fit = fit["theta"][0], fit["theta"][1]
            if (abs(c_fit) <= across + margin and heights[0] - margin <= z_fit <= heights[1] + margin
                    and (not in_window or z_fit >= hung_floor)):
                fits.append({"side": side, "psi": psi_side, "seed": [float(c), float(z), float(share)],
                             "from_arm": bool(in_window), "from_top": bool(in_top),
                             "track_support": float(track["min_share"]),
                             "track": track["found"], "profile_cov": track["profile_cov"], **fit,
                             "image_cov": fit["cov"], "cov": combined_covariance(fit["cov"], track["profile_cov"])})
        kept: list[dict] = []
        for f in sorted(_distinct(fits, centre, 0.033 * tower_height, up),
                        key=lambda f: -float(f["track"][:, 3].sum())):
            if shared_evidence(views, f["track"], f["theta"], [k["theta"] for k in kept], centre, f["psi"], up,
                               tol_px) <= max_shared:
                kept.append(f)
        kept = borrowers_dropped(views, kept, centre, up, tol_px, max_shared)
        if refine:
            kept = [_refined(views, f, [k["theta"] for k in kept if k is not f], centre, half_length, up, tol_px,
                             span_length, free, kappa_bounds) for f in kept]
            if shared_azimuth and len(kept) > 1:
                psi_shared, psi_sigma = side_azimuth(np.array([f["theta"][2] for f in kept]),
                                                     np.array([f["image_cov"][2, 2] for f in kept]))
                pivots = [float(np.median(f["track"][:, 0])) for f in kept]
                kept = [_refined(views, {**f, "theta": turned(f["theta"], psi_shared, pivot)},
                                 [k["theta"] for k in kept if k is not f], centre, half_length, up, tol_px,
                                 span_length, tuple(i for i in free if i != 2), kappa_bounds, psi_sigma)
                        for f, pivot in zip(kept, pivots)]
        sides[side] = kept
    # the phase wires' curvature from both sides (one tension through the suspension clamps), no span length given
    pooled = (phase_curvature(sides[1], sides[-1])
              if refine and shared_span and shared_curvature and not span_length else None)
    lengths: dict = {}
    measured: dict = {}
    if pooled is not None:
        slopes = {side: held_slopes(views, sides[side], centre, half_length, up, tol_px, kappa_bounds, pooled[0])
                  for side in (1, -1)}
        lengths, pooled, measured = side_lengths(slopes, pooled, psi, next_tower)
    for side in (1, -1):
        kept = sides[side]
        if refine:
            if pooled is not None:
                kept = _span_from_curvature(views, kept, centre, half_length, up, tol_px, kappa_bounds, pooled,
                                            lengths.get(side), measured.get(side))
            elif shared_span and not span_length:
                kept = _shared_span(views, kept, centre, half_length, up, tol_px, kappa_bounds)
            if shared_sag:
                kept = _shared_sag(views, kept, centre, half_length, up, tol_px, span_length, kappa_bounds,
                                   (SETTLE_REACH * tower_height, RESCAN_CAP * tower_height, step))
            if settle:
                kept = [_settled(views, f, kept, centre, half_length, up, tol_px, kappa_bounds,
                                 SETTLE_REACH * tower_height, step) for f in kept]
                # a weak curve beside a wire is moved onto it by the scan: one record per wire
                kept = _distinct(kept, centre, 0.033 * tower_height, up, key=lambda f: -f["support"])
        if windowed:
            kept = one_per_tip(kept, [(float(c) * side, float(z)) for c, z in seeds], max_insulator * tower_height,
                               SETTLE_REACH * tower_height)
        # the shared sag's rescan and the last scan move a weak curve where it gathers the most support,
        # one photo's plane of sight through a wire among those places: judged as it is returned
        kept = single_view_dropped(views, kept, centre, up, tol_px, min_photos)
        spans += kept
    if refine and shared_sag:
        spans = clamped(spans, centre, SETTLE_REACH * tower_height, RESCAN_CAP * tower_height, up)
    if refine and shared_sag and not span_length:
        spans = _lone_earth_shared(views, spans, centre, half_length, up, tol_px, kappa_bounds)
    return spans


def side_turns(spans: list[dict], psi: float) -> tuple[float, float]:
    """Each side's azimuth as its wires measured it (`side_azimuth` of the spans' theta[2] with
    their image variances) less the one searched (side +1: psi, side -1: psi + pi), wrapped to
    (-pi, pi]; 0 for a side without a wire. Returns (turn +1, turn -1) [rad]."""
    out = []
    for side in (1, -1):
        kept = [f for f in spans if f["side"] == side]
        if not kept:
            out.append(0.0)
            continue
        found, _ = side_azimuth(np.array([f["theta"][2] for f in kept]),
                                np.array([f["image_cov"][2, 2] for f in kept]))
        searched = psi if side == 1 else psi + math.pi
        out.append(float(math.remainder(found - searched, 2.0 * math.pi)))
    return out[0], out[1]


def turned_search(views: Views, centre, psi: float, *args, **kwargs) -> tuple[list[dict], tuple[float, float]]:
    """`find_spans`, and once more with each side's azimuth turned to the one its wires measured
    (`side_turns`) when either side's is more than TRACK_MAX_TURN off: the line's direction from
    the tower's mesh is good to about a centiradian, and a track that may turn by 2 mrad loses a
    weak wire tens of metres out where the azimuth is 10 mrad off (a metre at 100 m). The second
    search is kept when it finds at least as many spans. Returns (spans, the turns searched)."""
    spans = find_spans(views, centre, psi, *args, **kwargs)
    turns = side_turns(spans, psi)
    if max(abs(t) for t in turns) <= TRACK_MAX_TURN:
        return spans, (0.0, 0.0)
    again = find_spans(views, centre, psi, *args, **{**kwargs, "side_turns": turns})
    return (again, turns) if len(again) >= len(spans) else (spans, (0.0, 0.0))


def earth_window(seeds, seed_window: tuple, heights: tuple) -> tuple[tuple, tuple]:
    """The cross-section's window of the earth wires (across (lo, hi), heights (lo, hi)): above the
    highest cross-arm's window (its tips' height + seed_window's `above`) up to the top of the
    cross-section (heights[1]), across no wider than the cross-arms' tips (seeds [(c, z)]). An
    earth wire runs from the tower's top, above the arms and within their reach; its peak in the
    open plane falls short of DEFAULT_PEAK_SUPPORT where birds or the far sky break it."""
    c = np.asarray([p[0] for p in seeds], np.float64)
    z = np.asarray([p[1] for p in seeds], np.float64)
    reach = float(np.max(np.abs(c)))
    return (-reach, reach), (float(z.max()) + float(seed_window[2]), float(heights[1]))


def side_span(lengths: np.ndarray) -> tuple[float, float]:
    """The level span [export units] the wires of one side share, from each wire's own (`derived`
    "span" of its refined curve, the curvature free) lengths [K]: their median and its 1-sigma,
    1.4826 MAD / sqrt(K) (at least 1e-3 of the median). Unweighted: the image residuals' sigma
    of a span rests on the curvature, which the photos barely see, and a wire whose curvature
    ran to its bound states the smallest sigma of all (the lowest phase wire at 640x480: 147 m
    +- 3 against 297-323 m for the others)."""
    return median_and_sigma(lengths, floor_share=1e-3)


def median_and_sigma(values: np.ndarray, floor_share: float = 0.0) -> tuple[float, float]:
    """The median of values [K] and its robust 1-sigma, 1.4826 MAD / sqrt(K), at least floor_share
    of the median's magnitude: what the wires of a side share (`side_span`, `side_slope`), one
    wire far off moving it by one place only."""
    x = np.asarray(values, np.float64)
    med = float(np.median(x))
    sigma = 1.4826 * float(np.median(np.abs(x - med))) / math.sqrt(len(x))
    return med, max(sigma, floor_share * abs(med))


def with_span(theta, length: float) -> np.ndarray:
    """theta [5] with the curvature of a level span of that length at its slope: 2 asinh(-m0) / L."""
    out = np.asarray(theta, np.float64).copy()
    out[4] = level_kappa(float(out[3]), length)
    return out


def _shared_span(views: Views, kept: list[dict], centre, half_length: float, up, tol_px: float,
                 kappa_bounds: tuple, shared: tuple | None = None) -> list[dict]:
    """The wires of one side, no span length given, refined again with the span they share
    (`side_span` of their own, or shared (L, sigma_L) where given; the same next tower, a level
    span): the curvature tied to each wire's slope, the azimuth held; the shared length's variance
    added to the curvature's ((kappa / L)^2 sigma_L^2). Each record gets "span_length_shared"
    (L, sigma_L); its "span_length" (the given one) stays None. Without `shared` it takes two
    wires: one alone is returned as it is."""
    if shared is not None:
        length, sigma = (float(v) for v in shared)
    elif len(kept) < 2:
        return kept
    else:
        lengths = np.array([derived(f["theta"], centre, up)["span"] for f in kept])
        finite = np.isfinite(lengths)
        if not finite.any():
            return kept
        length, sigma = side_span(lengths[finite])
    out = []
    for f in kept:
        others = [k["theta"] for k in kept if k is not f]
        r = _refined(views, {**f, "theta": with_span(f["theta"], length)}, others, centre, half_length, up, tol_px,
                     length, (0, 1, 3), kappa_bounds, math.sqrt(max(float(f["cov"][2, 2]), 0.0)))
        cov = r["cov"].copy()
        cov[4, 4] += (float(r["theta"][4]) / length) ** 2 * sigma ** 2
        out.append({**r, "cov": cov, "span_length": None, "span_length_shared": (length, sigma)})
    return out


def phase_wires(kept: list[dict]) -> list[dict]:
    """The wires of a side's records (`find_spans`) hung in the cross-arms' windows ("from_arm"):
    the phase conductors, one conductor type strung to one tension."""
    return [f for f in kept if f.get("from_arm")]


def pooled_curvature(kappas: np.ndarray) -> tuple[float, float]:
    """The curvature (1 / the catenary parameter) the phase wires of both sides of a suspension
    tower share, from each wire's own kappas [K] (both sides together): their median and its
    1-sigma, 1.4826 MAD / sqrt(K) (at least 1e-3 of the median). The insulator string hangs
    vertical, so a conductor pulls one horizontal tension either side: one a = H / w. The median,
    as `side_span`'s: a wire whose curvature ran to its bound states the smallest sigma of all."""
    return median_and_sigma(kappas, floor_share=1e-3)


def phase_curvature(plus: list[dict], minus: list[dict]) -> tuple[float, float] | None:
    """`pooled_curvature` of the phase wires (`phase_wires`) of both sides' records (`find_spans`,
    their curvature fitted), (kappa, sigma); None when a side has none (a side without phase
    wires says nothing of the other's tension) or the median curvature is not a sag (<= 0)."""
    plus, minus = phase_wires(plus), phase_wires(minus)
    if not plus or not minus:
        return None
    kappa, sigma = pooled_curvature(np.array([float(f["theta"][4]) for f in plus + minus]))
    return (kappa, sigma) if kappa > 0 else None


def slope_span(slopes: np.ndarray, kappa: float, sigma_kappa: float) -> tuple[float, float] | None:
    """The level span [export units] of one side from its phase wires' slopes at the attachment
    slopes [K] (each fitted with the curvature held at kappa) and the curvature they share:
    L = 2 asinh(-m) / kappa of their median m (`side_slope`), and its 1-sigma, first order in
    both: (L / kappa)^2 sigma_kappa^2 + (2 / (kappa sqrt(1 + m^2)))^2 sigma_m^2. None when the
    median slope does not fall from the attachment (no level span)."""
    slope, sigma_m = side_slope(slopes)
    if slope >= 0 or kappa <= 0:
        return None
    length = 2.0 * math.asinh(-slope) / kappa
    dl_dm = -2.0 / (kappa * math.sqrt(1.0 + slope * slope))
    return length, math.hypot(length / kappa * sigma_kappa, dl_dm * sigma_m)


def held_slopes(views: Views, kept: list[dict], centre, half_length: float, up, tol_px: float,
                kappa_bounds: tuple, kappa: float) -> np.ndarray:
    """The slopes at the attachment [K] of one side's phase wires (`phase_wires`), each refined
    with its curvature held at kappa (the slope freed from the curvature the photos barely see)."""
    phase = phase_wires(kept)
    held = [_refined(views, {**f, "theta": np.append(np.asarray(f["theta"], np.float64)[:4], kappa)},
                     [k["theta"] for k in kept if k is not f], centre, half_length, up, tol_px, None, (0, 1, 3),
                     kappa_bounds, math.sqrt(max(float(f["cov"][2, 2]), 0.0))) for f in phase]
    return np.array([float(f["theta"][3]) for f in held])


NEXT_TOWER_SIGMAS = 4.0   # the next tower's search window: the curvature's span +- this many of its sigmas,
NEXT_TOWER_SHARE = 0.05   # and at least this share of it


def next_tower_window(length: float, sigma: float) -> tuple[float, float]:
    """The distances (lo, hi) the next tower is searched over about the span the curvature gives
    (length, sigma): +- max(NEXT_TOWER_SIGMAS sigma, NEXT_TOWER_SHARE length)."""
    half = max(NEXT_TOWER_SIGMAS * sigma, NEXT_TOWER_SHARE * length)
    return max(length - half, 0.5 * length), length + half


def curvature_from_spans(slopes: dict, measured: dict) -> tuple[float, float]:
    """The curvature (kappa, sigma) of the sides' measured spans: each side's level span L at its
    phase wires' median slope m (`side_slope`) gives kappa = 2 asinh(-m) / L, its variance first
    order in both, (kappa sigma_L / L)^2 + (2 sigma_m / (L sqrt(1 + m^2)))^2; the sides'
    inverse-variance mean. slopes {side: [K]}, measured {side: {"length", "sigma"}}."""
    kappas, weights = [], []
    for side, found in measured.items():
        slope, sigma_m = side_slope(slopes[side])
        length, sigma_l = float(found["length"]), float(found["sigma"])
        kappa = 2.0 * math.asinh(-slope) / length
        var = (kappa * sigma_l / length) ** 2 + (2.0 * sigma_m / (length * math.sqrt(1.0 + slope * slope))) ** 2
        kappas.append(kappa)
        weights.append(1.0 / max(var, 1e-30))
    w = np.asarray(weights)
    return float(np.asarray(kappas) @ w / w.sum()), float(1.0 / math.sqrt(w.sum()))


def side_lengths(slopes: dict, pooled: tuple, psi: float, next_tower=None) -> tuple[dict, tuple, dict]:
    """Each side's level span from its phase wires' slopes at the attachment slopes {side: [K]} and
    the curvature pooled across the tower (kappa, sigma) (`slope_span`; None for a side without
    phase wires or a fall). With next_tower (a callable (azimuth, (lo, hi)) -> {"length", "sigma",
    ...} | None, `export.next_tower`), the next tower is searched on each side within
    `next_tower_window` of that span; the sides where it is found set the curvature
    (`curvature_from_spans`), their spans are the measured ones and the others' follow from
    their slopes at it. Returns ({side: (L, sigma) | None}, (kappa, sigma), {side: found})."""
    kappa, sigma = pooled
    lengths = {side: slope_span(s, kappa, sigma) if len(s) else None for side, s in slopes.items()}
    measured: dict = {}
    if next_tower is not None:
        for side, est in lengths.items():
            if est is not None:
                found = next_tower(psi if side == 1 else psi + math.pi, next_tower_window(*est))
                if found is not None:
                    measured[side] = found
    if not measured:
        return lengths, (kappa, sigma), {}
    kappa, sigma = curvature_from_spans(slopes, measured)
    lengths = {side: (float(measured[side]["length"]), float(measured[side]["sigma"])) if side in measured else
               (slope_span(s, kappa, sigma) if len(s) else None) for side, s in slopes.items()}
    return lengths, (kappa, sigma), measured


def _span_from_curvature(views: Views, kept: list[dict], centre, half_length: float, up, tol_px: float,
                         kappa_bounds: tuple, pooled: tuple, shared: tuple | None,
                         measured: dict | None = None) -> list[dict]:
    """The wires of one side, no span length given, refined with the span shared (L, sigma) its
    phase wires' slopes give at the curvature pooled (kappa, sigma) (`side_lengths`: across the
    tower, `phase_curvature`, or from the next towers measured), every wire of the side tied to
    it (`_shared_span`). Each record gets "curvature_across" (kappa, sigma), "curvature_own" (its
    curvature and 1-sigma before, the image residuals') and "next_tower" (measured: the side's
    next tower found, `export.next_tower`; else None). A side whose slopes give no span shares
    its wires' own span instead (`_shared_span`, from two wires)."""
    if shared is None:
        return _shared_span(views, kept, centre, half_length, up, tol_px, kappa_bounds)
    kappa, sigma_kappa = (float(v) for v in pooled)
    out = _shared_span(views, kept, centre, half_length, up, tol_px, kappa_bounds, shared)
    own = [(float(f["theta"][4]), math.sqrt(max(float(f["image_cov"][4, 4]), 0.0))) for f in kept]
    return [{**f, "curvature_across": (kappa, sigma_kappa), "curvature_own": k, "next_tower": measured}
            for f, k in zip(out, own)]


MIN_SHARED_SAG = 3   # the arms' wires on a side that make a median: with 2 an outlier is half of it


def side_slope(slopes: np.ndarray) -> tuple[float, float]:
    """The slope at the attachment (dz / ds) the phase wires of one side share, from their own
    [K]: their median and its 1-sigma, 1.4826 MAD / sqrt(K) (at least 1e-4). The median, as
    `side_span`'s: one wire tracked onto its neighbour's detections near the tower comes out
    with a confident, wrong sag (34 % off at 640x480, the others within 3 %)."""
    med, sigma = median_and_sigma(slopes)
    return med, max(sigma, 1e-4)


def with_slope(theta, slope: float, length: float) -> np.ndarray:
    """theta [5] leaving its attachment at `slope`, with the curvature of a level span of that
    length there (`level_kappa`)."""
    out = np.asarray(theta, np.float64).copy()
    out[3] = slope
    out[4] = level_kappa(slope, length)
    return out


def _shared_sag(views: Views, kept: list[dict], centre, half_length: float, up, tol_px: float,
                span_length: float | None, kappa_bounds: tuple, scan: tuple | None = None) -> list[dict]:
    """The wires of one side hung in the cross-arms' windows ("from_arm"), at least MIN_SHARED_SAG
    of them, refined again with the slope at the attachment they share (`side_slope`): with the
    span's one length (the given one, else "span_length_shared") one slope is one curvature and
    one sag, and only the attachment (across, height) is fitted, the azimuth held. The shared
    slope's variance replaces the wire's own (no correlation with the fitted parameters), the
    curvature's follows it (d kappa / d m0 = -2 / (L sqrt(1 + m0^2))) plus the shared length's
    ((kappa / L)^2 sigma_L^2). Each such record gets "slope_shared" (m0, sigma); the others are
    returned as they are. Nothing changes without a span length of either kind. scan (floor, cap,
    step): a wire whose own slope, over its track's reach, puts it more than floor off the shared
    one's curve is moved to pass its own curve's height at its track's first station (`pivoted`)
    and its attachment scanned jointly within floor (`rescanned`), kept there when the shared
    curve holds more support than the wire's own (its own slope ran off; a wire that does hang
    deeper keeps its attachment)."""
    arm = [f for f in kept if f.get("from_arm")]
    shared_length = next((f["span_length_shared"] for f in arm if f.get("span_length_shared")), (None, 0.0))
    length = span_length or shared_length[0]
    if len(arm) < MIN_SHARED_SAG or not length:
        return kept
    sigma_length = 0.0 if span_length else float(shared_length[1])
    slope, sigma = side_slope(np.array([f["theta"][3] for f in arm]))
    out = []
    for f in kept:
        if not f.get("from_arm"):
            out.append(f)
            continue
        others = [k["theta"] for k in kept if k is not f]
        psi_sigma = math.sqrt(max(float(f["cov"][2, 2]), 0.0))
        theta = with_slope(f["theta"], slope, length)
        if scan is not None:
            reach = rescan_reach(float(f["theta"][3]), slope, float(f["stations"][-1]), scan[1])
            if reach > scan[0]:
                first, last = float(f["track"][0, 0]), float(f["stations"][-1])
                moved, _, support = scan_attachment(views, pivoted(theta, f["theta"], first), centre, first, last,
                                                    scan[0], scan[2], up, tol_px, joint=True)
                # a wire that does hang to its own sag keeps its attachment: its own curve holds more support
                if support > curve_support(views, f["theta"], centre, track_samples(f), up, tol_px):
                    theta = moved
        r = _refined(views, {**f, "theta": theta}, others, centre, half_length,
                     up, tol_px, length, (0, 1), kappa_bounds, psi_sigma)
        kappa = float(r["theta"][4])
        dk = -2.0 / (length * math.sqrt(1.0 + slope * slope)) if slope < 0 else 0.0
        cov = r["cov"].copy()
        cov[3:, :], cov[:, 3:] = 0.0, 0.0
        cov[3, 3], cov[3, 4] = sigma ** 2, dk * sigma ** 2
        cov[4, 3], cov[4, 4] = dk * sigma ** 2, (dk * sigma) ** 2 + (kappa / length) ** 2 * sigma_length ** 2
        out.append({**r, "cov": cov, "span_length": span_length, "slope_shared": (slope, sigma),
                    "slope_own": float(f["theta"][3])})
    return out


def clamp_pairs(spans: list[dict], centre, radius: float, up=(0.0, 0.0, 1.0)) -> list[tuple[int, int]]:
    """Pairs (i, j) of indices into spans (`find_spans`' records of both sides) of wires hung from
    the arms ("from_arm") with a shared slope ("slope_shared"), i on side +1 and j on side -1,
    whose attachments (their curves at s = 0) lie within radius of each other, the nearest first
    and each wire in one pair: one conductor through one suspension clamp, a span either side."""
    att = [curve_points(f["theta"], centre, np.zeros(1), up)[0] for f in spans]
    arm = [i for i, f in enumerate(spans) if f.get("from_arm") and f.get("slope_shared")]
    near = sorted((float(np.linalg.norm(att[i] - att[j])), i, j) for i in arm for j in arm
                  if spans[i]["side"] == 1 and spans[j]["side"] == -1)
    used: set = set()
    out = []
    for d, i, j in near:
        if d <= radius and i not in used and j not in used:
            out.append((i, j))
            used |= {i, j}
    return out


def attachment_on(theta, point, centre, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """theta [5] with its attachment (across, height) moved to the 3-D point [3] (its azimuth,
    slope and curvature kept): across = (point - axis) . e_across(psi), height = point . up."""
    out = np.asarray(theta, np.float64).copy()
    _, across, u = line_axes(float(out[2]), up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u
    p = np.asarray(point, np.float64)
    out[0], out[1] = float((p - base) @ across), float(p @ u)
    return out


def clamped(spans: list[dict], centre, floor: float, cap: float, up=(0.0, 0.0, 1.0)) -> list[dict]:
    """The spans of both sides with the attachment of a wire whose own slope ran off taken from its
    other span through the same clamp (`clamp_pairs` within floor): of a pair, the one whose own
    slope ("slope_own"), over its track's reach, lies more than floor off its side's shared one
    (`rescan_reach`, capped at cap) was tracked onto the ground's texture or a neighbour over part
    of its reach and its attachment extrapolated with it (plad-like seed 2: 0.6 m low, its span
    across the tower on the wire), while the other's own slope agreed with its side's. It takes
    the other's attachment point (`attachment_on`) and its attachment's covariance, its shared
    slope and curvature kept, and records "clamp_shared" True. Pairs that both agree, or both ran
    off, are left."""
    out = list(spans)
    for i, j in clamp_pairs(spans, centre, floor, up):
        off = [rescan_reach(float(spans[k].get("slope_own", spans[k]["theta"][3])),
                            float(spans[k]["slope_shared"][0]), float(spans[k]["stations"][-1]), cap) > floor
               for k in (i, j)]
        if off[0] == off[1]:
            continue
        bad, good = (i, j) if off[0] else (j, i)
        point = curve_points(spans[good]["theta"], centre, np.zeros(1), up)[0]
        theta = attachment_on(spans[bad]["theta"], point, centre, up)
        # the across axes of the two sides point opposite ways: the across-height covariance flips with them
        flip = float(np.sign(line_axes(float(theta[2]), up)[1] @ line_axes(float(spans[good]["theta"][2]), up)[1]))
        cov = np.array(spans[bad]["cov"], np.float64).copy()
        cov[:2, :], cov[:, :2] = 0.0, 0.0
        block = np.array(spans[good]["cov"], np.float64)[:2, :2].copy()
        block[0, 1] *= flip
        block[1, 0] *= flip
        cov[:2, :2] = block
        out[bad] = {**spans[bad], "theta": theta, "cov": cov, "clamp_shared": True}
    return out


def lone_earth_wires(spans: list[dict]) -> list[int]:
    """The indices into spans (`find_spans`' records of both sides) of the earth wires (not
    "from_arm") alone on their side while the other side has earth wires of its own: nothing on
    their side to check their sag against, something across the tower to share it with."""
    earth = [f["side"] for f in spans if not f.get("from_arm")]
    return [i for i, f in enumerate(spans)
            if not f.get("from_arm") and earth.count(f["side"]) == 1 and len(earth) > 1]


def across_curvature(kappas: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """The curvature (1 / the catenary parameter) a lone earth wire takes from the earth wires
    across the tower, kappas [K] with their own variances [K]: their median and its 1-sigma, the
    larger of the scaled MAD (`median_and_sigma`) and their own sigmas' root mean square (two
    wires that agree by chance state no better than each of them)."""
    kappa, sigma = median_and_sigma(kappas)
    own = math.sqrt(float(np.mean(np.where(np.isfinite(variances), variances, 0.0))))
    return kappa, max(sigma, own)


def level_slope_jacobian(kappa: float, length: float) -> tuple[float, float]:
    """(d m0 / d kappa, d m0 / d L) of a level span's slope at its attachment, m0 = -sinh(kappa L / 2)."""
    c = math.cosh(0.5 * kappa * length)
    return -0.5 * length * c, -0.5 * kappa * c


def _lone_earth_shared(views: Views, spans: list[dict], centre, half_length: float, up, tol_px: float,
                       kappa_bounds: tuple) -> list[dict]:
    """The spans of both sides (no span length given) with each lone earth wire
    (`lone_earth_wires`) given the curvature of the earth wires across the tower
    (`across_curvature`): an earth wire strung over a suspension tower pulls the same horizontal
    tension either side, the same catenary parameter. Its own sag rests on one wire's slope over
    the span its side's phase wires measured (on ttpla-like seed 2 26.6 % deep, its stated sigma
    3 %). With its side's span length ("span_length_shared") that curvature is one slope
    (-sinh(kappa L / 2)); only the attachment (across, height) is refined, the azimuth held. Its
    covariance: the attachment's block from the image residuals, the curvature's variance the
    shared one's, the slope's through `level_slope_jacobian` with the span length's. Each such
    record gets "curvature_shared" (kappa, sigma); a wire without a shared span length is left."""
    out = list(spans)
    for i in lone_earth_wires(spans):
        f = spans[i]
        if not f.get("span_length_shared"):
            continue
        length, sigma_length = (float(v) for v in f["span_length_shared"])
        donors = [g for g in spans if not g.get("from_arm") and g["side"] != f["side"]]
        kappa, sigma = across_curvature(np.array([g["theta"][4] for g in donors]),
                                        np.array([g["cov"][4, 4] for g in donors]))
        slope = -math.sinh(0.5 * kappa * length)
        others = [g["theta"] for g in spans if g["side"] == f["side"] and g is not f]
        psi_sigma = math.sqrt(max(float(f["cov"][2, 2]), 0.0))
        r = _refined(views, {**f, "theta": with_slope(f["theta"], slope, length)}, others, centre, half_length,
                     up, tol_px, length, (0, 1), kappa_bounds, psi_sigma)
        dm_dk, dm_dl = level_slope_jacobian(kappa, length)
        cov = r["cov"].copy()
        cov[3:, :], cov[:, 3:] = 0.0, 0.0
        cov[3, 3] = (dm_dk * sigma) ** 2 + (dm_dl * sigma_length) ** 2
        cov[3, 4] = cov[4, 3] = dm_dk * sigma ** 2
        cov[4, 4] = sigma ** 2
        out[i] = {**r, "cov": cov, "span_length": None, "curvature_shared": (kappa, sigma)}
    return out


def rescan_reach(slope_own: float, slope: float, reach: float, cap: float) -> float:
    """How far [export units] setting a wire's slope from slope_own to the side's `slope` moves its
    curve at the end of its track's reach: |dm| reach, at most cap."""
    return float(min(abs(slope_own - slope) * reach, cap))


def pivoted(theta, own, pivot: float) -> np.ndarray:
    """theta [5] (a wire given its side's slope and curvature) moved up or down to pass at the height
    of its own curve own [5] at horizontal distance `pivot` (the first station its track found,
    where every photo sees it)."""
    out = np.asarray(theta, np.float64).copy()
    at = np.array([pivot])
    out[1] += float(catenary.sag_profile(at, own[3], own[4])[0] - catenary.sag_profile(at, out[3], out[4])[0])
    return out


def rescanned(views: Views, theta, centre, s_from: float, s_to: float, reach: float, step: float,
              up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX, gain: float = SETTLE_GAIN) -> np.ndarray:
    """theta [5] with its attachment (across, height) moved to the cell of a joint grid within
    +-reach (step apart) where its `curve_support` from s_from to s_to is highest, when that gains
    more than `gain` over theta's own; else theta (`scan_attachment`, joint). A wire whose own
    slope ran off (tracked onto the ground's texture or a neighbour over part of its reach) had its
    attachment extrapolated with it: given the side's slope it lies metres off, across and in
    height at once, where the alternating scan of `settled` climbs to a false maximum (on
    plad-like seed 2 a phase wire 1.3 m low and 0.8 m across: the alternating scan went to 1.6 m
    high, the joint one to the wire, support 0.05 -> 0.29)."""
    return scan_attachment(views, theta, centre, s_from, s_to, reach, step, up, tol_px, gain, joint=True)[0]


def turned(theta, psi: float, pivot: float) -> np.ndarray:
    """theta [5] with the azimuth psi, turned about the point at horizontal distance `pivot` (its
    across offset there kept: c + pivot (psi_old - psi), to first order): the middle of the track,
    where the wire's detections are, stays; turned about the attachment instead, a correction of a
    few milliradians would move the observed part by decimetres and leave the refinement a pixel
    off, in another local minimum."""
    out = np.asarray(theta, np.float64).copy()
    out[0] += pivot * (out[2] - psi)
    out[2] = psi
    return out


def side_azimuth(psis: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """The azimuth [rad] the wires of one side share, from each wire's own psis [K] and their
    variances [K] (rad^2, from the image residuals): the median weighted by 1 / variance, and its
    1-sigma, 1.4826 times the weighted median absolute deviation over sqrt of the weights' effective
    count (at least 1e-4 rad). The wires of a side run to the same next tower, parallel where its
    cross-arms are like this one's. Each wire's own azimuth rests on the few photos that see its
    far part, and a low wire's on detections over the ground or on a converging neighbour's: a
    few milliradians off, where the earth wires against the sky agree to a few tenths."""
    psis = np.asarray(psis, np.float64)
    w = 1.0 / np.maximum(np.asarray(variances, np.float64), 1e-12)
    w = np.where(np.isfinite(w), w, 0.0) + 1e-12
    med = weighted_median(psis, w)
    mad = 1.4826 * weighted_median(np.abs(psis - med), w)
    n_eff = float(w.sum() ** 2 / (w ** 2).sum())
    return med, max(mad / math.sqrt(n_eff), 1e-4)


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The weighted median of x [K] with weights w [K] > 0: the smallest x whose cumulative weight
    (x sorted) reaches half the total."""
    order = np.argsort(x, kind="stable")
    cum = np.cumsum(np.asarray(w, np.float64)[order])
    return float(np.asarray(x, np.float64)[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _enough(track: dict, min_found: int, min_share: float) -> bool:
    """Whether a track (`track_span`) found at least min_found stations and min_share of those tried
    up to the last one found: the 12 misses in a row that end every track would put a low wire
    seen to 40-76 m (11-19 stations found) under half."""
    found = len(track["found"])
    return found >= min_found and found >= min_share * max(track.get("tried_to_reach", track["tried"]), 1)


def _refined(views: Views, f: dict, others: list, centre, half_length: float, up, tol_px: float,
             span_length: float | None, free: tuple, kappa_bounds: tuple, psi_sigma: float | None = None) -> dict:
    """A kept wire's record (`find_spans`) with theta refined clear of the other wires
    (`refine_span` with others) and its image figures (`_finish`) recomputed; with psi_sigma (the
    side's shared azimuth held fixed) that azimuth's 1-sigma in the covariance."""
    reach = float(f["stations"][-1])
    theta = refine_span(views, f["theta"], centre, float(f["track"][0, 0]), reach, up, tol_px, span_length,
                        free=free, others=others, kappa_bounds=kappa_bounds)
    fit = _finish(views, theta, centre, half_length, reach, up, tol_px, span_length=span_length)
    # the image residuals' covariance of the refined curve (the curvature tied with a span length):
    # the profile's, through the track's stations a pixel apart, states the refined sag's error 3-20
    # times too wide at 640x480
    cov = np.array(fit["cov"], np.float64)
    if psi_sigma is not None:     # the azimuth the side's wires share: its own sigma, no correlation
        cov[2, :], cov[:, 2] = 0.0, 0.0
        cov[2, 2] = psi_sigma ** 2
    return {**f, **fit, "image_cov": fit["cov"], "cov": cov}


def _settled(views: Views, f: dict, kept: list[dict], centre, half_length: float, up, tol_px: float,
             kappa_bounds: tuple, reach: float, step: float) -> dict:
    """A wire's final record (`find_spans`) with its attachment scanned (`settled`) over its
    track's stations and, when it moved, the attachment (across, height) refined again clear of
    the other wires, the rest of theta held (with the span's length in use: the given one, else
    the side's shared one, else none); its covariance keeps the held parameters' rows and takes
    the attachment's block from the new image residuals. "settled": whether it moved; "support":
    its curve's `curve_support` over the track's stations, as it is returned (the scan's own when
    it did not move)."""
    s_from, s_to = float(f["track"][0, 0]), float(f["stations"][-1])
    theta, moved, support = scan_attachment(views, f["theta"], centre, s_from, s_to, reach, step, up, tol_px)
    if moved:
        others = [k["theta"] for k in kept if k is not f]
        length = f.get("span_length") or (f.get("span_length_shared") or (None,))[0]
        r = _refined(views, {**f, "theta": theta}, others, centre, half_length, up, tol_px, length, (0, 1),
                     kappa_bounds)
        cov = np.array(f["cov"], np.float64).copy()
        cov[:2, :], cov[:, :2] = 0.0, 0.0
        cov[:2, :2] = np.asarray(r["image_cov"], np.float64)[:2, :2]
        f = {**r, "cov": cov, "span_length": f.get("span_length")}
        support = curve_support(views, f["theta"], centre, station_samples(s_from, s_to), up, tol_px)
    return {**f, "settled": moved, "support": support}


def tip_of(theta, tips, drop: float, rise: float) -> int | None:
    """The index of the cross-arm tip [(across, height)] a wire (theta [5]: its attachment's across
    offset and height) hangs from: of the tips from `rise` below its attachment to `drop` above it
    (an insulator's longest), the nearest across; None when there is none. The nearest tip in the
    plane would be the wrong one: a wire hangs an insulator below its own tip, nearer the tip of
    the level beneath."""
    c, z = float(theta[0]), float(theta[1])
    near = [(abs(tc - c), k) for k, (tc, tz) in enumerate(tips) if -rise <= tz - z <= drop]
    return min(near)[1] if near else None


def one_per_tip(kept: list[dict], tips, drop: float, rise: float) -> list[dict]:
    """The records of one side with one wire per cross-arm tip (tips [(across, height)], `tip_of`):
    of the wires hung in the arms' windows ("from_arm") that hang from one tip, the one whose
    curve gathers the most support ("support", else "inlier_share"); the others as they are. A
    phase conductor hangs from its tip by one insulator string (a bundle's sub-conductors lie
    within one wire's radius and are one record already, `_distinct`); a second curve in a tip's
    window, a metre or two beside the wire, rests on the wire's own detections seen from a few
    photos."""
    hung = [tip_of(f["theta"], tips, drop, rise) if f.get("from_arm") else None for f in kept]
    best: dict[int, dict] = {}
    for k, f in zip(hung, kept):
        if k is not None and (k not in best or f.get("support", f["inlier_share"]) >
                              best[k].get("support", best[k]["inlier_share"])):
            best[k] = f
    return [f for k, f in zip(hung, kept) if k is None or best[k] is f]


def effective_photos(ok: np.ndarray) -> float:
    """How many photos a curve's support rests on: ok [N, M] bool, the (photo, station) pairs
    supporting it (`gated_support`'s); with n_i = ok[i].sum() [N], Kish's effective count
    (sum n_i)^2 / sum n_i^2: k photos supporting it equally count k, one photo's support alone 1
    however many stations it holds; 0 with no support."""
    n = np.asarray(ok, bool).reshape(len(ok), -1).sum(axis=1).astype(np.float64)
    square = float(np.sum(n * n))
    return float(n.sum()) ** 2 / square if square > 0 else 0.0


def single_view_dropped(views: Views, kept: list[dict], centre, up, tol_px: float = DEFAULT_TOL_PX,
                        min_photos: float = MIN_EFFECTIVE_PHOTOS, samples: int = 60) -> list[dict]:
    """The wires of one side (`find_spans`' records, each with "theta", "track", "stations") less
    those whose support over their track's stations (`samples` of them, as `curve_support`) rests
    on fewer than min_photos photos (`effective_photos`). Any curve in the plane through one
    photo's centre and a wire projects onto that wire's detections in it: one photo's support
    places a curve nowhere."""
    out = []
    for f in kept:
        s = track_samples(f, samples)
        _, _, ok, _ = gated_support(views, curve_points(f["theta"], centre, s, up),
                                    curve_tangents(f["theta"], centre, s, up), tol_px, with_detections=True)
        if effective_photos(ok) >= min_photos:
            out.append(f)
    return out


def borrowers_dropped(views: Views, kept: list[dict], centre, up, tol_px: float = DEFAULT_TOL_PX,
                      max_shared: float = 0.5) -> list[dict]:
    """The wires of one side (`find_spans`' records, each with "track", "theta", "psi") less those
    that only borrow the others' detections: each wire's `shared_evidence` against ALL the others;
    while the largest exceeds max_shared, that wire is dropped and the shares recomputed. A curve
    between two wires, which the photos from one side of the line see on one wire and those from
    the other side on the other, borrows from a wire kept after it (the strongest-first pass
    compares it with the wires before it only); a wire of its own keeps its own support, the
    photos along the line seeing it alone."""
    kept = list(kept)
    while len(kept) > 1:
        shares = [shared_evidence(views, f["track"], f["theta"], [k["theta"] for k in kept if k is not f], centre,
                                  f["psi"], up, tol_px) for f in kept]
        worst = int(np.argmax(shares))
        if shares[worst] <= max_shared:
            break
        kept.pop(worst)
    return kept


def combined_covariance(image_cov: np.ndarray, profile_cov: np.ndarray) -> np.ndarray:
    """theta's covariance [5, 5] of a tracked span: the across offset and the azimuth (theta[0],
    theta[2]) from the image residuals' (`_covariance`, image_cov [5, 5]), the height, slope and
    curvature (theta[1], theta[3], theta[4]) from the profile fit through the track's station
    heights (`fit_profile`, profile_cov [3, 3] of (z_a, m0, kappa)), no correlation between the
    two blocks. The profile fit is what sets the vertical parameters; the image covariance counts
    every (photo, sample) pair as an independent observation, though neighbouring samples fall on
    the same detections, and states the sag several times too precisely."""
    cov = np.zeros((5, 5))
    lateral, vertical = [0, 2], [1, 3, 4]
    cov[np.ix_(lateral, lateral)] = np.asarray(image_cov, np.float64)[np.ix_(lateral, lateral)]
    cov[np.ix_(vertical, vertical)] = np.asarray(profile_cov, np.float64)
    return cov


def seed_peaks(views: Views, centre, psi: float, station: float, seeds, window: tuple, step: float,
               up=(0.0, 0.0, 1.0), tol_px: float = DEFAULT_TOL_PX, min_support: float = DEFAULT_TRACK_SUPPORT,
               min_views: int = DEFAULT_MIN_VIEWS) -> list[tuple]:
    """The cross-section's peaks (`cross_section_peaks` at `station`) in the window around each seed
    (c, z) [S, 2] (the across offset and height of a cross-arm's tip on this side): across
    [c - w, c + w], heights [z - below, z + above] for window (w, below, above). A suspension
    insulator hangs the wire below its tip, and the wire falls on its way to the station. Returns
    [(across, height, support)], strongest first within each window, the seeds in their order."""
    w, below, above = (float(v) for v in window)
    out: list[tuple] = []
    for c, z in seeds:
        peaks = cross_section_peaks(views, centre, psi, station, (c - w, c + w), (z - below, z + above), step, up,
                                    tol_px, min_support, min_views, separation=3 * tol_px * step)
        out += [tuple(float(v) for v in p) for p in peaks]
    return out


def _finish(views: Views, theta, centre, s_min: float, reach: float, up, tol_px: float,
            samples: int = SAMPLES, span_length: float | None = None) -> dict:
    """fit_span's record of a tracked curve theta [5] observed from s_min to reach: the share of
    its projected samples within 2 tol_px of a detection, the covariance (`_covariance`; with
    span_length, the curvature tied to the slope as the track fitted it)."""
    s = np.linspace(s_min, max(reach, s_min + 1e-6), samples)
    _, dist, seen = views.offsets(curve_points(theta, centre, s, up))
    inlier = seen & (dist <= 2 * tol_px)
    cov, sigma = _covariance(theta, views, centre, s, up, inlier, span_length)
    return {"theta": np.asarray(theta, np.float64), "cov": cov, "sigma_px": sigma,
            "inlier_share": float(inlier.sum() / max(seen.sum(), 1)), "residuals": int(inlier.sum()),
            "seen": int(seen.sum()), "stations": s, "span_length": span_length}


def shared_evidence(views: Views, track: np.ndarray, theta, others: list, centre, psi: float, up,
                    tol_px: float = DEFAULT_TOL_PX) -> float:
    """The share of a tracked wire's support that lies on other wires: track [F, 4] (s, c, z,
    share: `track_span`'s stations found, across offsets along e_line(psi)); others: the thetas
    [5] of the wires kept already (each drawn from its attachment to the track's last station).
    Of the (photo, station) pairs supporting the track (`gated_support`), the share whose
    detection lies within tol_px of another wire's projected polyline in that photo. A curve
    beside a wire, that photos looking along the line cannot tell from it, is supported by that
    wire's detections only (share near 1); a wire of its own by its own (near 0)."""
    from scipy.spatial import cKDTree

    if not len(others) or not len(track):
        return 0.0
    line, across, u = line_axes(psi, up)
    base = np.asarray(centre, np.float64)
    base = base - (base @ u) * u
    pts = base[None] + track[:, 1:2] * across + track[:, 0:1] * line + track[:, 2:3] * u
    slope = catenary.sag_profile(track[:, 0] + 1e-3, theta[3], theta[4]) - catenary.sag_profile(track[:, 0], theta[3],
                                                                                                  theta[4])
    tangent = line[None] * 1e-3 + slope[:, None] * u[None]
    _, _, ok, det = gated_support(views, pts, tangent, tol_px, with_detections=True)
    if not ok.any():
        return 0.0
    s_far = np.linspace(0.0, float(track[-1, 0]) * 1.1, 600)
    drawn = [project_all(curve_points(t, centre, s_far, up), views.c2w, views.intrinsics) for t in others]
    shared = np.zeros_like(ok)
    for i in np.nonzero(ok.any(axis=1))[0]:
        poly = _polyline_in(drawn, int(i))
        d, _ = cKDTree(poly).query(det[i][ok[i]])
        # the polyline's samples are up to a few pixels apart: a detection on it is within half that
        shared[i, np.nonzero(ok[i])[0]] = d <= tol_px + 0.5 * _sample_gap(poly)
    return float(shared.sum() / ok.sum())


def _sample_gap(poly: np.ndarray) -> float:
    """The median distance between consecutive points of a polyline [P, 2] (pixels)."""
    if len(poly) < 2:
        return 0.0
    return float(np.median(np.linalg.norm(np.diff(poly, axis=0), axis=1)))


def _distinct(fits: list[dict], centre, radius: float, up, key=None) -> list[dict]:
    """One fit per wire: of fits whose curves pass within `radius` of each other (median over 20
    stations of the shorter observed reach), the first by `key` (None: `track_rank`)."""
    kept: list[dict] = []
    order = key or track_rank
    for f in sorted(fits, key=order):
        same = False
        for k in kept:
            s = np.linspace(f["stations"][0], min(f["stations"][-1], k["stations"][-1]), 20)
            gap = np.linalg.norm(curve_points(f["theta"], centre, s, up) - curve_points(k["theta"], centre, s, up),
                                 axis=1)
            same = same or float(np.median(gap)) <= radius
        if not same:
            kept.append(f)
    return kept


def track_rank(fit: dict) -> tuple:
    """The sort key of fits of one wire (`_distinct`), best first: the track that held it at the
    higher support ("track_support": the usual one before a window's lower retry, which takes
    cells the usual one rejected and on tower-small seed 2 ran 0.8-1 m beside the lowest wires,
    one station more), then the most stations found, then the most inlier offsets."""
    return -float(fit.get("track_support", 0.0)), -len(fit.get("track", ())), -fit["residuals"]


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
                "up": [float(v) for v in np.asarray(up, np.float64)], "level_span_assumed": True,
                "span_length_given": None if fit.get("span_length") is None else float(fit["span_length"]),
                "span_length_shared": None if fit.get("span_length_shared") is None else
                [float(v) for v in fit["span_length_shared"]],
                "slope_shared": None if fit.get("slope_shared") is None else [float(v) for v in fit["slope_shared"]],
                "curvature_shared": None if fit.get("curvature_shared") is None else
                [float(v) for v in fit["curvature_shared"]],
                "curvature_across": None if fit.get("curvature_across") is None else
                [float(v) for v in fit["curvature_across"]],
                "curvature_own": None if fit.get("curvature_own") is None else
                [_num(v) for v in fit["curvature_own"]],
                "next_tower": None if fit.get("next_tower") is None else
                {k: float(v) if k in ("length", "sigma", "score") else int(v) for k, v in fit["next_tower"].items()},
                "settled": bool(fit.get("settled", False)), "clamp_shared": bool(fit.get("clamp_shared", False))})
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
