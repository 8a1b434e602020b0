"""Circle-grid detection for mask-based thermal calibration targets (seed 003; Vidas et al. 2012).

A mask with circular holes in front of a warm (or cold) background appears as bright (or dark)
discs. The steps:

1. contrast normalisation (percentile stretch of 8/16-bit or float images; CLAHE as a fallback);
2. ``cv2.findCirclesGrid`` with a ``SimpleBlobDetector`` tuned for small, blurred discs, for bright
   and dark discs (``polarity="auto"``), symmetric or asymmetric, with and without clustering;
3. grid ordering: the candidate orders that keep the pattern are checked against a homography fit
   of the object points; among the valid ones the right-handed one (board frame z away from the
   camera) with corner 0 nearest the image's top-left is kept;
4. sub-pixel centres by background-subtracted, intensity-weighted moments in a circular window,
   re-centred until it converges (blur is a symmetric convolution: it leaves the centroid of a disc
   in place as long as the window holds the blurred disc);
5. perspective-bias correction: the centroid of an imaged circle is the centre of the image ellipse,
   which is not the image of the circle's centre. With a homography ``H`` (plane mm → image px)
   fitted to the centres, each circle ``(x - x0)² + (y - y0)² = R²`` is mapped to its image conic
   ``C' = H^-T C H^-1``; the ellipse centre minus ``H (x0, y0)`` is the bias, subtracted from the
   measurement (two passes).

References
----------
Vidas, S., Lakemond, R., Denman, S., Fookes, C., Sridharan, S., Wark, T. (2012). A mask-based
approach for the geometric calibration of thermal-infrared cameras. IEEE TIM 61(6), 1625-1635.
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10),
1066-1077 (perspective bias of circle centres; conic projection).
Khodaei, B. et al. (2015). 3D surface generation from aerial thermal imagery (seed 003: mask grid of
20 mm holes at 50 mm spacing, contrast enhancement, sub-pixel centres).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import ConfigError
from .detect_common import (
    CircleGridSpec,
    Detection,
    clahe_u8,
    flatten_background,
    image_size_of,
    normalize_to_u8,
    spec_of,
    to_gray_float,
)

__all__ = ["detect_circle_grid", "refine_circle_centres", "refine_circle_edges", "circle_shape_matrices", "ellipse_centre_bias", "order_grid_by_homography",
           "ellipse_candidates"]


def _blob_detector(image_area: float) -> cv2.SimpleBlobDetector:
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = 10, 245, 10
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 3
    p.filterByColor = True
    p.blobColor = 0  # dark blobs; bright discs are found on the inverted image
    p.filterByArea = True
    p.minArea = 4.0
    p.maxArea = max(50.0, 0.05 * image_area)
    p.filterByCircularity = True
    p.minCircularity = 0.5
    p.filterByConvexity = True
    p.minConvexity = 0.7
    p.filterByInertia = True
    p.minInertiaRatio = 0.1
    return cv2.SimpleBlobDetector_create(p)


def _redrawn_detector() -> cv2.SimpleBlobDetector:
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = 100, 160, 30
    p.minRepeatability = 1
    p.minDistBetweenBlobs = 1
    p.filterByColor = True
    p.blobColor = 0
    p.filterByArea = True
    p.minArea = 1.0
    p.maxArea = 1e9
    p.filterByCircularity = p.filterByConvexity = p.filterByInertia = False
    return cv2.SimpleBlobDetector_create(p)


_REDRAWN_DETECTOR = _redrawn_detector()


def _redraw_blobs(shape, keypoints) -> np.ndarray:
    """A white uint8 image with a black disc at every keypoint (centres to 1/16 px, radius >= 2 px):
    the blob detector finds exactly these, and the grid finder is not slowed by clutter."""
    img = np.full(shape[:2], 255, np.uint8)
    for k in keypoints:
        c = (int(round(k.pt[0] * 16)), int(round(k.pt[1] * 16)))
        rad = int(round(max(2.0, 0.5 * k.size) * 16))
        cv2.circle(img, c, rad, 0, -1, lineType=cv2.LINE_8, shift=4)
    return img


def _fit_h(obj_xy, img_xy):
    H, _ = cv2.findHomography(np.asarray(obj_xy, np.float64), np.asarray(img_xy, np.float64), 0)
    return H


def _right_handed(H, obj_xy, spacing_mm: float) -> bool:
    """Handedness of the grid's image: sign of the Jacobian determinant of ``H`` at the grid centre."""
    o = obj_xy.mean(axis=0)
    e = 1e-3 * spacing_mm
    q = _apply_h(H, np.array([o, o + [e, 0], o + [0, e]]))
    dx, dy = q[1] - q[0], q[2] - q[0]
    return bool(dx[0] * dy[1] - dx[1] * dy[0] > 0)


def _apply_h(H, xy):
    p = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return p[:, :2] / p[:, 2:3]


def order_grid_by_homography(points_px: np.ndarray, spec: CircleGridSpec, tol_frac: float = 0.2, *,
                             distortion_aware: bool = True):
    """Canonical order of a detected grid (row-major, as returned by OpenCV, any start corner).

    Candidates: identity, row flip, column flip, 180° rotation of the (rows, cols) index array. A
    candidate is valid when a homography object → image fits it within ``tol_frac`` of the grid
    spacing (this rejects orders that break an asymmetric grid's stagger). Among the valid ones,
    right-handed ones (image cross product of the board x and y axes > 0, image y down) are
    preferred, then the one whose point 0 is nearest the image's top-left corner. When no order fits a
    homography and ``distortion_aware``, orders that a second-order polynomial map fits within 0.15 of
    the spacing are accepted (strong lens distortion).

    Returns
    -------
    points : ndarray (N, 2) reordered, or None when no candidate fits
    rms_px : float, homography residual RMS of the chosen order
    """
    rows, cols = spec.rows, spec.columns
    obj = spec.object_points()[:, :2]
    idx = np.arange(rows * cols).reshape(rows, cols)
    cands = [idx, idx[::-1, :], idx[:, ::-1], idx[::-1, ::-1]]
    spacing_px = np.median(np.linalg.norm(np.diff(points_px.reshape(rows, cols, 2), axis=1), axis=2))
    if spec.asymmetric:
        spacing_px /= 2.0  # neighbours in a row are 2 s apart; the row pitch s is the scale here
    good = []
    for c in cands:
        p = points_px[c.ravel()]
        H = _fit_h(obj, p)
        if H is None:
            continue
        res = np.linalg.norm(_apply_h(H, obj) - p, axis=1)
        if res.max() > tol_frac * spacing_px + 0.5:
            continue
        good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p, float(np.sqrt(np.mean(res**2)))))
    if not good and distortion_aware:
        # strong barrel distortion over a grid that spans much of the frame bends its rows by more
        # than a homography allows: accept an order that a second-order map fits (a wrong order of an
        # asymmetric grid breaks its stagger by half a spacing and still fails)
        for c in cands:
            p = points_px[c.ravel()]
            rms, mx = _quad_fit_rms(obj, p)
            H = _fit_h(obj, p)
            if H is None or mx > 0.15 * spacing_px + 0.5:
                continue
            good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p, rms))
    if not good:
        return None, np.inf
    good.sort(key=lambda g: (g[0], g[1]))
    return good[0][2], good[0][3]


