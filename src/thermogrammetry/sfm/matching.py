"""Image pairs, descriptor matching and geometric verification.

- **Pairs** (:func:`select_pairs`): with GNSS, each image is paired with its ``k`` nearest neighbours in
  plan (and all images within ``radius_m``); without GNSS, with its ``window`` sequence neighbours, and
  all pairs when the block is small (``exhaustive_up_to`` images). Never a blind all-pairs search
  beyond that.
- **Matching** (:func:`match_descriptors`): nearest two neighbours both ways, Lowe's ratio test and a
  mutual (cross) check.
- **Verification** (:func:`verify_pair`): OpenCV's USAC MAGSAC++ essential matrix on the normalised
  (undistorted) image coordinates of the current camera model, with the RANSAC seed fixed; the
  inliers of the essential matrix are the verified matches. Where no camera is known the
  fundamental matrix (MAGSAC++) in pixels is used instead.

References
----------
Lowe, D. G. (2004). Distinctive image features from scale-invariant keypoints. IJCV 60(2), 91-110.
Barath, D., Noskova, J., Ivashechkin, M., Matas, J. (2020). MAGSAC++, a fast, reliable and accurate
robust estimator. CVPR.
Nistér, D. (2004). An efficient solution to the five-point relative pose problem. IEEE PAMI 26(6).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .._validate import config_keys

__all__ = ["MatchOptions", "PairMatches", "select_pairs", "match_descriptors", "verify_pair", "homography_prior", "guided_matches"]


@dataclass(frozen=True)
class MatchOptions:
    """How pairs are chosen and matched (typed; unknown keys refused by :meth:`from_dict`).

    Attributes
    ----------
    ratio : float
        Lowe's ratio (second-nearest / nearest distance must exceed 1/ratio).
    neighbours : int
        GNSS nearest neighbours per image.
    window : int
        Sequence neighbours per image (each side) without GNSS.
    exhaustive_up_to : int
        All pairs when the block has at most this many images and no GNSS.
    max_error_px : float
        Inlier threshold of the verification (px on the image, converted with the focal length).
    min_inliers : int
        A pair with fewer verified matches is dropped.
    max_ransac_iterations : int
        MAGSAC++ iterations at most (4000 finds a 5-point sample free of outliers with 99.99 %
        confidence down to an inlier ratio of ~0.3).
    seed : int
        RANSAC seed (``cv2.setRNGSeed``).
    guided_radius_px : float
        0: off. Otherwise a homography from the ratio-test matches (:func:`homography_prior`) guides a
        second search within this radius (:func:`guided_matches`), kept when it finds more matches
        (low-texture and repetitive frames).
    """

    ratio: float = 0.85
    neighbours: int = 12
    window: int = 8
    exhaustive_up_to: int = 120
    max_error_px: float = 2.0
    min_inliers: int = 20
    max_ransac_iterations: int = 4000
    seed: int = 0
    guided_radius_px: float = 0.0

    def __post_init__(self):
        if not 0 < self.ratio < 1:
            raise ConfigError(f"MatchOptions.ratio={self.ratio!r}: expected a number in (0, 1)")
        if self.min_inliers < 8:
            raise ConfigError(f"MatchOptions.min_inliers={self.min_inliers!r}: expected >= 8")
        if not (np.isfinite(self.guided_radius_px) and self.guided_radius_px >= 0):
            raise ConfigError(f"MatchOptions.guided_radius_px={self.guided_radius_px!r}: expected a number >= 0 (0 = off)")

    @classmethod
    def from_dict(cls, d: dict) -> "MatchOptions":
        return cls(**config_keys(cls, d))


@dataclass
class PairMatches:
    """Verified matches of an image pair.

    Attributes
    ----------
    i, j : int
        Image indices (i < j).
    idx : (M, 2) int32, feature indices in image i and j
    n_putative : int
    model : str, "essential" | "fundamental" | "none"
    reason : str, why the pair was dropped ("" when kept)
    """

    i: int
    j: int
    idx: np.ndarray
    n_putative: int
    model: str = "essential"
    reason: str = ""

    @property
    def ok(self) -> bool:
        return not self.reason


def select_pairs(n_images: int, centers=None, *, options: MatchOptions | None = None, order=None) -> list[tuple[int, int]]:
    """Candidate pairs ``(i, j)``, ``i < j``, sorted.

    Parameters
    ----------
    n_images : int
    centers : (n, 3) array or None
        Approximate positions (GNSS, metres in a projected CRS); rows of NaN = unknown.
    options : MatchOptions
    order : (n,) int or None
        Acquisition order (sequence neighbours); default the index order.
    """
    opt = options or MatchOptions()
    pairs: set[tuple[int, int]] = set()
    order = np.arange(n_images) if order is None else np.asarray(order)
    have = np.zeros(n_images, bool) if centers is None else np.all(np.isfinite(np.asarray(centers, float)), axis=1)
    if n_images <= opt.exhaustive_up_to and have.sum() < 0.5 * n_images:
        return [(i, j) for i in range(n_images) for j in range(i + 1, n_images)]
    # sequence neighbours always (video frames, frames without GNSS)
    for a in range(n_images):
        for b in range(a + 1, min(a + 1 + opt.window, n_images)):
            i, j = int(order[a]), int(order[b])
            pairs.add((min(i, j), max(i, j)))
    if have.sum() >= 2:
        from scipy.spatial import cKDTree

        idx = np.nonzero(have)[0]
        xy = np.asarray(centers, float)[idx, :2]
        tree = cKDTree(xy)
        k = min(opt.neighbours + 1, len(idx))
        _, nn = tree.query(xy, k=k)
        for a, row in enumerate(np.atleast_2d(nn)):
            for b in row[1:]:
                i, j = int(idx[a]), int(idx[b])
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


_SCRATCH = threading.local()


def _scratch(n: int, slot: int) -> np.ndarray:
    """A float32 work array of ``n`` elements, reused by the calls of this thread (``slot`` tells apart the arrays that
    one call uses at the same time). It grows to the largest request and is freed by :func:`release_scratch`."""
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None:
        bufs = _SCRATCH.bufs = {}
    buf = bufs.get(slot)
    if buf is None or buf.size < n:
        buf = bufs[slot] = np.empty(n, np.float32)
    return buf[:n]


def release_scratch() -> None:
    """Free this thread's matching work arrays (after the matching step)."""
    _SCRATCH.bufs = {}


