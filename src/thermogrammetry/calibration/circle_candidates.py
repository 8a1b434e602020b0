"""Disc candidates of a circle-grid image: the blob detectors and the multi-scale ellipse candidates.

Two sources of candidates for :func:`~thermogrammetry.calibration.detect_circles.detect_circle_grid`:

- a ``cv2.SimpleBlobDetector`` tuned for small, blurred discs (:func:`blob_detector`), whose keypoints
  are redrawn as clean black discs (:func:`redraw_blobs`) for ``cv2.findCirclesGrid`` with
  :data:`REDRAWN_DETECTOR`;
- ellipses fitted to the contours of adaptive thresholds over several scales
  (:func:`ellipse_candidates`), grouped by size (:func:`size_group`) and reduced to one per disc
  (:func:`one_per_disc`): large discs under strong distortion or perspective, low contrast.

References
----------
Vidas, S., Lakemond, R., Denman, S., Fookes, C., Sridharan, S., Wark, T. (2012). A mask-based
approach for the geometric calibration of thermal-infrared cameras. IEEE TIM 61(6), 1625-1635.
Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
thermal imagery (mask grid of holes, contrast enhancement).
"""

from __future__ import annotations

import cv2
import numpy as np

from .detect_common import normalize_to_u8

__all__ = ["blob_detector", "REDRAWN_DETECTOR", "redraw_blobs", "ellipse_candidates", "size_group", "one_per_disc"]


def blob_detector(image_area: float) -> cv2.SimpleBlobDetector:
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


REDRAWN_DETECTOR = _redrawn_detector()


def redraw_blobs(shape, keypoints) -> np.ndarray:
    """A white uint8 image with a black disc at every keypoint (centres to 1/16 px, radius >= 2 px):
    the blob detector finds exactly these, and the grid finder is not slowed by clutter."""
    img = np.full(shape[:2], 255, np.uint8)
    for k in keypoints:
        c = (int(round(k.pt[0] * 16)), int(round(k.pt[1] * 16)))
        rad = int(round(max(2.0, 0.5 * k.size) * 16))
        cv2.circle(img, c, rad, 0, -1, lineType=cv2.LINE_8, shift=4)
    return img


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


def size_group(c: np.ndarray, n: int) -> np.ndarray:
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


def one_per_disc(cand: np.ndarray) -> np.ndarray:
    """One :func:`ellipse_candidates` row per disc: nested contours of one disc at other thresholds
    (centre within a quarter of the minor axis, and area within 4x or found at fewer scales) are dropped."""
    keep = []
    for i in np.lexsort((-cand[:, 4], -cand[:, 5])):
        if all(np.hypot(*(cand[i, :2] - cand[j, :2])) > 0.25 * min(cand[i, 3], cand[j, 3])
               or (max(cand[i, 4], cand[j, 4]) > 4.0 * min(cand[i, 4], cand[j, 4]) and cand[i, 5] >= cand[j, 5])
               for j in keep):
            keep.append(i)
    return cand[np.sort(np.asarray(keep, dtype=int))]