def refine_circle_centres(gray: np.ndarray, centres_px: np.ndarray, radius_px: np.ndarray, window_px: np.ndarray,
                          bright: bool, *, plane_background: np.ndarray | bool = True,
                          ring_px: np.ndarray | float = 2.0, iterations: int = 8, tol_px: float = 1e-3):
    """Sub-pixel disc centres by background-subtracted intensity-weighted moments.

    Parameters
    ----------
    gray : ndarray (H, W) float
        The image (any scale; float precision is kept -- no 8-bit quantisation).
    centres_px : ndarray (N, 2)
        Initial centres, OpenCV pixel convention.
    radius_px : ndarray (N,)
        Approximate disc radius (only used to size the background annulus).
    window_px : ndarray (N,)
        Radius of the circular window; must hold the blurred disc and stay clear of the neighbours.
    bright : bool
        Discs brighter than the background.
    ring_px : float or ndarray (N,)
        Width of the background annulus outside the window.
    plane_background : bool or ndarray (N,) of bool
        Background below each disc from a robust plane through the annulus around the window
        (removes vignetting / uneven mask temperature gradients, which a constant would turn into
        a centroid shift: 0.053 → 0.025 px RMS on a 320x240 view with 3 % vignetting); False: the
        annulus median (less noise, and safe when a neighbour's blurred disc reaches the annulus).

    Returns
    -------
    centres : ndarray (N, 2) float64
    ok : ndarray (N,) bool -- False when the window left the image or held no signal.
    """
    h, w = gray.shape
    c = np.asarray(centres_px, np.float64).copy()
    ok = np.ones(len(c), bool)
    sign = 1.0 if bright else -1.0
    use_plane = np.broadcast_to(np.asarray(plane_background, bool), (len(c),))
    ring_w = np.broadcast_to(np.asarray(ring_px, float), (len(c),))
    for k in range(len(c)):
        rw = float(window_px[k])
        ro = rw + float(ring_w[k])
        for _ in range(iterations):
            x0, y0 = c[k]
            xa, xb = int(np.floor(x0 - ro - 1)), int(np.ceil(x0 + ro + 1))
            ya, yb = int(np.floor(y0 - ro - 1)), int(np.ceil(y0 + ro + 1))
            if xa < 0 or ya < 0 or xb >= w or yb >= h:
                ok[k] = False
                break
            patch = gray[ya : yb + 1, xa : xb + 1].astype(np.float64)
            yy, xx = np.mgrid[ya : yb + 1, xa : xb + 1]
            rr = np.hypot(xx - x0, yy - y0)
            inner = rr <= rw
            ring = (rr > rw) & (rr <= ro)
            # background: a plane through the annulus (vignetting and uneven mask temperature make
            # a gradient across the window, which a constant would turn into a centroid shift)
            # fitted robustly: ring pixels touched by a neighbour's blurred disc are rejected
            if use_plane[k]:
                coef = _robust_plane(xx[ring] - x0, yy[ring] - y0, patch[ring])
                bg = coef[0] + coef[1] * (xx[inner] - x0) + coef[2] * (yy[inner] - y0)
            else:
                bg = np.median(patch[ring])
            wgt = sign * (patch[inner] - bg)
            m0 = wgt.sum()
            if not np.isfinite(m0) or m0 <= 0:
                ok[k] = False
                break
            new = np.array([np.sum(wgt * xx[inner]) / m0, np.sum(wgt * yy[inner]) / m0])
            step = np.linalg.norm(new - c[k])
            c[k] = new
            if step < tol_px:
                break
    return c, ok


def circle_shape_matrices(H: np.ndarray, centres_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N, 2, 2) matrices ``Q`` of the image ellipses of circles by a homography: the outline is
    ``(x - u0)ᵀ Q (x - u0) = 1``, so the radius along a unit direction ``u`` is ``1 / sqrt(uᵀ Q u)``."""
    Hi = np.linalg.inv(H)
    out = np.empty((len(centres_mm), 2, 2))
    for k, (x0, y0) in enumerate(np.asarray(centres_mm, float)):
        C = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [-x0, -y0, x0 * x0 + y0 * y0 - radius_mm**2]])
        Ci = Hi.T @ C @ Hi
        A, b, f = Ci[:2, :2], Ci[:2, 2], Ci[2, 2]
        u0 = np.linalg.solve(A, -b)
        out[k] = A / (u0 @ A @ u0 - f)
    return out


def refine_circle_edges(gray: np.ndarray, centres_px: np.ndarray, shape_q: np.ndarray, bright: bool, *,
                        n_rays: int = 180, blur_px: float = 2.0, iterations: int = 8, tol_px: float = 1e-3,
                        level_slope: bool = True):
    """Sub-pixel disc centres from the disc's outline: the area centroid of the polygon of sub-pixel
    edge points (each the mid-level crossing of a ray's profile between its own local disc and
    background levels).

    Along ``n_rays`` rays from the current centre the image is sampled (bicubic, 0.2 px steps); on
    each ray the edge is the steepest step of the right sign near the expected outline, the disc level
    a straight line through the profile inside it (``0.45 e .. e - blur_px``) and the background a line
    through the profile just outside (``e + blur_px`` onwards, ``max(3 px, 0.3 e)`` long: clear of the
    neighbouring discs of a grid with gap ≥ the radius), both evaluated at the edge (``level_slope``;
    False: their medians), and the edge point the crossing of their mean (linear interpolation). The
    lines follow a background slope along the ray: under an 8 K hot spot on a 1 K contrast they cut the
    centre error from 0.14 to 0.028 px RMS (``tests/test_detect_circles_lowcontrast.py`` views).
    A blur by a symmetric PSF puts the mid-level crossing of a straight step on the step, and the
    per-ray levels follow a non-uniform mask or disc temperature (which bias a moment centroid:
    ~0.05 px for a 0.3 K / 100 mm gradient on a 14 K contrast). Edge points off a least-squares
    conic through them by > max(0.25 px, 4 MAD) (a ray that crossed a defect or the frame border)
    are replaced by that conic's point. The area centroid of the outline is what
    :func:`ellipse_centre_bias` / :func:`~thermogrammetry.calibration.circle_bias.circle_centroid_bias`
    relate to the projected circle centre; the rays are re-cast from the new centre until it settles.

    Parameters
    ----------
    gray : ndarray (H, W) float
    centres_px : ndarray (N, 2) initial centres (inside each disc; a few px off is fine)
    shape_q : ndarray (N, 2, 2) expected outline ``(x - c)ᵀ Q (x - c) = 1`` (e.g. :func:`circle_shape_matrices`);
        the edge is searched within 0.6-1.45 of it along each ray
    bright : bool -- discs brighter than their surround
    n_rays : rays per disc
    blur_px : half-width of the blurred edge kept out of the level estimates (px; ~2.5 PSF σ)
    level_slope : disc and background levels by lines extrapolated to the edge (default) or by medians

    Returns
    -------
    centres : ndarray (N, 2)
    ok : ndarray (N,) bool -- False when fewer than 60 % of the rays gave an edge (then the input centre
        is returned)
    outlines : ndarray (N, n_rays, 2) -- the edge polygon of the last round (NaN where not ok), px
    quality : ndarray (N, 2) -- fraction of the rays whose edge point was measured (not filled in by
        the conic), and the RMS departure of those points from the conic (px; ~0.01-0.05 for a whole
        sharp disc, larger for an outline with a straight piece, e.g. a disc cut by an occluder)
    """
    g = np.ascontiguousarray(gray, np.float32)
    h, w = g.shape
    c = np.asarray(centres_px, np.float64).copy()
    ok = np.zeros(len(c), bool)
    outlines = np.full((len(c), n_rays, 2), np.nan)
    measured = np.full((len(c), 2), np.nan)
    ang = 2.0 * np.pi * np.arange(n_rays) / n_rays
    dirs = np.column_stack([np.cos(ang), np.sin(ang)])
    sgn = -1.0 if bright else 1.0  # profile rises outward for a dark disc
    for k in range(len(c)):
        Q = np.asarray(shape_q[k], float)
        rdir = 1.0 / np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", dirs, Q, dirs), 1e-12))  # expected radius per ray
        start = c[k].copy()
        moved = np.inf
        for _ in range(iterations):
            step = 0.2
            s_max = 1.45 * rdir + blur_px + np.maximum(3.0, 0.3 * 1.45 * rdir)
            ns = int(np.ceil(s_max.max() / step)) + 1
            s = step * np.arange(ns)
            P = start[None, None, :] + s[None, :, None] * dirs[:, None, :]  # (rays, ns, 2)
            mx, my = P[..., 0].astype(np.float32), P[..., 1].astype(np.float32)
            prof = cv2.remap(g, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            inside_img = (P[..., 0] >= 1) & (P[..., 0] <= w - 2) & (P[..., 1] >= 1) & (P[..., 1] <= h - 2)
            prof = np.where(inside_img, prof, np.nan).astype(np.float64)
            edge = np.full(n_rays, np.nan)
            for j in range(n_rays):
                p = prof[j]
                # a ray that leaves the frame keeps its samples up to the border (a disc near the
                # border has a short background segment there)
                fin = np.flatnonzero(~np.isfinite(p))
                last = (fin[0] if fin.size else ns) - 1
                lo_i, hi_i = int(0.6 * rdir[j] / step), min(int(1.45 * rdir[j] / step) + 1, ns - 2, last - 1)
                d = sgn * (p[lo_i + 1:hi_i + 1] - p[lo_i - 1:hi_i - 1])
                if d.size == 0 or not np.all(np.isfinite(d)):
                    continue
                e_i = lo_i + int(np.argmax(d))
                e = s[e_i]
                a_in, b_in = int(0.45 * e / step), int((e - blur_px) / step)
                a_out = int(np.ceil((e + blur_px) / step))
                b_out = min(a_out + int(max(3.0, 0.3 * e) / step), ns - 1, last)
                if b_in - a_in < 3 or b_out - a_out < 3:
                    continue
                inner, outer = p[a_in:b_in + 1], p[a_out:b_out + 1]
                if not (np.all(np.isfinite(inner)) and np.all(np.isfinite(outer))):
                    continue
                if level_slope:
                    # levels extrapolated to the edge along the ray: a background slope (a hot spot,
                    # vignetting) otherwise moves the mid level by slope x the segment's offset
                    si, so = s[a_in:b_in + 1] - e, s[a_out:b_out + 1] - e
                    li = float(np.polyval(np.polyfit(si, inner, 1), 0.0))
                    lo_ = float(np.polyval(np.polyfit(so, outer, 1), 0.0))
                else:
                    li, lo_ = np.median(inner), np.median(outer)
                if sgn * (lo_ - li) <= 0:
                    continue
                mid = 0.5 * (li + lo_)
                seg = sgn * (p[b_in:a_out + 1] - mid)  # negative inside, positive outside
                cross = np.flatnonzero((seg[:-1] < 0) & (seg[1:] >= 0))
                if cross.size != 1:
                    continue
                i0 = cross[0]
                f = seg[i0] / (seg[i0] - seg[i0 + 1])
                edge[j] = s[b_in + i0] + f * step
            good = np.isfinite(edge)
            if good.sum() < 0.6 * n_rays:
                break
            pts = start + edge[:, None] * dirs
            # robust conic (x^2, xy, y^2, x, y, 1) through the edge points: replace outliers / gaps by it
            q = pts - start
            for _r in range(2):
                A = np.column_stack([q[good, 0] ** 2, q[good, 0] * q[good, 1], q[good, 1] ** 2, q[good, 0], q[good, 1]])
                coef, *_ = np.linalg.lstsq(A, np.ones(int(good.sum())), rcond=None)
                # radius of the conic along each ray: a r^2 + b r = 1
                a2 = coef[0] * dirs[:, 0] ** 2 + coef[1] * dirs[:, 0] * dirs[:, 1] + coef[2] * dirs[:, 1] ** 2
                b1 = coef[3] * dirs[:, 0] + coef[4] * dirs[:, 1]
                with np.errstate(invalid="ignore", divide="ignore"):
                    rc = (-b1 + np.sqrt(b1 * b1 + 4 * a2)) / (2 * a2)
                res = edge - rc
                mad = 1.4826 * np.median(np.abs(res[good] - np.median(res[good])))
                good = good & (np.abs(res) <= max(0.25, 4.0 * mad))
            if good.sum() < 0.6 * n_rays or not np.all(np.isfinite(rc)):
                break
            r_all = np.where(good, edge, rc)
            v = start + r_all[:, None] * dirs
            x, y = v[:, 0], v[:, 1]
            x1, y1 = np.roll(x, -1), np.roll(y, -1)
            cr = x * y1 - x1 * y
            area = 0.5 * cr.sum()
            new = np.array([((x + x1) * cr).sum(), ((y + y1) * cr).sum()]) / (6.0 * area)
            moved = np.linalg.norm(new - start)
            start = new
            outlines[k] = v
            measured[k] = good.mean(), float(np.sqrt(np.mean(res[good] ** 2)))
            if moved < tol_px:
                ok[k] = True
                break
        else:
            # not settled: a start far off the disc's centre gives a lopsided outline; accept only a
            # last step below 0.05 px
            ok[k] = bool(moved < 0.05)
        if ok[k]:
            c[k] = start
    return c, ok, outlines, measured


def _robust_plane(x: np.ndarray, y: np.ndarray, v: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Plane ``v ~ c0 + c1 x + c2 y`` by least squares with 3-sigma (MAD) rejection; returns (3,)."""
    keep = np.ones(v.size, bool)
    coef = np.array([np.median(v), 0.0, 0.0])
    for _ in range(rounds):
        if keep.sum() < 6:
            break
        A = np.column_stack([np.ones(int(keep.sum())), x[keep], y[keep]])
        coef, *_ = np.linalg.lstsq(A, v[keep], rcond=None)
        res = v - (coef[0] + coef[1] * x + coef[2] * y)
        mad = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
        new = np.abs(res) <= 3.0 * max(mad, 1e-12)
        if np.array_equal(new, keep):
            break
        keep = new
    return coef