def _unit_rows(d: np.ndarray, tol: float = 1e-3) -> bool:
    n = np.einsum("ij,ij->i", d, d, dtype=np.float64) if len(d) else np.ones(0)
    return bool(np.all(np.abs(n - 1.0) < tol))


def match_descriptors(d1: np.ndarray, d2: np.ndarray, *, ratio: float = 0.85) -> np.ndarray:
    """Ratio-test + mutual nearest-neighbour matches.

    Parameters
    ----------
    d1, d2 : (N1, D), (N2, D) float32 (L2) or uint8 (Hamming) descriptors

    Returns
    -------
    (M, 2) int32 index pairs into d1 and d2
    """
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), np.int32)
    if d1.dtype == np.uint8:
        import cv2

        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        D = None

        def best(a, b):
            knn = bf.knnMatch(a, b, k=2)
            m = np.full(len(a), -1, np.int64)
            for q, pair in enumerate(knn):
                if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
                    m[q] = pair[0].trainIdx
            return m

        m12, m21 = best(d1, d2), best(d2, d1)
    elif _unit_rows(d1) and _unit_rows(d2):
        # unit-norm descriptors (RootSIFT): |a - b|^2 = 2 - 2 a.b, so the nearest neighbours are the largest dot
        # products; each direction reduces along contiguous rows of its own product (2x faster than the
        # general path, which spends most of its time in element-wise passes over the distance matrix)
        a = np.ascontiguousarray(d1, np.float32)
        b = np.ascontiguousarray(d2, np.float32)

        def best_rows(S):
            # nearest and second-nearest along contiguous rows; S is modified and restored
            r = np.arange(len(S))
            j = S.argmax(axis=1)
            s1 = S[r, j].copy()
            S[r, j] = -np.inf
            s2 = S.max(axis=1)
            S[r, j] = s1
            dmin = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
            dsec = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
            return np.where(dmin < ratio * dsec, j, -1)

        # the products go into this thread's scratch arrays: a fresh 36 MB product per pair (3000 x 3000) is mapped
        # and zeroed page by page on first touch, which cost as much as the product itself (M3T flight: 17 -> 10 ms)
        S = np.matmul(a, b.T, out=_scratch(len(a) * len(b), 0).reshape(len(a), len(b)))
        m12 = best_rows(S)
        # the mutual check needs the reverse match only of the columns that some row chose: a second product of those
        # descriptors, reduced along its contiguous rows (each dot product is the same sum as in S; 5 ms where gathering
        # S's columns through NumPy's strided indexing took 13-30 ms)
        cols = np.unique(m12[m12 >= 0])
        m21 = np.full(len(b), -1, np.int64)
        if len(cols):
            m21[cols] = best_rows(np.matmul(b[cols], a.T, out=_scratch(len(cols) * len(a), 1).reshape(len(cols), len(a))))
    else:
        # squared Euclidean distances by one matrix product (float64 accumulation of float32 inputs)
        a = np.asarray(d1, np.float32)
        b = np.asarray(d2, np.float32)
        D = a @ b.T
        D *= -2.0
        D += (a * a).sum(1)[:, None]
        D += (b * b).sum(1)[None, :]
        np.maximum(D, 0.0, out=D)

        def best(D, axis):
            # nearest and second-nearest along ``axis`` without copying or transposing D
            first = np.argmin(D, axis=axis)
            r = np.arange(D.shape[1 - axis])
            at = (r, first) if axis == 1 else (first, r)
            dmin = D[at].copy()
            D[at] = np.inf
            dsec = D.min(axis=axis)
            D[at] = dmin
            ok = np.sqrt(dmin) < ratio * np.sqrt(dsec)
            return np.where(ok, first, -1)

        m12 = best(D, 1)
        m21 = best(D, 0)
    q = np.nonzero(m12 >= 0)[0]
    keep = q[m21[m12[q]] == q]
    return np.stack([keep, m12[keep]], axis=1).astype(np.int32)


