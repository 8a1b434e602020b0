"""Coded checkerboard: a checkerboard with an ArUco marker in its middle (MRT coded target).

OpenCV's chessboard detectors need the whole inner grid to be visible and unoccluded; the marker
blanks 4 x 4 squares in the middle of the board and the board is often partly outside the image, so
they find the board in 1 of the 60 views of ``../shared/data/ir_coded_checkerboard``. The marker
fixes the board frame instead (Schramm et al. 2021):

1. detect the marker (``cv2.aruco``; stretched, CLAHE, inverted and upsampled images are tried);
2. homography board(mm) → image from the marker's four corners;
3. grow ring by ring around the marker (Chebyshev distance in squares from the central corner):
   predict the ring's corners with the current homography, refine each with ``cornerSubPix``
   (window matched to the local square size), verify it (it moved less than a fraction of a square,
   and the four squares around it show the expected dark/bright alternation with enough contrast),
   then re-estimate the homography from all accepted corners and go to the next ring.

Growing ring by ring keeps the prediction error (lens distortion, marker corner noise) well below the
capture range of the refinement, and the alternation check rejects corners outside the board,
occluded by hands, or beyond the image border.

References
----------
Schramm, S., Ebert, J., Rangel, J., Schmoll, R., Kroll, A. (2021). Iterative corner detection of a
coded checkerboard target for the geometric calibration of infrared cameras. J. Sens. Sens. Syst.
10(2), 207-218. doi:10.5194/jsss-10-207-2021
Garrido-Jurado, S. et al. (2014). Automatic generation and detection of highly reliable fiducial
markers under occlusion. Pattern Recognition 47(6) (ArUco).
"""

from __future__ import annotations

import cv2
import numpy as np

from .detect_chessboard import _sample
from .detect_common import (
    CodedCheckerboardSpec,
    Detection,
    clahe_u8,
    image_size_of,
    normalize_to_u8,
    spec_of,
    to_gray_float,
)

__all__ = ["detect_coded_checkerboard", "detect_marker"]


def _dictionary(spec: CodedCheckerboardSpec):
    return spec.dictionary()