def ellipse_centre_bias(H: np.ndarray, centres_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """Perspective bias of imaged circle centres: centre of the image ellipse minus image of the centre.

    Parameters
    ----------
    H : ndarray (3, 3)
        Homography plane (mm) → image (px).
    centres_mm : ndarray (N, 2)
    radius_mm : float

    Returns
    -------
    bias_px : ndarray (N, 2)

    Notes
    -----
    Circle conic ``C = [[1, 0, -x0], [0, 1, -y0], [-x0, -y0, x0² + y0² - R²]]``; image conic
    ``C' = H^-T C H^-1``; the centre of conic ``[[a, b, d], [b, c, e], [d, e, f]]`` solves
    ``[[a, b], [b, c]] u = -[d, e]`` (Heikkilä 2000).
    """
    Hi = np.linalg.inv(H)
    out = np.empty((len(centres_mm), 2))
    for k, (x0, y0) in enumerate(np.asarray(centres_mm, float)):
        C = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [-x0, -y0, x0 * x0 + y0 * y0 - radius_mm**2]])
        Ci = Hi.T @ C @ Hi
        u = np.linalg.solve(Ci[:2, :2], -Ci[:2, 2])
        p = H @ np.array([x0, y0, 1.0])
        out[k] = u - p[:2] / p[2]
    return out


