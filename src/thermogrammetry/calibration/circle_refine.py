"""Sub-pixel circle centres and their perspective bias.

1. sub-pixel centres by background-subtracted, intensity-weighted moments in a circular window,
   re-centred until it converges (:func:`refine_circle_centres`; blur is a symmetric convolution: it
   leaves the centroid of a disc in place as long as the window holds the blurred disc);
2. the area centroid of each disc's sub-pixel outline (:func:`refine_circle_edges`), its expected
   outline from the homography (:func:`circle_shape_matrices`);
3. perspective bias: the centroid of an imaged circle is the centre of the image ellipse, which is
   not the image of the circle's centre. With a homography ``H`` (plane mm → image px) each circle
   ``(x - x0)² + (y - y0)² = R²`` is mapped to its image conic ``C' = H^-T C H^-1``; the ellipse centre
   minus ``H (x0, y0)`` is the bias (:func:`ellipse_centre_bias`).

References
----------
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10),
1066-1077 (perspective bias of circle centres; conic projection).
Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
thermal imagery (sub-pixel centres of a mask grid).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["refine_circle_centres", "circle_shape_matrices", "refine_circle_edges", "ellipse_centre_bias"]


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
                    li, lo_ = _line_at_zero(si, inner), _line_at_zero(so, outer)
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


def _line_at_zero(x: np.ndarray, y: np.ndarray) -> float:
    """Value at ``x = 0`` of the least-squares line through ``(x, y)`` (closed form; what ``np.polyfit(x, y, 1)``
    evaluated at 0 gives, up to rounding, without its per-call overhead: this runs twice per ray)."""
    xm, ym = x.mean(), y.mean()
    dx = x - xm
    return float(ym - xm * (dx @ (y - ym)) / (dx @ dx))


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