def verify_pair(xy1: np.ndarray, xy2: np.ndarray, matches: np.ndarray, *, camera1=None, camera2=None,
                rays1=None, rays2=None, options: MatchOptions | None = None) -> tuple[np.ndarray, str, str]:
    """Geometric verification of putative matches.

    Parameters
    ----------
    xy1, xy2 : (N1, 2), (N2, 2) px keypoints
    matches : (M, 2) int putative index pairs
    camera1, camera2 : thermogrammetry.Camera or None
        When given, the essential matrix is estimated on normalised coordinates (distortion removed).
    rays1, rays2 : (N1, 2), (N2, 2) or None
        Normalised coordinates of all keypoints, precomputed once per image (``camera.unproject``);
        used instead of unprojecting again.

    Returns
    -------
    inliers : (K, 2) int32 verified index pairs
    model : "essential" | "fundamental"
    reason : "" or why the pair failed
    """
    import cv2

    opt = options or MatchOptions()
    if len(matches) < opt.min_inliers:
        return np.zeros((0, 2), np.int32), "none", f"{len(matches)} putative matches < {opt.min_inliers}"
    p1 = xy1[matches[:, 0]]
    p2 = xy2[matches[:, 1]]
    cv2.setRNGSeed(int(opt.seed))
    if camera1 is not None and camera2 is not None:
        n1 = rays1[matches[:, 0]] if rays1 is not None else camera1.unproject(p1)[:, :2]
        n2 = rays2[matches[:, 1]] if rays2 is not None else camera2.unproject(p2)[:, :2]
        f = 0.5 * (float(np.mean(np.diag(camera1.K)[:2])) + float(np.mean(np.diag(camera2.K)[:2])))
        E, mask = cv2.findEssentialMat(np.ascontiguousarray(n1), np.ascontiguousarray(n2), np.eye(3), method=cv2.USAC_MAGSAC,
                                       prob=0.9999, threshold=opt.max_error_px / f, maxIters=opt.max_ransac_iterations)
        model = "essential"
    else:
        E, mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, opt.max_error_px, 0.9999, opt.max_ransac_iterations)
        model = "fundamental"
    if E is None or mask is None:
        return np.zeros((0, 2), np.int32), model, "no geometric model found"
    inl = matches[mask.ravel().astype(bool)]
    if len(inl) < opt.min_inliers:
        return np.zeros((0, 2), np.int32), model, f"{len(inl)} verified matches < {opt.min_inliers}"
    return inl.astype(np.int32), model, ""