def ellipse_candidates(gray: np.ndarray, bright: bool, block_sizes=(15, 31, 61, 121, 241)) -> np.ndarray:
    """Disc candidates from adaptive thresholds over several scales, each contour fitted by an ellipse.

    A contour is kept when it fills its fitted ellipse (area ratio 0.85-1.1), is convex (area / hull
    area > 0.92) and not too elongated (axis ratio > 0.25). Detections of the same disc at several
    scales are merged (centres closer than a quarter of the minor axis); ``count`` says at how many
    scales a disc was found (noise specks are found at one).

    Returns
    -------
    ndarray (K, 8): x, y (px, OpenCV convention), major, minor axis (px), area (px²), count, angle of
    the major axis (radians, from image x towards image y), and the contour's largest relative
    departure from the fitted ellipse (``max |ρ - 1|``, ρ the contour point's normalised elliptic
    radius: ~0.03 for a whole blurred disc, larger for a disc cut by an occluder's edge).
    """
    u8 = normalize_to_u8(gray)
    img = cv2.GaussianBlur(u8 if bright else 255 - u8, (0, 0), 1.0)
    h, w = img.shape
    raw = []
    for bs in block_sizes:
        if bs >= min(h, w):
            continue
        for c_off in (-2, -8):
            bw = cv2.adaptiveThreshold(img, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, bs, c_off)
            cs, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
            for c in cs:
                if len(c) < 8:
                    continue
                a = cv2.contourArea(c)
                if a < 12 or a > 0.25 * h * w:
                    continue
                (cx, cy), (ma, mi), _ang = cv2.fitEllipse(c)
                ea = np.pi * ma * mi / 4.0
                if ea <= 0 or min(ma, mi) < 3 or min(ma, mi) / max(ma, mi) < 0.25 or not 0.85 < a / ea < 1.1:
                    continue
                if a / max(cv2.contourArea(cv2.convexHull(c)), 1e-9) < 0.92:
                    continue
                ang = np.deg2rad(_ang) + (0.0 if ma >= mi else 0.5 * np.pi)
                q = c.reshape(-1, 2).astype(np.float64) - (cx, cy)
                ca, sa = np.cos(ang), np.sin(ang)
                u, v = q[:, 0] * ca + q[:, 1] * sa, -q[:, 0] * sa + q[:, 1] * ca
                # contour pixels are the outermost pixel centres inside the threshold: their radius is
                # ~half a pixel short of the fitted ellipse's; compare with the fitted axes
                rho = np.hypot(u / (0.5 * max(ma, mi)), v / (0.5 * min(ma, mi)))
                raw.append((cx, cy, max(ma, mi), min(ma, mi), a, ang % np.pi, float(np.abs(rho - 1.0).max())))
    if not raw:
        return np.zeros((0, 8))
    raw = np.array(raw)
    order = np.argsort(-raw[:, 4])
    used = np.zeros(len(raw), bool)
    out = []
    for i in order:
        if used[i]:
            continue
        d = np.hypot(raw[:, 0] - raw[i, 0], raw[:, 1] - raw[i, 1])
        grp = (~used) & (d < 0.25 * raw[i, 3]) & (raw[:, 4] > 0.5 * raw[i, 4])
        used |= grp
        g = raw[grp]
        med = g[np.argsort(g[:, 4])[len(g) // 2]]
        out.append((*med[:5], float(len(g)), med[5], med[6]))
    return np.array(out)


def _quad_fit_rms(obj, pts):
    """RMS and max residual of a second-order polynomial map object -> image (distortion-aware
    stand-in for a homography when checking an ordering)."""
    x, y = obj[:, 0] / np.abs(obj).max(), obj[:, 1] / max(np.abs(obj).max(), 1e-12)
    A = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    if len(obj) <= A.shape[1]:
        A = A[:, :3]
    coef, *_ = np.linalg.lstsq(A, pts, rcond=None)
    r = np.linalg.norm(A @ coef - pts, axis=1)
    return float(np.sqrt(np.mean(r * r))), float(r.max())


def _grid_from_ellipses(gray, spec, bright, c=None):
    """Grid of ``spec`` from ellipse candidates: the N candidates of the most common size that are
    found at several scales, ordered by ``cv2.findCirclesGrid`` on a clean redrawn image and
    checked with a second-order (distortion-aware) map. Returns (points (N, 2) or None, why).
    ``c``: the :func:`ellipse_candidates` of ``gray`` when already computed."""
    if c is None:
        c = ellipse_candidates(gray, bright)
    n = spec.n_points
    if len(c) < n:
        return None, f"{len(c)} ellipse candidates < {n}"
    # size consistency: grid discs are similar (perspective changes their area by < ~4x); pick the
    # largest group in log-area within a factor 4, preferring discs found at several scales
    grp = _size_group(c, n)
    if len(grp) < n:
        return None, f"only {len(grp)} ellipses of a consistent size"
    grp = grp[np.argsort(-c[grp, 5] - 1e-6 * c[grp, 4])][: max(n + 6, int(1.5 * n))]
    cand = c[grp]
    kind = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    obj = spec.object_points()[:, :2]
    idx = np.arange(spec.rows * spec.columns).reshape(spec.rows, spec.columns)
    scale = 4
    for m in sorted({n, len(cand)}):
        sub = cand[:m]
        clean = np.full((gray.shape[0] * 1, gray.shape[1] * 1), 255, np.uint8)
        rad = max(2.0, 0.25 * float(np.median(sub[:, 3])))
        for x, y in sub[:, :2]:
            cv2.circle(clean, (int(round(x * 16)), int(round(y * 16))), int(round(rad * 16)), 0, -1, cv2.LINE_8, shift=4)
        for flags in (kind, kind | cv2.CALIB_CB_CLUSTERING):
            ok, centres = cv2.findCirclesGrid(clean, spec.pattern_size, flags=flags, blobDetector=_REDRAWN_DETECTOR)
            if not ok or centres is None:
                continue
            pts = centres.reshape(-1, 2).astype(np.float64)
            # snap to the candidates (the redrawn dots are rounded to 1/16 px)
            d = np.linalg.norm(pts[:, None] - sub[None, :, :2], axis=2)
            pts = sub[np.argmin(d, axis=1), :2]
            spacing = np.median(np.linalg.norm(np.diff(pts.reshape(spec.rows, spec.columns, 2), axis=1), axis=2))
            good = []
            for cnd in (idx, idx[::-1, :], idx[:, ::-1], idx[::-1, ::-1]):
                p = pts[cnd.ravel()]
                rms, mx = _quad_fit_rms(obj, p)
                if mx > 0.15 * spacing + 0.5:
                    continue
                H = _fit_h(obj, p)
                if H is None:
                    continue
                good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p))
            if good:
                good.sort(key=lambda g: (g[0], g[1]))
                if _polarity_ok(gray, good[0][2], cand, bright):
                    return good[0][2], ""
    if not spec.asymmetric:
        pts = _grid_from_hull(cand[:n, :2], spec)
        if pts is not None and _polarity_ok(gray, pts, cand, bright):
            return pts, ""
    return None, f"{len(cand)} ellipses of a consistent size, no {spec.pattern_size[0]}x{spec.pattern_size[1]} grid among them"


def _polarity_ok(gray, pts, cand, bright) -> bool:
    """Every disc is brighter (``bright``) or darker than a ring just outside it (half a disc
    radius beyond the fitted ellipse): rejects grids of the gaps between discs of the other polarity."""
    smooth = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), 1.0)
    h, w = smooth.shape
    rad = 0.5 * float(np.median(cand[:, 2]))
    a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    sign = 1.0 if bright else -1.0
    good = 0
    for x, y in pts:
        ring = np.column_stack([x + 1.5 * rad * np.cos(a), y + 1.5 * rad * np.sin(a)])
        ring = ring[(ring[:, 0] >= 0) & (ring[:, 0] <= w - 1) & (ring[:, 1] >= 0) & (ring[:, 1] <= h - 1)]
        if not len(ring) or not (0 <= x <= w - 1 and 0 <= y <= h - 1):
            continue
        inner = smooth[int(round(y)), int(round(x))]
        outer = np.median(smooth[np.rint(ring[:, 1]).astype(int), np.rint(ring[:, 0]).astype(int)])
        good += sign * (inner - outer) > 0
    return good >= 0.9 * len(pts)


def _grid_from_hull(p: np.ndarray, spec) -> np.ndarray | None:
    """Order exactly N candidates of a symmetric grid from their convex hull: the four sharpest hull
    turns are the grid corners, the hull counts between them tell rows from columns; a homography
    of the corners predicts the rest, assigned to the nearest candidates and checked with a
    second-order map (distortion bends the rows, so no global homography check)."""
    cols, rows = spec.columns, spec.rows
    if len(p) != cols * rows:
        return None
    hull = cv2.convexHull(p.astype(np.float32), returnPoints=False).ravel()
    if len(hull) < 4:
        return None
    hp = p[hull]
    v_in = hp - np.roll(hp, 1, axis=0)
    v_out = np.roll(hp, -1, axis=0) - hp
    ang = np.abs(np.arctan2(v_in[:, 0] * v_out[:, 1] - v_in[:, 1] * v_out[:, 0], np.sum(v_in * v_out, axis=1)))
    corners = np.sort(np.argsort(-ang)[:4])
    gaps = np.diff(np.r_[corners, corners[0] + len(hull)]) - 1  # hull points between successive corners
    obj = spec.object_points()[:, :2]
    oc = {0: obj[0], 1: obj[cols - 1], 2: obj[-1], 3: obj[(rows - 1) * cols]}  # grid corners, cyclic order
    best = None
    for shift in range(4):
        for direction in (1, -1):
            seq = [corners[(shift + direction * k) % 4] for k in range(4)]
            img_c = hp[seq]
            H = _fit_h(np.array([oc[k] for k in range(4)]), img_c)
            if H is None:
                continue
            pred = _apply_h(H, obj)
            d = np.linalg.norm(pred[:, None] - p[None], axis=2)
            a = np.argmin(d, axis=1)
            if len(set(a.tolist())) != len(p):
                continue
            q = p[a]
            rms, mx = _quad_fit_rms(obj, q)
            if best is None or rms < best[0]:
                best = (rms, mx, q)
    if best is None:
        return None
    q = best[2]
    spacing = np.median(np.linalg.norm(np.diff(q.reshape(rows, cols, 2), axis=1), axis=2))
    if best[1] > 0.15 * spacing + 0.5:
        return None
    # canonical choice among the grid's symmetric orderings (right-handed, corner 0 nearest top-left)
    idx = np.arange(rows * cols).reshape(rows, cols)
    good = []
    for cnd in (idx, idx[::-1, :], idx[:, ::-1], idx[::-1, ::-1]):
        r = q[cnd.ravel()]
        H = _fit_h(obj, r)
        o = obj.mean(axis=0)
        e = 1e-3 * spec.spacing_mm
        z = _apply_h(H, np.array([o, o + [e, 0], o + [0, e]]))
        dx, dy = z[1] - z[0], z[2] - z[0]
        good.append((not (dx[0] * dy[1] - dx[1] * dy[0] > 0), float(r[0].sum()), r))
    good.sort(key=lambda g: (g[0], g[1]))
    return good[0][2]