def detect_marker(u8: np.ndarray, spec: CodedCheckerboardSpec):
    """Find the board's ArUco marker.

    Returns
    -------
    corners : ndarray (4, 2) or None
        Marker corners in ArUco order (OpenCV pixel convention), None when not found.
    inverted : bool
        True when the marker was found in the inverted image (the board appears with reversed
        polarity, as heated targets can).
    method : str
        Which image variant gave the marker; or the list of variants tried.
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(_dictionary(spec), params)
    cl = clahe_u8(u8)
    variants = [("stretch", u8, False, 1), ("clahe", cl, False, 1), ("inverted", 255 - cl, True, 1),
                ("upsampled", cv2.resize(cl, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC), False, 2),
                ("upsampled-inverted", 255 - cv2.resize(cl, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC), True, 2)]
    for name, img, inv, scale in variants:
        corners, ids, _ = det.detectMarkers(img)
        if ids is None:
            continue
        ids = np.asarray(ids).ravel()
        hit = np.flatnonzero(ids == spec.marker_id)
        if hit.size == 0:
            continue
        c = np.asarray(corners[hit[0]], np.float64).reshape(4, 2)
        if scale != 1:
            c = (c + 0.5) / scale - 0.5
        return c, inv, name
    return None, False, ", ".join(v[0] for v in variants)


def _fit_h(obj_xy: np.ndarray, img_xy: np.ndarray):
    H, _ = cv2.findHomography(obj_xy.astype(np.float64), img_xy.astype(np.float64), 0)
    return H


def _apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return p[:, :2] / p[:, 2:3]


def _local_outliers(accepted: dict, obj: np.ndarray, cols: int, square_mm: float, tol_frac: float) -> list:
    """Ids whose leave-one-out prediction from a local homography (accepted corners within two
    squares -- three where the neighbourhood is sparse -- at least 6) misses them by more than
    ``max(tol_frac * square_px, 0.75 px)``, plus corners with fewer than 6 such neighbours (nothing
    to check them against). Only the worst of a neighbourhood is reported per pass, so a bad corner
    does not condemn good ones."""
    ids = np.array(sorted(accepted), dtype=np.int64)
    if ids.size < 7:
        return []
    pts = np.array([accepted[i] for i in ids])
    c, r = ids % cols, ids // cols
    err = np.full(ids.size, np.nan)
    lim = np.full(ids.size, np.inf)
    isolated = []
    for k in range(ids.size):
        cheb = np.maximum(np.abs(c - c[k]), np.abs(r - r[k]))
        cheb[k] = 99
        near = cheb <= 2
        if near.sum() < 6:
            near = cheb <= 3  # sparse neighbourhood (board edge, occlusion): look a little further
        if near.sum() < 6:
            isolated.append(int(ids[k]))  # nothing to check it against: not trusted
            continue
        H = _fit_h(obj[ids[near]], pts[near])
        if H is None:
            continue
        pred = _apply_h(H, obj[ids[k]][None])[0]
        sq = np.linalg.norm(_apply_h(H, obj[ids[k]][None] + [square_mm, 0])[0] - pred)
        err[k] = np.linalg.norm(pred - pts[k])
        lim[k] = max(tol_frac * sq, 0.75)
    ratio = np.where(np.isfinite(err), err / lim, 0.0)
    out = list(isolated)
    for k in np.argsort(-ratio):
        if ratio[k] <= 1:
            break
        # skip when a worse neighbour is already condemned (it spoils this one's local fit)
        if any(max(abs(c[k] - (j % cols)), abs(r[k] - (j // cols))) <= 2 for j in out):
            continue
        out.append(int(ids[k]))
    return out


def detect_coded_checkerboard(image, spec: CodedCheckerboardSpec | None = None, image_id: str = "", *,
                              min_corners: int = 12, max_shift_frac: float = 0.3,
                              min_contrast_frac: float = 0.25, local_tol_frac: float = 0.06) -> Detection:
    """Find the coded checkerboard and identify its visible corners.

    Parameters
    ----------
    image : array_like (H, W) or (H, W, 1|3|4), uint8 / uint16 / float
    spec : CodedCheckerboardSpec, optional
        Defaults to the MRT 60x45 cm target.
    image_id : str
    min_corners : int
        The board counts as found when at least this many corners are identified.
    max_shift_frac : float
        A refined corner may lie at most this fraction of the local square size from its prediction.
    min_contrast_frac : float
        Minimum dark/bright alternation around a corner, as a fraction of the marker's contrast.
    local_tol_frac : float
        Leave-one-out tolerance of the local homography check, as a fraction of the square size.

    Returns
    -------
    Detection
        ``points_px`` (N, 2), ``object_ids`` (N,) into ``spec.object_points()`` (sorted ascending);
        ``extra`` holds the marker corners and the polarity.
    """
    spec = CodedCheckerboardSpec() if spec is None else spec_of(spec, CodedCheckerboardSpec, "CodedCheckerboardSpec")
    gray = to_gray_float(image, f"image {image_id!r}" if image_id else "image")
    size = image_size_of(gray)
    u8 = normalize_to_u8(gray)
    marker, inverted, how = detect_marker(u8, spec)
    if marker is None:
        return Detection.failure(image_id, f"ArUco marker {spec.marker_id} not found (tried: {how})", size)

    h_img, w_img = gray.shape
    smooth = cv2.GaussianBlur(u8.astype(np.float32), (0, 0), 1.0)
    sign = -1.0 if inverted else 1.0  # +: dark squares have low values

    obj = spec.object_points()[:, :2]
    s = spec.square_mm
    # marker contrast: the marker border (dark) against the blank area around it (bright)
    mk_mm = spec.marker_corners_mm()
    ctr = spec.center_mm
    border_mm = ctr + (mk_mm - ctr) * 0.9           # inside the black border ring
    blank_mm = ctr + (mk_mm - ctr) * 1.15           # in the white blank area just outside
    H = _fit_h(mk_mm, marker)
    if H is None:
        return Detection.failure(image_id, "degenerate marker corners (no homography)", size)
    contrast = sign * float(np.mean(_sample(smooth, _apply_h(H, blank_mm))) - np.mean(_sample(smooth, _apply_h(H, border_mm))))
    if contrast <= 0:
        return Detection.failure(image_id, f"marker found ({how}) but it shows no contrast against the board", size)
    min_alt = min_contrast_frac * contrast

    valid = spec.valid_ids()
    cols = spec.inner_columns
    cc, cr = (spec.inner_columns - 1) // 2, (spec.inner_rows - 1) // 2
    c_idx, r_idx = valid % cols, valid // cols
    ring = np.maximum(np.abs(c_idx - cc), np.abs(r_idx - cr))
    # quadrant offsets (mm) and expected darkness of the 4 squares around each corner
    q_off = np.array([[-0.3, -0.3], [0.3, -0.3], [-0.3, 0.3], [0.3, 0.3]]) * s
    q_dc = np.array([-1, 0, -1, 0])
    q_dr = np.array([-1, -1, 0, 0])

    accepted: dict[int, np.ndarray] = {}
    rejected_counts = {"outside": 0, "moved": 0, "contrast": 0}
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    for k in range(1, int(ring.max()) + 1):
        ids = valid[ring == k]
        if ids.size == 0:
            continue
        if len(accepted) >= 8:
            a_ids = np.array(sorted(accepted))
            H_new = _fit_h(obj[a_ids], np.array([accepted[i] for i in a_ids]))
            if H_new is not None:
                H = H_new
        pred = _apply_h(H, obj[ids])
        # local square size in px: distance to the predicted neighbours one square right/down
        sq = 0.5 * (np.linalg.norm(_apply_h(H, obj[ids] + [s, 0]) - pred, axis=1)
                    + np.linalg.norm(_apply_h(H, obj[ids] + [0, s]) - pred, axis=1))
        half = np.clip(np.rint(0.25 * sq), 2, 10).astype(int)
        inside = ((pred[:, 0] >= half + 1) & (pred[:, 0] <= w_img - 2 - half)
                  & (pred[:, 1] >= half + 1) & (pred[:, 1] <= h_img - 2 - half) & (sq >= 4))
        rejected_counts["outside"] += int((~inside).sum())
        for j in np.flatnonzero(inside):
            p0 = pred[j].astype(np.float32).reshape(1, 1, 2)
            p = cv2.cornerSubPix(u8, p0.copy(), (int(half[j]), int(half[j])), (-1, -1), crit).reshape(2).astype(np.float64)
            if not np.all(np.isfinite(p)) or np.linalg.norm(p - pred[j]) > max_shift_frac * sq[j]:
                rejected_counts["moved"] += 1
                continue
            # alternation check around the refined corner, offsets mapped through the local homography
            qpts = _apply_h(H, obj[ids[j]] + q_off) - pred[j] + p
            if np.any(qpts < 0) or np.any(qpts[:, 0] > w_img - 1) or np.any(qpts[:, 1] > h_img - 1):
                rejected_counts["outside"] += 1
                continue
            v = sign * _sample(smooth, qpts)
            dark = spec.square_color_dark(c_idx[ring == k][j] + q_dc, r_idx[ring == k][j] + q_dr)
            if dark.all() or not dark.any():
                continue  # not a saddle by construction (cannot happen for valid ids)
            # mean(bright) - mean(dark): the checker alternation; a linear brightness gradient
            # across the corner (uneven heating) cancels in this combination
            if float(v[~dark].mean() - v[dark].mean()) < min_alt:
                rejected_counts["contrast"] += 1
                continue
            accepted[int(ids[j])] = p

    # local consistency: every corner must agree with a homography through its accepted neighbours
    # (within 2 squares); a corner pulled onto the board's outline by the refinement does not.
    # Distortion is nearly projective over 2 squares, so the threshold can be tight.
    n_before = len(accepted)
    for _ in range(6):
        bad = _local_outliers(accepted, obj, cols, s, local_tol_frac)
        if not bad:
            break
        for i in bad:
            del accepted[i]
    rejected_counts["inconsistent"] = n_before - len(accepted)
    n = len(accepted)
    extra = {"marker_px": marker, "inverted": inverted, "marker_method": how, "rejected": rejected_counts,
             "marker_contrast": contrast}
    if n < min_corners:
        return Detection(image_id=str(image_id), found=False, points_px=np.zeros((0, 2)),
                         object_ids=np.zeros(0, np.int64),
                         reason=(f"marker found ({how}) but only {n} corners identified (< {min_corners}); "
                                 f"rejected: {rejected_counts}"), image_size=size, extra=extra)
    a_ids = np.array(sorted(accepted), dtype=np.int64)
    pts = np.array([accepted[i] for i in a_ids])
    return Detection(image_id=str(image_id), found=True, points_px=pts, object_ids=a_ids,
                     reason=(f"marker found ({how}); {n} of {valid.size} corners identified; "
                             f"not identified: {rejected_counts}"),
                     image_size=size, method="aruco-grow", extra=extra)