def homography_prior(xy1: np.ndarray, xy2: np.ndarray, matches: np.ndarray, *, threshold_px: float = 3.0,
                     min_inliers: int = 8, seed: int = 0) -> np.ndarray | None:
    """A homography ``x2 ~ H x1`` from a few putative matches (MAGSAC++), or None.

    Low-texture pairs pass the ratio test with a few dozen matches only -- too few for the essential
    matrix, enough for a homography that predicts where every keypoint of image 1 lands in image 2
    (walls are nearly planar; parallax is absorbed by the search radius of :func:`guided_matches`).

    Parameters
    ----------
    xy1, xy2 : (N1, 2), (N2, 2) px keypoints
    matches : (M, 2) int putative index pairs
    threshold_px : float
        MAGSAC++ inlier threshold (px).
    min_inliers : int
    seed : int

    Returns
    -------
    (3, 3) float64 or None
    """
    import cv2

    if len(matches) < max(min_inliers, 4):
        return None
    cv2.setRNGSeed(int(seed))
    H, mask = cv2.findHomography(np.ascontiguousarray(xy1[matches[:, 0]]), np.ascontiguousarray(xy2[matches[:, 1]]),
                                 cv2.USAC_MAGSAC, threshold_px, maxIters=4000, confidence=0.9999)
    if H is None or mask is None or int(mask.sum()) < min_inliers or not np.all(np.isfinite(H)):
        return None
    return H


def guided_matches(xy1: np.ndarray, d1: np.ndarray, xy2: np.ndarray, d2: np.ndarray, H: np.ndarray, *,
                   radius_px: float = 10.0, ratio: float = 0.9, max_candidates: int = 16) -> np.ndarray:
    """Matches searched only near where ``H`` predicts each keypoint (guided matching).

    Each keypoint of image 1 is mapped by ``H``; its match is the nearest descriptor among the keypoints
    of image 2 within ``radius_px`` of the prediction, kept when it passes the ratio test against the
    second-nearest *in that neighbourhood*. Repeated structure (identical windows, tiles) and weak
    texture, which defeat a global ratio test, are disambiguated by position. Each keypoint of image 2
    is used once (the closest descriptor wins).

    Parameters
    ----------
    xy1, xy2 : (N1, 2), (N2, 2) px
    d1, d2 : (N1, D), (N2, D) float32 descriptors (Euclidean)
    H : (3, 3) homography, image 1 -> image 2
    radius_px, ratio : float
    max_candidates : int
        Keypoints of image 2 considered per prediction (nearest first).

    Returns
    -------
    (M, 2) int32 index pairs

    References
    ----------
    Hartley, R., Zisserman, A. (2004). Multiple View Geometry, 2nd ed., sec. 11.6 (guided matching).
    """
    from scipy.spatial import cKDTree

    if len(xy1) == 0 or len(xy2) == 0:
        return np.zeros((0, 2), np.int32)
    p = np.c_[xy1, np.ones(len(xy1))] @ np.asarray(H, float).T
    with np.errstate(all="ignore"):
        p = p[:, :2] / p[:, 2:3]
    ok = np.all(np.isfinite(p), axis=1)
    k = int(min(max_candidates, len(xy2)))
    dist, idx = cKDTree(xy2).query(np.where(ok[:, None], p, 1e12), k=k, distance_upper_bound=radius_px)
    dist, idx = dist.reshape(len(p), k), idx.reshape(len(p), k)
    near = np.isfinite(dist) & ok[:, None]
    idx_c = np.where(near, idx, 0)
    dd = np.linalg.norm(np.asarray(d2, np.float32)[idx_c] - np.asarray(d1, np.float32)[:, None, :], axis=2)
    dd = np.where(near, dd, np.inf)
    o = np.argsort(dd, axis=1, kind="stable")
    r = np.arange(len(p))
    best = dd[r, o[:, 0]]
    second = dd[r, o[:, 1]] if k > 1 else np.full(len(p), np.inf)
    keep = np.isfinite(best) & (best < ratio * second)
    q = np.nonzero(keep)[0]
    if len(q) == 0:
        return np.zeros((0, 2), np.int32)
    j = idx_c[q, o[q, 0]]
    # one use per keypoint of image 2: the closest descriptor wins
    order = np.lexsort((best[q], j))
    q, j = q[order], j[order]
    first = np.r_[True, j[1:] != j[:-1]]
    m = np.stack([q[first], j[first]], axis=1).astype(np.int32)
    return m[np.argsort(m[:, 0], kind="stable")]