def detect_circle_grid(image, spec: CircleGridSpec, image_id: str = "", *, polarity: str = "auto",
                       refine: str = "edges", perspective_correction: bool = True, partial: bool = True,
                       min_partial_points: int = 6, flatfield: bool = True) -> Detection:
    """Find a symmetric or asymmetric circle grid and measure sub-pixel centres.

    Parameters
    ----------
    image : array_like (H, W) or (H, W, 1|3|4), uint8 / uint16 / float
    spec : CircleGridSpec
    image_id : str
    polarity : {"auto", "bright", "dark"}
        Discs brighter (holes over a warm background) or darker than their surround; "auto" tries
        bright first, then dark.
    refine : {"edges", "moments", "none"}
        "moments": :func:`refine_circle_centres` on the float image; "edges" (default): those, then the
        area centroid of each disc's sub-pixel outline (:func:`refine_circle_edges`; needs
        ``spec.diameter_mm``, otherwise the moment centres are kept): 0.008 px RMS against the exact
        centroid on sharp 640 x 512 views of 60 mm circles under ~80 px barrel distortion and 55° tilt,
        where the moment window gave 0.09 px (a temperature gradient across the discs, windows too
        small for strongly foreshortened discs); "none": blob-detector centres.
    perspective_correction : bool
        Remove the perspective bias (:func:`ellipse_centre_bias`); needs ``spec.diameter_mm``.
    partial : bool
        When no pass finds the whole grid, accept part of it (circles outside the frame, cut by its
        border or hidden): the ellipse candidates of a consistent size are put on a lattice by
        growing it from neighbour to neighbour (:func:`_grow_lattice`), the patch is placed on the
        target (:func:`_place_on_target`) and checked with a second-order map and the polarity
        test; circles whose measuring window leaves the frame are dropped. A symmetric patch may fit
        the target at several places (a 3x3 patch of a 4x3 grid at two); they differ by a rigid
        motion of the target plane, which the view's own pose absorbs, so the calibration is the
        same whichever is taken (not so for a rig with a shared target pose: keep the views whole
        there). ``extra["partial"]`` says so and ``extra["placements"]`` counts the valid ones.
    min_partial_points : int
        Fewest circles of a partial grid (default 6, the calibration's minimum per image).
    flatfield : bool
        When the passes on the stretched image fail, run them again on the image flattened by
        :func:`~thermogrammetry.calibration.detect_common.flatten_background` (σ = 1/16 of the larger
        side): low-contrast masks under a heater's hot spot or vignetting ("bright-flatfield",
        "bright-flatfield-ellipses", "...-flatfield-partial"). Centres are measured on the raw image.

    Returns
    -------
    Detection
        ``points_px`` (K, 2) in canonical order (:func:`order_grid_by_homography`), ``object_ids``
        (K,): ``arange(N)`` for a whole grid, the found circles' ids for a partial one.

    Notes
    -----
    A :class:`~thermogrammetry.targets.CodedCircleGridTarget` with marks goes through
    :func:`~thermogrammetry.calibration.detect_circle_marks.detect_coded_circle_grid`: the ring-coded
    marks are read, their rings painted over, this detector runs on the plain grid, and the decoded
    marks fix the numbering (the 180° ambiguity of a whole symmetric grid, the placement of a partial
    one); ``extra["coded_marks"]`` records which marks were decoded.
    """
    spec = spec_of(spec, CircleGridSpec, "CircleGridSpec")
    if getattr(spec, "marks", ()):
        # ring-coded marks (seed 003): read them, paint their rings over, number the grid by them
        from .detect_circle_marks import detect_coded_circle_grid

        return detect_coded_circle_grid(image, spec, image_id, polarity=polarity, refine=refine,
                                        perspective_correction=perspective_correction, partial=partial,
                                        min_partial_points=min_partial_points, flatfield=flatfield)
    if polarity not in ("auto", "bright", "dark"):
        raise ConfigError(f"polarity: expected 'auto', 'bright' or 'dark', got {polarity!r}")
    if refine not in ("edges", "moments", "none"):
        raise ConfigError(f"refine: expected 'edges', 'moments' or 'none', got {refine!r}")
    if int(min_partial_points) < 4:
        raise ConfigError(f"min_partial_points: expected >= 4 circles, got {min_partial_points!r}")
    gray = to_gray_float(image, f"image {image_id!r}" if image_id else "image")
    size = image_size_of(gray)
    u8 = normalize_to_u8(gray)
    area = float(gray.size)
    blob = _blob_detector(area)
    kind = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    pattern = spec.pattern_size
    pols = ["bright", "dark"] if polarity == "auto" else [polarity]
    small = min(gray.shape) < 300

    tried = []

    def blob_pass(pol, vname, img, scale):
        """The blob detector + cv2.findCirclesGrid on one 8-bit variant; the ordered grid or None."""
        det = blob if scale == 1 else _blob_detector(area * scale * scale)
        # findCirclesGrid's grid search grows steeply with the number of blobs (18 s for 800 noise
        # blobs in a 160x120 frame): detect the blobs here, keep the largest few times N (grid
        # discs are larger than noise specks) and hand findCirclesGrid a clean redrawn image
        # a light blur first: noise specks otherwise make thousands of contours (2.5 s per call
        # on a 640x480 noise frame, 0.2 s after the blur); the centres are refined on the raw image
        keypoints = det.detect(cv2.GaussianBlur(img, (0, 0), 1.0 * scale))
        if len(keypoints) < spec.n_points:
            tried.append(f"{pol}-{vname} ({len(keypoints)} blobs < {spec.n_points})")
            return None, ""
        cap = max(3 * spec.n_points, spec.n_points + 30)
        keypoints = sorted(keypoints, key=lambda k: -k.size)[:cap]
        clean = _redraw_blobs(img.shape, keypoints)
        for flags, fname in ((kind, ""), (kind | cv2.CALIB_CB_CLUSTERING, "+clustering")):
            ok, centres = cv2.findCirclesGrid(clean, pattern, flags=flags, blobDetector=_REDRAWN_DETECTOR)
            name = f"{pol}-{vname}{fname}"
            if not ok or centres is None:
                tried.append(name)
                continue
            pts = centres.reshape(-1, 2).astype(np.float64)
            if scale != 1:
                pts = (pts + 0.5) / scale - 0.5
            ordered, rms = order_grid_by_homography(pts, spec)
            if ordered is None:
                tried.append(f"{name} (rejected: grid fits neither a homography nor a second-order map)")
                continue
            return ordered, name
        return None, ""

    for pol in pols:
        base = 255 - u8 if pol == "bright" else u8  # the blob detector looks for dark blobs
        variants = [("stretch", base, 1), ("clahe", clahe_u8(base), 1)]
        if small:
            variants.append(("upsampled", cv2.resize(base, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC), 3))
        for vname, img, scale in variants:
            ordered, name = blob_pass(pol, vname, img, scale)
            if ordered is not None:
                return _finish(gray, ordered, spec, image_id, size, name, tried, pol == "bright", refine,
                               perspective_correction)
    # large discs under strong distortion / perspective: ellipse candidates over several scales of
    # adaptive threshold, grid topology from the candidates' neighbour structure, distortion-aware check
    cands = {}
    for pol in pols:
        cands[pol] = ellipse_candidates(gray, pol == "bright")
        pts, why = _grid_from_ellipses(gray, spec, pol == "bright", cands[pol])
        name = f"{pol}-ellipses"
        if pts is not None:
            return _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine, perspective_correction)
        tried.append(f"{name} ({why})")
    # low contrast under a hot spot / vignetting: the same passes on the image flattened by a wide
    # blur (flatten_background, σ = 1/16 of the larger side: it must span more than a circle and
    # its gap; a chessboard's 1/64-1/32 leaves the discs of a sparse grid half-flattened). Run only
    # when everything above failed, so a view found before keeps its centres; the centres are
    # measured on the raw image (its plane background takes the smooth remainder of the hot spot)
    ff_imgs = []
    if flatfield:
        for frac, tag in ((16.0, "flatfield"), (32.0, "flatfield-narrow")):
            ff_u8 = flatten_background(gray, max(gray.shape) / frac)
            ff_img = ff_u8.astype(np.float32)
            ff_imgs.append((tag, ff_img))
            for pol in pols:
                ordered, name = blob_pass(pol, tag, 255 - ff_u8 if pol == "bright" else ff_u8, 1)
                if ordered is not None:
                    return _finish(gray, ordered, spec, image_id, size, name, tried, pol == "bright", refine,
                                   perspective_correction)
            for pol in pols:
                # one row per disc: a flattened disc gives nested contours at many thresholds
                cands[f"{tag}-{pol}"] = _one_per_disc(ellipse_candidates(ff_img, pol == "bright"))
                pts, why = _grid_from_ellipses(ff_img, spec, pol == "bright", cands[f"{tag}-{pol}"])
                name = f"{pol}-{tag}-ellipses"
                if pts is not None:
                    return _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine,
                                   perspective_correction)
                tried.append(f"{name} ({why})")
    # part of the grid: outside the frame, cut by its border or hidden
    if partial:
        for tag, img in [("", gray)] + ff_imgs:
            for pol in pols:
                key = f"{tag}-{pol}" if tag else pol
                pts, ids, n_place, why = _partial_grid(img, spec, pol == "bright", cands[key], int(min_partial_points))
                name = f"{pol}-{tag + '-' if tag else ''}partial"
                if pts is not None and len(ids) == spec.n_points:
                    # every circle: a whole grid after all, in the canonical order of the other passes
                    full = np.empty_like(pts)
                    full[ids] = pts
                    ordered, _ = order_grid_by_homography(full, spec, tol_frac=0.5)
                    return _finish(gray, full if ordered is None else ordered, spec, image_id, size,
                                   name.replace("partial", "lattice"), tried, pol == "bright", refine,
                                   perspective_correction)
                if pts is not None:
                    det = _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine,
                                  perspective_correction, ids=ids, min_points=int(min_partial_points),
                                  n_placements=n_place)
                    if det.found:
                        return det
                    why = det.reason
                tried.append(f"{name} ({why})")
    return Detection.failure(image_id, f"no {pattern[0]}x{pattern[1]} "
                             f"{'asymmetric ' if spec.asymmetric else ''}circle grid found (tried: {', '.join(tried)})", size)


