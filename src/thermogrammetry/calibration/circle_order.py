"""Grid topology and ordering of circle-grid candidates: homography checks, canonical order, whole grids
from ellipse candidates.

The candidate orders of a detected grid (identity, row flip, column flip, 180° rotation) are checked
against a homography fit of the object points (or, under strong distortion, a second-order map,
:func:`quad_fit_rms`); among the valid ones the right-handed one (board frame z away from the camera)
with corner 0 nearest the image's top-left is kept (:func:`order_grid_by_homography`). Whole grids
from ellipse candidates (:func:`grid_from_ellipses`) are ordered by ``cv2.findCirclesGrid`` on a clean
redrawn image or, for a symmetric grid, from the candidates' convex hull; :func:`polarity_ok` rejects
grids of the gaps between discs of the other polarity.

References
----------
Vidas, S., Lakemond, R., Denman, S., Fookes, C., Sridharan, S., Wark, T. (2012). A mask-based
approach for the geometric calibration of thermal-infrared cameras. IEEE TIM 61(6), 1625-1635.
"""

from __future__ import annotations

import cv2
import numpy as np

from .circle_candidates import REDRAWN_DETECTOR, ellipse_candidates, size_group
from .detect_common import CircleGridSpec

__all__ = ["fit_h", "apply_h", "order_grid_by_homography", "quad_fit_rms", "grid_from_ellipses", "polarity_ok"]


def fit_h(obj_xy, img_xy):
    H, _ = cv2.findHomography(np.asarray(obj_xy, np.float64), np.asarray(img_xy, np.float64), 0)
    return H


def _right_handed(H, obj_xy, spacing_mm: float) -> bool:
    """Handedness of the grid's image: sign of the Jacobian determinant of ``H`` at the grid centre."""
    o = obj_xy.mean(axis=0)
    e = 1e-3 * spacing_mm
    q = apply_h(H, np.array([o, o + [e, 0], o + [0, e]]))
    dx, dy = q[1] - q[0], q[2] - q[0]
    return bool(dx[0] * dy[1] - dx[1] * dy[0] > 0)


def apply_h(H, xy):
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
        H = fit_h(obj, p)
        if H is None:
            continue
        res = np.linalg.norm(apply_h(H, obj) - p, axis=1)
        if res.max() > tol_frac * spacing_px + 0.5:
            continue
        good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p, float(np.sqrt(np.mean(res**2)))))
    if not good and distortion_aware:
        # strong barrel distortion over a grid that spans much of the frame bends its rows by more
        # than a homography allows: accept an order that a second-order map fits (a wrong order of an
        # asymmetric grid breaks its stagger by half a spacing and still fails)
        for c in cands:
            p = points_px[c.ravel()]
            rms, mx = quad_fit_rms(obj, p)
            H = fit_h(obj, p)
            if H is None or mx > 0.15 * spacing_px + 0.5:
                continue
            good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p, rms))
    if not good:
        return None, np.inf
    good.sort(key=lambda g: (g[0], g[1]))
    return good[0][2], good[0][3]


def quad_fit_rms(obj, pts):
    """RMS and max residual of a second-order polynomial map object -> image (distortion-aware
    stand-in for a homography when checking an ordering)."""
    x, y = obj[:, 0] / np.abs(obj).max(), obj[:, 1] / max(np.abs(obj).max(), 1e-12)
    A = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    if len(obj) <= A.shape[1]:
        A = A[:, :3]
    coef, *_ = np.linalg.lstsq(A, pts, rcond=None)
    r = np.linalg.norm(A @ coef - pts, axis=1)
    return float(np.sqrt(np.mean(r * r))), float(r.max())


def grid_from_ellipses(gray, spec, bright, c=None):
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
    grp = size_group(c, n)
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
            ok, centres = cv2.findCirclesGrid(clean, spec.pattern_size, flags=flags, blobDetector=REDRAWN_DETECTOR)
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
                rms, mx = quad_fit_rms(obj, p)
                if mx > 0.15 * spacing + 0.5:
                    continue
                H = fit_h(obj, p)
                if H is None:
                    continue
                good.append((not _right_handed(H, obj, spec.spacing_mm), float(p[0].sum()), p))
            if good:
                good.sort(key=lambda g: (g[0], g[1]))
                if polarity_ok(gray, good[0][2], cand, bright):
                    return good[0][2], ""
    if not spec.asymmetric:
        pts = _grid_from_hull(cand[:n, :2], spec)
        if pts is not None and polarity_ok(gray, pts, cand, bright):
            return pts, ""
    return None, f"{len(cand)} ellipses of a consistent size, no {spec.pattern_size[0]}x{spec.pattern_size[1]} grid among them"


def polarity_ok(gray, pts, cand, bright) -> bool:
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
            H = fit_h(np.array([oc[k] for k in range(4)]), img_c)
            if H is None:
                continue
            pred = apply_h(H, obj)
            d = np.linalg.norm(pred[:, None] - p[None], axis=2)
            a = np.argmin(d, axis=1)
            if len(set(a.tolist())) != len(p):
                continue
            q = p[a]
            rms, mx = quad_fit_rms(obj, q)
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
        H = fit_h(obj, r)
        o = obj.mean(axis=0)
        e = 1e-3 * spec.spacing_mm
        z = apply_h(H, np.array([o, o + [e, 0], o + [0, e]]))
        dx, dy = z[1] - z[0], z[2] - z[0]
        good.append((not (dx[0] * dy[1] - dx[1] * dy[0] > 0), float(r[0].sum()), r))
    good.sort(key=lambda g: (g[0], g[1]))
    return good[0][2]