def _finish(gray, pts, spec, image_id, size, name, tried, bright, refine, perspective_correction, *, ids=None,
            min_points=None, n_placements=1) -> Detection:
    """Sub-pixel centres, bias correction and the Detection of grid points ``pts`` (ids: ``arange(N)``
    for a whole grid; for a partial one (``ids`` given) circles whose window leaves the image or whose
    centre is unstable are dropped, and fewer than ``min_points`` left is a failure)."""
    partial = ids is not None
    ids = np.arange(spec.n_points, dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
    obj = spec.object_points()[ids, :2]
    H = _fit_h(obj, pts)
    # nearest-neighbour distance in px at every circle, from the homography
    nn_mm = spec.spacing_mm * (np.sqrt(2.0) if spec.asymmetric else 1.0)
    steps = np.stack([np.linalg.norm(_apply_h(H, obj + d) - _apply_h(H, obj), axis=1)
                      for d in ([nn_mm, 0], [0, nn_mm], [-nn_mm, 0], [0, -nn_mm])])
    nn_px = np.min(steps, axis=0)
    # (for asymmetric grids the nearest neighbour is diagonal, s*sqrt(2) away; an axis step of that
    # length approximates its pixel distance)
    if spec.diameter_mm is not None:
        r_px = 0.5 * spec.diameter_mm / nn_mm * nn_px
    else:
        r_px = 0.2 * nn_px  # seed 003 geometry (20 mm holes, 50 mm spacing) as a guess
    notes = []
    cut = np.zeros(len(pts), bool)
    if refine in ("moments", "edges"):
        # window: the disc plus ~3 sigma of a typical thermal blur, clear of the neighbouring disc
        # (which starts at nn_px - r_px) with a 2 px background annulus in between
        win = np.minimum(r_px * 1.25 + 3.0, nn_px - r_px - 3.0)
        if np.any(win < r_px + 1.0):
            notes.append("circles too close for moment windows; blob centres kept")
        else:
            # plane background where the annulus (win .. win + 2) stays >= 3 px clear of the
            # neighbouring disc (its blurred edge would read as a gradient); the median elsewhere
            # the annulus as wide as the room allows (2-6 px; a wider one gives a steadier plane)
            ring = np.clip((nn_px - r_px) - win - 3.0, 2.0, 6.0)
            plane = (nn_px - r_px) - (win + ring) >= 3.0
            new, ok = refine_circle_centres(gray, pts, r_px, win, bright, plane_background=plane, ring_px=ring)
            moved = np.linalg.norm(new - pts, axis=1) > 0.5 * r_px + 1.0
            keep = ok & ~moved
            # a circle cut by the frame border (its disc plus 2 px of blur reaching outside) would be
            # off by pixels (9 px measured on a 60 mm circle cut by the border): dropped; a whole disc
            # whose window or annulus leaves the frame, or whose centre does not settle, keeps its
            # blob position
            h_img, w_img = gray.shape
            r_mm = 0.5 * spec.diameter_mm if spec.diameter_mm is not None else 0.2 * nn_mm
            ang = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
            ring_mm = 1.05 * r_mm * np.column_stack([np.cos(ang), np.sin(ang)])
            cut = np.zeros(len(pts), bool)
            for k in range(len(pts)):  # the disc's outline by the homography, placed at its blob centre
                o = _apply_h(H, obj[k] + ring_mm) - _apply_h(H, obj[k:k + 1]) + pts[k]
                cut[k] = bool(np.any((o[:, 0] < 1.5) | (o[:, 0] > w_img - 2.5) | (o[:, 1] < 1.5) | (o[:, 1] > h_img - 2.5)))
            pts = np.where(keep[:, None], new, pts)
            if np.any(~keep & ~cut) and not (refine == "edges" and spec.diameter_mm is not None):
                notes.append(f"{int((~keep & ~cut).sum())} centre(s) kept at blob positions (window at the border "
                             "or unstable)")
            if np.any(cut) and not (refine == "edges" and spec.diameter_mm is not None):
                notes.append(f"{int(cut.sum())} circle(s) cut by the frame border dropped")
                pts, ids, obj = pts[~cut], ids[~cut], obj[~cut]
                partial = True
                if len(ids) < max(min_points or 6, 4):
                    return Detection.failure(image_id, f"{len(ids)} whole circles left (< {max(min_points or 6, 4)}; "
                                             "the others are cut by the frame border)", size)
    if refine == "edges" and spec.diameter_mm is not None and len(pts) >= 4:
        # outline-based centres (immune to a temperature gradient across the disc and to a moment
        # window that does not hold a strongly foreshortened disc), started from the moment centres
        Q = circle_shape_matrices(_fit_h(obj, pts), obj, 0.5 * spec.diameter_mm)
        new, ok_e, outl, _ = refine_circle_edges(gray, pts, Q, bright)
        ok_e &= np.linalg.norm(new - pts, axis=1) < 0.25 * np.sqrt(1.0 / np.linalg.eigvalsh(Q)[:, 0]) + 1.0
        pts = np.where(ok_e[:, None], new, pts)
        if np.any(~ok_e) and ok_e.sum() >= 8:
            # a blob detector's centre can be pixels off (a disc merged with a contrast feature): start
            # again where a second-order map through the other circles puts it
            good_i = np.flatnonzero(ok_e)
            sc = max(float(np.abs(obj).max()), 1e-9)
            A = lambda o: np.column_stack([np.ones(len(o)), o[:, 0] / sc, o[:, 1] / sc, (o[:, 0] / sc) ** 2,
                                           o[:, 0] * o[:, 1] / sc**2, (o[:, 1] / sc) ** 2])
            coef, *_ = np.linalg.lstsq(A(obj[good_i]), pts[good_i], rcond=None)
            bad = np.flatnonzero(~ok_e)
            guess = A(obj[bad]) @ coef
            new_b, ok_b, outl_b, _ = refine_circle_edges(gray, guess, Q[bad], bright)
            ok_b &= np.linalg.norm(new_b - guess, axis=1) < 0.25 * np.sqrt(1.0 / np.linalg.eigvalsh(Q[bad])[:, 0]) + 1.0
            pts[bad[ok_b]] = new_b[ok_b]
            outl[bad[ok_b]] = outl_b[ok_b]
            ok_e[bad[ok_b]] = True
            if np.any(ok_b):
                notes.append(f"{int(ok_b.sum())} centre(s) measured again from the grid's prediction")
            if np.any(~ok_e):
                # neither the blob's nor the predicted start gives an outline: the circle is dropped
                # rather than kept at a blob position that may be pixels off
                keep_e = ok_e.copy()
                notes.append(f"{int((~keep_e).sum())} circle(s) without a measurable outline dropped")
                pts, ids, obj, ok_e, outl, cut = (pts[keep_e], ids[keep_e], obj[keep_e], ok_e[keep_e], outl[keep_e],
                                                  cut[keep_e])
                partial = True
        if len(ids) < spec.n_points and len(ids) >= 6:
            # complete a partial grid: circles the candidate passes missed (a size outside the group's
            # range under steep perspective, a merged blob) are measured where the found ones put them
            pts, ids, obj, ok_e, outl, cut, n_add = _complete_grid(gray, spec, pts, ids, ok_e, outl, cut, bright)
            if n_add:
                notes.append(f"{n_add} circle(s) added where the others predict them")
                partial = len(ids) < spec.n_points
                if not partial:
                    name = name.replace("partial", "lattice")  # a whole grid, as a lattice pass that finds all
        # cut by the frame border: the measured outline (rays that left the frame were filled in by the
        # outline's conic) within 1.5 px of the border; without an outline, the homography's estimate
        h_img, w_img = gray.shape
        with np.errstate(invalid="ignore"):
            out_e = np.any((outl[..., 0] < 1.5) | (outl[..., 0] > w_img - 2.5) | (outl[..., 1] < 1.5)
                           | (outl[..., 1] > h_img - 2.5), axis=1)
        cut = np.where(ok_e, out_e, cut)
        if np.any(cut):
            notes.append(f"{int(cut.sum())} circle(s) cut by the frame border dropped")
            pts, ids, obj, ok_e = pts[~cut], ids[~cut], obj[~cut], ok_e[~cut]
            partial = True
            if len(ids) < max(min_points or 6, 4):
                return Detection.failure(image_id, f"{len(ids)} whole circles left (< {max(min_points or 6, 4)}; "
                                         "the others are cut by the frame border)", size)
        if np.any(~ok_e):
            notes.append(f"{int((~ok_e).sum())} centre(s) by moments or blob positions (too few edge points)")
    if perspective_correction and spec.diameter_mm is not None:
        raw = pts.copy()
        for _ in range(2):
            H = _fit_h(obj, pts)
            pts = raw - ellipse_centre_bias(H, obj, 0.5 * spec.diameter_mm)
        notes.append("perspective bias corrected")
    elif perspective_correction:
        notes.append("no perspective-bias correction (diameter_mm unknown)")
    H = _fit_h(obj, pts)
    rms = float(np.sqrt(np.mean(np.sum((_apply_h(H, obj) - pts) ** 2, axis=1))))
    reason = f"found by {name}" + (f" after {', '.join(tried)} failed" if tried else "")
    if partial:
        notes.insert(0, f"partial grid: {len(ids)} of {spec.n_points} circles"
                     + (f" (the patch fits the target at {n_placements} places, equivalent up to the view's pose)"
                        if n_placements > 1 else ""))
    if notes:
        reason += "; " + "; ".join(notes)
    extra = {"homography_rms_px": rms, "radius_px": float(np.median(r_px)), "polarity": "bright" if bright else "dark"}
    if partial:
        extra.update(partial=True, placements=int(n_placements))
    return Detection(image_id=str(image_id), found=True, points_px=np.ascontiguousarray(pts),
                     object_ids=np.ascontiguousarray(ids), reason=reason, image_size=size, method=name, extra=extra)


def _complete_grid(gray, spec, pts, ids, ok_e, outl, cut, bright):
    """Measure the circles of ``spec`` missing from ``ids`` where a map through the found ones puts
    them (second-order with >= 8 circles, else the homography); a circle is added when its outline is
    measured (:func:`refine_circle_edges`) within a third of its radius of the prediction, on >= 90 % of
    its rays and within max(0.25 px, 1 % of its radius) RMS of a conic (a whole disc: 0.10 px measured at 2 K
    contrast; 0.63 px for a disc of radius 12 px half under an occluding bar), and its area is
    within 0.6-1.6 of the homography's ellipse. Returns the arrays sorted by id, and the number added."""
    h, w = gray.shape
    all_obj = spec.object_points()[:, :2]
    obj = all_obj[ids]
    missing = np.setdiff1d(np.arange(spec.n_points), ids)
    good = np.flatnonzero(ok_e)
    if missing.size == 0 or good.size < 6:
        return pts, ids, obj, ok_e, outl, cut, 0
    H = _fit_h(obj[good], pts[good])
    if H is None:
        return pts, ids, obj, ok_e, outl, cut, 0
    guess = _apply_h(H, all_obj[missing])
    if good.size >= 8:
        sc = max(float(np.abs(all_obj).max()), 1e-9)

        def A(o):
            x, y = o[:, 0] / sc, o[:, 1] / sc
            return np.column_stack([np.ones(len(o)), x, y, x * x, x * y, y * y])

        coef, *_ = np.linalg.lstsq(A(obj[good]), pts[good], rcond=None)
        guess = A(all_obj[missing]) @ coef
    Q = circle_shape_matrices(H, all_obj[missing], 0.5 * spec.diameter_mm)
    semi = np.sqrt(1.0 / np.linalg.eigvalsh(Q))  # (K, 2): minor, major semi-axes
    inside = (guess[:, 0] > semi[:, 0]) & (guess[:, 0] < w - 1 - semi[:, 0]) & (guess[:, 1] > semi[:, 0]) & \
        (guess[:, 1] < h - 1 - semi[:, 0])
    if not np.any(inside):
        return pts, ids, obj, ok_e, outl, cut, 0
    missing, guess, Q, semi = missing[inside], guess[inside], Q[inside], semi[inside]
    new, ok_n, outl_n, qual = refine_circle_edges(gray, guess, Q, bright)
    x, y = outl_n[..., 0], outl_n[..., 1]
    with np.errstate(invalid="ignore"):
        area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    expect = np.pi * semi[:, 0] * semi[:, 1]
    # a whole disc: nearly every ray measured (a disc cut by an occluder or the frame border leaves
    # rays without an edge, filled in by the conic)
    with np.errstate(invalid="ignore"):
        ok_n &= (np.linalg.norm(new - guess, axis=1) < semi[:, 0] / 3.0 + 1.0) & (area > 0.6 * expect) & \
            (area < 1.6 * expect) & (qual[:, 0] >= 0.9) & (qual[:, 1] <= np.maximum(0.25, 0.01 * semi[:, 1]))
    if not np.any(ok_n):
        return pts, ids, obj, ok_e, outl, cut, 0
    ids2 = np.concatenate([ids, missing[ok_n]])
    order = np.argsort(ids2)
    cat = lambda a, b: np.concatenate([a, b])[order]
    pts2 = cat(pts, new[ok_n])
    return (pts2, ids2[order], all_obj[ids2[order]], cat(ok_e, np.ones(int(ok_n.sum()), bool)),
            cat(outl, outl_n[ok_n]), cat(cut, np.zeros(int(ok_n.sum()), bool)), int(ok_n.sum()))


# --------------------------------------------------------------------------------------------------
# partial grids: part of the grid outside the frame or hidden
# --------------------------------------------------------------------------------------------------
def _size_group(c: np.ndarray, n: int) -> np.ndarray:
    """Indices of the largest group of ellipse candidates within a factor 8 in area, preferring
    candidates found at several scales (grid discs are similar, but a close view tilted by 50° changes
    their area by up to ~4x across a 4 x 3 grid: 3.8x measured, so a window of 4x centred on a
    candidate missed the smallest disc)."""
    la = np.log(c[:, 4])
    best = None
    for i in np.argsort(-c[:, 5]):
        grp = np.flatnonzero(np.abs(la - la[i]) < np.log(8.0) / 2 + 1e-9)
        score = (len(grp) >= n, c[grp, 5].sum())
        if best is None or score > best[0]:
            best = (score, grp)
    return best[1]


def _ellipse_cov(c: np.ndarray) -> np.ndarray:
    """(2, 2) shape matrix ``R diag(major², minor²) Rᵀ`` of an :func:`ellipse_candidates` row."""
    ca, sa = np.cos(c[6]), np.sin(c[6])
    R = np.array([[ca, -sa], [sa, ca]])
    return R @ np.diag([c[2] ** 2, c[3] ** 2]) @ R.T


def _anisotropy(cov: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> float:
    """Axis ratio (>= 1) of an image ellipse mapped back through the local lattice basis ``[e1 e2]``:
    1 for the image of a circle when ``e1, e2`` are the images of two orthogonal, equally long
    target steps (grid axes of a symmetric grid, the diagonals of an asymmetric one)."""
    J = np.column_stack([e1, e2])
    if abs(np.linalg.det(J)) < 1e-9:
        return np.inf
    Ji = np.linalg.inv(J)
    w = np.linalg.eigvalsh(Ji @ cov @ Ji.T)
    return float(np.sqrt(max(w[1], 1e-300) / max(w[0], 1e-300)))


def _grow_lattice(p: np.ndarray, cand: np.ndarray | None = None):
    """Integer lattice coordinates of points that form (part of) a distorted 2-D grid.

    A seed (the candidate with the most neighbours within 1.5 x the typical nearest-neighbour
    distance, nearest the middle) and two basis steps to its neighbours start a breadth-first growth:
    the position of a neighbour is predicted by extrapolating along the row or column (``p[k] +
    (p[k] - p[back])``, exact to first order under smooth distortion) or, without a point behind, by
    the local step carried along; the nearest candidate within 30 % of the step is taken, else one
    two steps on (a hidden circle between). A candidate claimed by two lattice positions makes the
    structure ambiguous (returns None).

    The basis: any two independent lattice vectors generate the same point lattice (a diagonal is
    as good as an axis to the points alone, and under strong perspective a diagonal can be the
    shorter step), so the points cannot tell the grid's axes. The circles can: with ``cand`` (the
    :func:`ellipse_candidates` rows of ``p``) the pair of steps that maps the seed's ellipse back to
    the roundest shape (:func:`_anisotropy`) is taken; without it, the nearest neighbour and the
    shortest step at more than 60 degrees to it.

    Returns
    -------
    (idx (K,), ab (K, 2) int) or None -- indices into ``p`` and their lattice coordinates (basis
    right-handed in the image).
    """
    m = len(p)
    if m < 3:
        return None
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    np.fill_diagonal(d, np.inf)
    nn = float(np.median(d.min(axis=1)))
    cnt = (d < 1.5 * nn).sum(axis=1)
    mid = np.median(p, axis=0)
    seed = int(np.lexsort((np.linalg.norm(p - mid, axis=1), -cnt))[0])
    nb = np.flatnonzero(d[seed] < 1.5 * nn)
    if len(nb) < 2:
        return None
    v = p[nb] - p[seed]
    ln = np.linalg.norm(v, axis=1)
    if cand is not None and cand.shape[1] >= 8:
        cov = _ellipse_cov(cand[seed])
        pairs = []
        for i in range(len(v)):
            for j in range(len(v)):
                cr = v[i, 0] * v[j, 1] - v[i, 1] * v[j, 0]
                if cr <= 0.2 * ln[i] * ln[j]:  # independent (> ~12 degrees apart), right-handed
                    continue
                pairs.append((_anisotropy(cov, v[i], v[j]), cr, i, j))
        if not pairs:
            return None
        # the roundest pairs; among them the smallest cell: the diagonals of a square cell are
        # orthogonal and equally long too, but span a cell twice as large (they skip every other disc)
        lo = min(q[0] for q in pairs)
        _, _, i, j = min((q for q in pairs if q[0] <= lo + 0.15 * lo), key=lambda q: q[1])
        e1, e2 = v[i], v[j]
    else:
        e1 = v[np.argmin(ln)]
        cosang = np.abs(v @ e1) / (ln * np.linalg.norm(e1))
        perp = np.flatnonzero(cosang < 0.5)
        if not len(perp):
            return None
        e2 = v[perp[np.argmin(ln[perp])]]
        if e1[0] * e2[1] - e1[1] * e2[0] < 0:
            e2 = -e2
    coords = {seed: (0, 0)}
    pos = {(0, 0): seed}
    basis = {seed: (e1, e2)}
    queue = [seed]
    while queue:
        k = queue.pop(0)
        a, b = coords[k]
        for axis, sgn in ((0, 1), (0, -1), (1, 1), (1, -1)):
            e = np.array([sgn, 0]) if axis == 0 else np.array([0, sgn])
            backkey = (a - e[0], b - e[1])
            step = p[k] - p[pos[backkey]] if backkey in pos else sgn * basis[k][axis]
            for mult in (1, 2):
                key = (a + mult * e[0], b + mult * e[1])
                if key in pos:
                    break
                pred = p[k] + mult * step
                dist = np.linalg.norm(p - pred, axis=1)
                j = int(np.argmin(dist))
                if dist[j] > 0.3 * np.linalg.norm(step):
                    continue
                if j in coords:
                    if coords[j] != key:
                        return None  # one disc at two lattice positions: not a grid
                    break
                coords[j] = key
                pos[key] = j
                b_new = list(basis[k])
                b_new[axis] = sgn * (p[j] - p[k]) / mult
                basis[j] = tuple(b_new)
                queue.append(j)
                break
    idx = np.array(sorted(coords), dtype=int)
    ab = np.array([coords[i] for i in idx], dtype=int)
    return idx, ab


def _place_on_target(ab: np.ndarray, spec: CircleGridSpec):
    """Object ids for lattice coordinates ``ab`` (right-handed in the image): every placement of the
    observed lattice patch on the target by a rotation of the lattice (multiples of 90 degrees) and an
    integer translation that puts every point on a circle of the target.

    Symmetric grid: lattice steps are the spacing s along x and y. Asymmetric grid: the nearest
    neighbours are the diagonals ``(±s, ±s)``, so lattice ``(a, b)`` is at ``(a - b, a + b) s``.
    A rotation or translation of the whole patch is a rigid motion of the target plane, which the
    view's own pose absorbs: any valid placement gives the same calibration.

    Returns
    -------
    list of ndarray (K,) int -- object ids of each valid placement (empty: the patch fits nowhere).
    """
    obj = spec.object_points()[:, :2] / spec.spacing_mm
    lut = {(int(round(x)), int(round(y))): i for i, (x, y) in enumerate(obj)}
    if spec.asymmetric:
        uv = np.column_stack([ab[:, 0] - ab[:, 1], ab[:, 0] + ab[:, 1]])
    else:
        uv = ab.copy()
    tx = np.array([k[0] for k in lut])
    ty = np.array([k[1] for k in lut])
    out = []
    for rot in range(4):
        r = uv.copy()
        for _ in range(rot):
            r = np.column_stack([-r[:, 1], r[:, 0]])
        for du in range(tx.min() - r[:, 0].min(), tx.max() - r[:, 0].max() + 1):
            for dv in range(ty.min() - r[:, 1].min(), ty.max() - r[:, 1].max() + 1):
                ids = [lut.get((int(x + du), int(y + dv))) for x, y in r]
                if all(i is not None for i in ids):
                    out.append(np.array(ids, dtype=np.int64))
    return out


def _one_per_disc(cand: np.ndarray) -> np.ndarray:
    """One :func:`ellipse_candidates` row per disc: nested contours of one disc at other thresholds
    (centre within a quarter of the minor axis, and area within 4x or found at fewer scales) are dropped."""
    keep = []
    for i in np.lexsort((-cand[:, 4], -cand[:, 5])):
        if all(np.hypot(*(cand[i, :2] - cand[j, :2])) > 0.25 * min(cand[i, 3], cand[j, 3])
               or (max(cand[i, 4], cand[j, 4]) > 4.0 * min(cand[i, 4], cand[j, 4]) and cand[i, 5] >= cand[j, 5])
               for j in keep):
            keep.append(i)
    return cand[np.sort(np.asarray(keep, dtype=int))]


def _partial_grid(gray, spec, bright, cand, min_points: int):
    """A partial grid from ellipse candidates (:func:`_grow_lattice`, :func:`_place_on_target`),
    checked with a second-order map and the polarity test. Returns (points (K, 2), ids (K,),
    n_placements, why)."""
    n = spec.n_points
    if len(cand) < min_points:
        return None, None, 0, f"{len(cand)} ellipse candidates < {min_points}"
    # whole discs only: a disc cut by an occluder's edge or the frame border has a straight piece of
    # outline (relative departure from its fitted ellipse 0.15-0.3, against 0.02-0.05 for whole
    # blurred discs); its centroid would be off by pixels
    cand = cand[cand[:, 7] <= 0.1]
    cand = _one_per_disc(cand)
    if len(cand) < min_points:
        return None, None, 0, f"{len(cand)} whole-disc ellipse candidates < {min_points}"
    grp = _size_group(cand, n)
    c = cand[grp]
    if len(c) < min_points:
        return None, None, 0, f"only {len(c)} ellipses of a consistent size"
    grown = _grow_lattice(c[:, :2], c)
    if grown is None:
        return None, None, 0, "ellipses do not form a lattice"
    idx, ab = grown
    if len(idx) < min_points or len(np.unique(ab[:, 0])) < 2 or len(np.unique(ab[:, 1])) < 2:
        return None, None, 0, f"{len(idx)} ellipses on a lattice (< {min_points}, or on one line)"
    if len(idx) > n:
        return None, None, 0, f"{len(idx)} ellipses on a lattice: more than the {n} circles of the grid"
    pts = c[idx, :2]
    placements = _place_on_target(ab, spec)
    if not placements:
        span = ab.max(axis=0) - ab.min(axis=0) + 1
        return None, None, 0, (f"{len(idx)} ellipses on a {span[0]}x{span[1]} lattice that does not fit the "
                               f"{spec.columns}x{spec.rows} grid")
    ids = placements[0]
    obj = spec.object_points()[ids, :2]
    rms, mx = _quad_fit_rms(obj, pts)
    nn_px = float(np.median(np.sort(np.linalg.norm(pts[:, None] - pts[None], axis=2), axis=1)[:, 1]))
    if mx > 0.15 * nn_px + 0.5:
        return None, None, 0, f"partial lattice of {len(idx)} ellipses does not fit a smooth map ({mx:.1f} px)"
    if not _polarity_ok(gray, pts, c, bright):
        return None, None, 0, "partial lattice fails the polarity check"
    return pts, ids, len(placements), ""
