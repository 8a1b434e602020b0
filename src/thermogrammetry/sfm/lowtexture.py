"""Tie points for low-texture frame sequences: sensor pattern removed, corners tracked frame to frame (KLT).

Thermal frames of a plain wall carry a few tenths of a kelvin of smooth scene contrast, and the finest texture
in them is the sensor's own (fixed pattern, temporal noise). Descriptor matching fails there: keypoints are not
repeatable and their descriptors are alike. A walk or a video along such a wall is, however, a *sequence* with a
large overlap between consecutive frames, and a sequence is what a tracker uses:

1. each frame is prepared for tracking (:func:`tracking_image`): the sensor's fixed pattern (estimated from the
   frames, :func:`~thermogrammetry.sfm.features.fixed_pattern`; only its fine part, the scene's large structure
   that stays at the same rows in a horizontal walk is kept) is subtracted, the temporal noise smoothed, the
   background removed and the result scaled by its robust spread to 8 bits;
2. the motion between consecutive frames is found from the whole images (phase correlation), then refined by
   pyramidal Lucas-Kanade tracking of corners and a homography fitted to them (MAGSAC++), which predicts where
   every point lands;
3. points are tracked from frame to frame (pyramidal Lucas-Kanade started at the prediction), kept when the
   backward track returns within ``fb_max_px`` and the pair's essential matrix (MAGSAC++, fixed seed) accepts
   them; each track is refined against its first observation (no drift along the track); new corners
   (Shi-Tomasi) are added where the tracks thin out.

The result is one feature list per frame and the verified matches of consecutive frames; tracks are the chains
of these matches. Only consecutive frames are matched, so structure that repeats (identical windows) can only
mislead a consecutive pair, whose overlap is the largest.

References
----------
Lucas, B. D., Kanade, T. (1981). An iterative image registration technique with an application to stereo vision.
Shi, J., Tomasi, C. (1994). Good features to track. CVPR.
Bouguet, J.-Y. (2000). Pyramidal implementation of the Lucas Kanade feature tracker. Intel.
Kalal, Z., Mikolajczyk, K., Matas, J. (2010). Forward-backward error: automatic detection of tracking failures. ICPR.
Kuglin, C. D., Hines, D. C. (1975). The phase correlation image alignment method.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._sampling import fill_smooth
from ..errors import ConfigError

#: a track is refined against its first observation while that frame is at most this many frames back (the frames
#: held in memory are bounded by it)
ANCHOR_FRAMES = 8

__all__ = ["TrackingOptions", "SequenceTracks", "tracking_image", "frame_motion", "track_sequence", "PlaneParallax",
           "plane_parallax"]


@dataclass(frozen=True)
class TrackingOptions:
    """How a low-texture sequence is tracked (pixels of the frames).

    Attributes
    ----------
    smooth_sigma_px : float
        Gaussian smoothing of the temporal noise before tracking.
    background_sigma_px : float
        Blur removed as background (gradients, vignetting).
    pattern_sigma_px : float
        Only the fixed pattern's part finer than this blur is subtracted (0: all of it).
    max_corners : int
        Points per frame (tracked ones + new corners).
    min_distance_px : float
        Shi-Tomasi minimum distance between points.
    window_px : int
        Lucas-Kanade window (odd).
    levels : int
        Pyramid levels of the tracking from the predicted position.
    fb_max_px : float
        Largest forward-backward error kept.
    max_error_px : float
        Inlier threshold of the pair's essential matrix (px).
    min_inliers : int
        A consecutive pair with fewer verified tracks breaks the sequence there.
    max_drift_px : float
        The refinement against a track's first observation is kept within this distance of the chained position.
    max_incoherence_px : float
        > 0: a track whose displacement differs from the median of its 8 nearest neighbours' by more (after the
        frame's homography) is dropped (:func:`_coherent`). Off (0) by default: at 2 px it cost the ground's parallax
        (synthetic walk, seed 0: rotations 0.87 -> 2.05 deg RMS) and did not remove the glass-reflection tracks of the
        windowed facade.
    min_ncc : float
        Normalised cross-correlation of a track's windows in the two frames, at least (measured: tracks of the
        synthetic plain wall 0.66 and of the windowed facade 0.56 at their 1st percentile; Lucas-Kanade "tracks"
        between frames of pure noise 0.43 at their 99th).
    min_eigen_ratio : float
        Points are only started where the structure tensor over the tracking window has a smaller/larger
        eigenvalue ratio of at least this (texture in two directions).
    seed : int
        RANSAC seed.
    """

    smooth_sigma_px: float = 3.0
    background_sigma_px: float = 10.0
    pattern_sigma_px: float = 0.0
    max_corners: int = 800
    min_distance_px: float = 10.0
    window_px: int = 51
    levels: int = 2
    fb_max_px: float = 1.0
    max_error_px: float = 2.0
    min_inliers: int = 30
    max_drift_px: float = 1.0
    min_eigen_ratio: float = 0.2
    max_incoherence_px: float = 0.0
    min_ncc: float = 0.5
    seed: int = 0

    def __post_init__(self):
        if not (isinstance(self.window_px, (int, np.integer)) and self.window_px >= 5 and self.window_px % 2 == 1):
            raise ConfigError(f"TrackingOptions.window_px={self.window_px!r}: expected an odd integer >= 5")
        if not (isinstance(self.max_corners, (int, np.integer)) and self.max_corners >= 20):
            raise ConfigError(f"TrackingOptions.max_corners={self.max_corners!r}: expected an integer >= 20")
        for f in ("smooth_sigma_px", "background_sigma_px", "pattern_sigma_px", "min_distance_px", "fb_max_px",
                  "max_error_px", "max_drift_px"):
            v = float(getattr(self, f))
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"TrackingOptions.{f}={getattr(self, f)!r}: expected a number >= 0")
        if self.min_inliers < 8:
            raise ConfigError(f"TrackingOptions.min_inliers={self.min_inliers!r}: expected >= 8")


def tracking_image(frame, pattern=None, options: TrackingOptions | None = None, *,
                   scale: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """A frame prepared for tracking: 8-bit, pattern removed, noise smoothed, background removed, robustly scaled.

    Parameters
    ----------
    frame : (H, W) array, any numeric dtype (kelvin, counts); NaN = invalid
    pattern : (H, W) float or None
        The sensor's fixed pattern in the frame's unit (:func:`~thermogrammetry.sfm.features.fixed_pattern`).
    options : TrackingOptions
    scale : (centre, sigma) or None
        The 8-bit mapping; None: from this frame (median and MAD of the band-passed values). A sequence is mapped
        with ONE scale: Lucas-Kanade has no gain or offset term, and on smooth low-contrast frames a gain
        difference of a few percent between two frames biases the tracks by a pixel.

    Returns
    -------
    img8 : (H, W) uint8, 128 + 24 · (band-passed value − centre) / sigma, clipped
    valid : (H, W) bool, pixels whose neighbourhood (window) is valid
    scale : (centre, sigma) used
    """
    import cv2

    opt = options or TrackingOptions()
    a = np.asarray(frame, np.float32)
    if a.ndim != 2:
        raise ConfigError(f"frame: expected a 2D frame, got shape {a.shape}")
    valid = np.isfinite(a)
    if not valid.any():
        return np.zeros(a.shape, np.uint8), valid, (0.0, 1.0) if scale is None else scale
    if not valid.all():  # no-data (NaN, a masked display) filled smoothly: no edge at its border
        a = fill_smooth(a, valid)
    if pattern is not None and np.shape(pattern) == a.shape:
        p = np.asarray(pattern, np.float32)
        if opt.pattern_sigma_px > 0:
            p = p - cv2.GaussianBlur(p, (0, 0), opt.pattern_sigma_px)
        a = a - p
    if opt.smooth_sigma_px > 0:
        a = cv2.GaussianBlur(a, (0, 0), opt.smooth_sigma_px)
    if opt.background_sigma_px > 0:
        a = a - cv2.GaussianBlur(a, (0, 0), opt.background_sigma_px)
    if scale is None:
        d = a[valid]
        c = float(np.median(d))
        s = 1.4826 * float(np.median(np.abs(d - c)))
        if not s > 0:
            s = float(np.std(d)) or 1.0
        scale = (c, s)
    img8 = np.clip(128.0 + 24.0 * (a - scale[0]) / scale[1], 0, 255).astype(np.uint8)
    if not valid.all():
        valid = cv2.erode(valid.astype(np.uint8), np.ones((opt.window_px, opt.window_px), np.uint8)).astype(bool)
    return img8, valid, scale


def _lk(img_a, img_b, pa, pb0, opt: TrackingOptions, levels: int):
    """Pyramidal LK a -> b from the predictions pb0, checked backwards: (pb (N, 2), ok (N,))."""
    import cv2

    if len(pa) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.005)
    win = (int(opt.window_px), int(opt.window_px))
    pa32 = np.ascontiguousarray(pa, np.float32).reshape(-1, 1, 2)
    pb32 = np.ascontiguousarray(pb0, np.float32).reshape(-1, 1, 2)
    pb, st, _ = cv2.calcOpticalFlowPyrLK(img_a, img_b, pa32, pb32.copy(), winSize=win, maxLevel=int(levels),
                                         criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(img_b, img_a, pb, pa32.copy(), winSize=win, maxLevel=int(levels),
                                            criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    pb = pb.reshape(-1, 2).astype(np.float64)
    fb = np.linalg.norm(back.reshape(-1, 2) - pa.reshape(-1, 2), axis=1)
    h, w = img_b.shape
    inside = (pb[:, 0] >= 0) & (pb[:, 0] <= w - 1) & (pb[:, 1] >= 0) & (pb[:, 1] <= h - 1)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb <= opt.fb_max_px) & inside & np.all(np.isfinite(pb), axis=1)
    return pb, ok


def _corners(img8, valid, opt: TrackingOptions, existing=None, n: int | None = None) -> np.ndarray:
    """Corners spread over the frame: the strongest Shi-Tomasi response (smallest eigenvalue of the structure tensor
    over a 9 px block) in every cell of a regular grid, cells sized for ``n`` points (at least ``min_distance_px``);
    none within ``min_distance_px`` of ``existing`` points, none in cells whose response is below a tenth of the
    median cell's (flat). A plain "strongest N" would put them all on the one strong edge of a plain wall -- its
    foot, where the ground meets it, and where nothing moves like a single plane."""
    import cv2

    n = int(opt.max_corners if n is None else n)
    h, w = img8.shape
    if n <= 0:
        return np.zeros((0, 2))
    eig = cv2.cornerMinEigenVal(img8, 9, ksize=3)
    eig[~valid] = 0.0
    # the tracker's window must see texture in two directions: on smooth frames a window is often a ramp (its
    # structure tensor nearly singular) and the track slides along it; measured on the synthetic wall (clean
    # frames, 41 px windows): tracks with eigenvalue ratio < 0.1 err by 1.2 px (median), >= 0.2 by 0.43 px
    f = img8.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
    win = (int(opt.window_px), int(opt.window_px))
    jxx, jyy, jxy = (cv2.boxFilter(g, -1, win) for g in (gx * gx, gy * gy, gx * gy))
    tr = jxx + jyy
    disc = np.sqrt(np.maximum(0.25 * tr * tr - (jxx * jyy - jxy * jxy), 0.0))
    ratio = (0.5 * tr - disc) / np.maximum(0.5 * tr + disc, 1e-12)
    eig[ratio < opt.min_eigen_ratio] = 0.0
    if existing is not None and len(existing):
        mask = np.ones((h, w), np.uint8)
        r = max(1, int(round(opt.min_distance_px)))
        for x, y in np.round(existing).astype(int):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        eig[mask == 0] = 0.0
    cell = int(max(round(opt.min_distance_px), np.ceil(np.sqrt(h * w / max(opt.max_corners, 1)))))
    ny, nx = h // cell, w // cell
    if ny == 0 or nx == 0:
        return np.zeros((0, 2))
    oy, ox = (h - ny * cell) // 2, (w - nx * cell) // 2
    blocks = eig[oy:oy + ny * cell, ox:ox + nx * cell].reshape(ny, cell, nx, cell).transpose(0, 2, 1, 3).reshape(ny, nx, -1)
    arg = blocks.argmax(axis=2)
    best = np.take_along_axis(blocks, arg[..., None], axis=2)[..., 0]
    pos = best[best > 0]
    if not len(pos):
        return np.zeros((0, 2))
    keep = best > 0.1 * float(np.median(pos))
    cy, cx = np.nonzero(keep)
    a = arg[cy, cx]
    xy = np.c_[ox + cx * cell + a % cell, oy + cy * cell + a // cell].astype(np.float64)
    order = np.argsort(-best[cy, cx], kind="stable")[:n]
    return xy[np.sort(order)]


def _shift_candidates(img_a, img_b, n: int = 4) -> list[np.ndarray]:
    """The ``n`` strongest peaks of the phase correlation of two frames at a quarter of their resolution: shifts
    ``d`` (px, full resolution) with ``b(x + d) ≈ a(x)``, strongest first.

    Phase correlation whitens the spectrum, so the finest structure weighs as much as the coarse: what is left of
    the sensor's pattern (it does not move) makes a peak at zero that can beat the scene's -- hence a quarter of the
    resolution (the texture of a plain wall is coarse) and several candidates, each tried by the tracker."""
    import cv2

    a = cv2.pyrDown(cv2.pyrDown(img_a.astype(np.float32)))
    b = cv2.pyrDown(cv2.pyrDown(img_b.astype(np.float32)))
    h, w = a.shape
    win = cv2.createHanningWindow((w, h), cv2.CV_32F)
    A = np.fft.rfft2((a - a.mean()) * win)
    B = np.fft.rfft2((b - b.mean()) * win)
    R = np.conj(A) * B
    R /= np.maximum(np.abs(R), 1e-12)
    r = np.fft.irfft2(R, s=(h, w))
    r = cv2.GaussianBlur(np.fft.fftshift(r).astype(np.float32), (0, 0), 1.0)
    out = []
    for _ in range(n):
        k = int(np.argmax(r))
        y, x = divmod(k, w)
        if not np.isfinite(r[y, x]) or r[y, x] <= 0:
            break
        out.append(4.0 * np.array([x - w // 2, y - h // 2], float))
        r[max(0, y - 3):y + 4, max(0, x - 3):x + 4] = -np.inf
    return out


def frame_motion(img_a, valid_a, img_b, options: TrackingOptions | None = None, *, prior=None) -> tuple[np.ndarray | None, str]:
    """Homography ``x_b ~ H x_a`` between two overlapping frames of a sequence, from the images alone.

    Candidate translations come from the phase correlation of the whole frames (:func:`_shift_candidates`) and from
    ``prior`` (e.g. the previous pair's motion: a walk keeps its pace); from each, corners of ``a`` are tracked into
    ``b`` (pyramidal LK, 2 more levels than the tracking) and a homography is fitted to them (MAGSAC++, 2 px). The
    candidate with the most inliers wins.

    Returns
    -------
    H : (3, 3) or None
    reason : "" or why no motion was found
    """
    import cv2

    opt = options or TrackingOptions()
    pts = _corners(img_a, valid_a, opt, n=min(opt.max_corners, 400))
    if len(pts) < opt.min_inliers:
        return None, f"{len(pts)} corners in the first frame"
    starts = []
    if prior is not None:
        q = np.c_[pts, np.ones(len(pts))] @ np.asarray(prior, float).T
        starts.append(q[:, :2] / q[:, 2:3])
    starts += [pts + d for d in _shift_candidates(img_a, img_b)]
    best, why = None, "no candidate motion"
    for p0 in starts:
        pb, ok = _lk(img_a, img_b, pts, p0, opt, opt.levels + 2)
        if ok.sum() < opt.min_inliers:
            why = f"{int(ok.sum())} corners tracked from the candidate shifts"
            continue
        cv2.setRNGSeed(int(opt.seed))
        H, mask = cv2.findHomography(np.ascontiguousarray(pts[ok]), np.ascontiguousarray(pb[ok]), cv2.USAC_MAGSAC, 2.0,
                                     maxIters=4000, confidence=0.9999)
        if H is None or mask is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
            why = "no homography from the tracked corners"
            continue
        n_in = int(mask.sum())
        if n_in >= opt.min_inliers and (best is None or n_in > best[0]):
            best = (n_in, H / H[2, 2])
        elif best is None:
            why = f"{n_in} corners agree with a homography"
    return (None, why) if best is None else (best[1], "")


@dataclass
class SequenceTracks:
    """Features and verified consecutive matches of a tracked sequence.

    Attributes
    ----------
    xy : list of (N_k, 2) float64 per frame, px (OpenCV convention)
    matches : dict (k, k + 1) -> (M, 2) int32 feature indices in frames k and k + 1
    reasons : dict (k, k + 1) -> str, why a consecutive pair has no matches ("" when it has)
    n_putative : dict (k, k + 1) -> int, tracks that survived the forward-backward check
    """

    xy: list
    matches: dict
    reasons: dict
    n_putative: dict


def _ncc(img_a, img_b, pa, pb, size: int) -> np.ndarray:
    """Normalised cross-correlation of the ``size`` x ``size`` patches at ``pa`` in a and ``pb`` in b (sub-pixel)."""
    import cv2

    out = np.zeros(len(pa))
    fa, fb = img_a.astype(np.float32), img_b.astype(np.float32)
    for k, (p, q) in enumerate(zip(pa, pb)):
        A = cv2.getRectSubPix(fa, (size, size), (float(p[0]), float(p[1]))).ravel()
        B = cv2.getRectSubPix(fb, (size, size), (float(q[0]), float(q[1]))).ravel()
        A = A - A.mean()
        B = B - B.mean()
        den = np.sqrt(float(A @ A) * float(B @ B))
        out[k] = float(A @ B) / den if den > 0 else 0.0
    return out


def _coherent(pa, pb, H, ok, opt: TrackingOptions, k: int = 8) -> np.ndarray:
    """Motion coherence: a track's displacement (minus the frame homography's) must agree with the median of its
    ``k`` nearest neighbours' within ``max_incoherence_px``. A point that slides along an edge or a window's reveal
    stays on its epipolar line (the essential matrix keeps it) but leaves its neighbours; depth steps (the ground
    in front of the wall, recesses) move whole neighbourhoods and are kept."""
    from scipy.spatial import cKDTree

    keep = np.zeros(len(pa), bool)
    idx = np.nonzero(ok)[0]
    if len(idx) <= k:
        keep[idx] = True
        return keep
    q = np.c_[pa[idx], np.ones(len(idx))] @ np.asarray(H, float).T
    res = pb[idx] - q[:, :2] / q[:, 2:3]
    _, nb = cKDTree(pa[idx]).query(pa[idx], k=k + 1)
    med = np.median(res[nb[:, 1:]], axis=1)
    keep[idx] = np.linalg.norm(res - med, axis=1) <= opt.max_incoherence_px
    return keep


def _verify(pa, pb, cam_a, cam_b, opt: TrackingOptions) -> np.ndarray:
    """Inlier mask of the essential matrix (normalised coordinates of the cameras) or the fundamental matrix."""
    import cv2

    cv2.setRNGSeed(int(opt.seed))
    if cam_a is not None and cam_b is not None:
        na = cam_a.unproject(pa)[:, :2]
        nb = cam_b.unproject(pb)[:, :2]
        f = 0.5 * (float(np.mean(np.diag(cam_a.K)[:2])) + float(np.mean(np.diag(cam_b.K)[:2])))
        E, mask = cv2.findEssentialMat(np.ascontiguousarray(na), np.ascontiguousarray(nb), np.eye(3), method=cv2.USAC_MAGSAC,
                                       prob=0.9999, threshold=opt.max_error_px / f, maxIters=4000)
    else:
        E, mask = cv2.findFundamentalMat(np.ascontiguousarray(pa), np.ascontiguousarray(pb), cv2.USAC_MAGSAC,
                                         opt.max_error_px, 0.9999, 4000)
    if E is None or mask is None:
        return np.zeros(len(pa), bool)
    return mask.ravel().astype(bool)


def track_sequence(load, n_frames: int, *, pattern=None, cameras=None, options: TrackingOptions | None = None) -> SequenceTracks:
    """Track a frame sequence (in acquisition order) and verify every consecutive pair.

    Parameters
    ----------
    load : callable k -> (H, W) frame
        Frames are read one at a time (two are held).
    n_frames : int
    pattern : (H, W) or None, the sensor's fixed pattern (frame unit)
    cameras : list of Camera or None
        Camera model of each frame (essential-matrix verification on normalised coordinates); None: fundamental
        matrix in pixels.
    options : TrackingOptions

    Returns
    -------
    SequenceTracks
        Deterministic for given frames and options.
    """
    opt = options or TrackingOptions()
    xy = [np.zeros((0, 2)) for _ in range(n_frames)]
    matches, reasons, nput = {}, {}, {}
    if n_frames == 0:
        return SequenceTracks(xy, matches, reasons, nput)
    anchors: dict[int, tuple] = {}  # frame -> (img8) of frames that are first observations of live tracks
    img_prev, val_prev, scale = tracking_image(load(0), pattern, opt)
    cur = _corners(img_prev, val_prev, opt)
    xy[0] = cur.copy()
    # live tracks: position in the previous frame, feature index there, anchor frame and anchor position
    live_idx = np.arange(len(cur))
    live_anchor = np.zeros(len(cur), int)
    live_apos = cur.copy()
    anchors[0] = img_prev
    H_prev = None
    for k in range(1, n_frames):
        img, val, _ = tracking_image(load(k), pattern, opt, scale=scale)
        pos_prev = xy[k - 1][live_idx] if len(live_idx) else np.zeros((0, 2))
        H, why = frame_motion(img_prev, val_prev, img, opt, prior=H_prev)
        H_prev = H if H is not None else H_prev
        new_feats = np.zeros((0, 2))
        kept_prev = np.zeros((0,), int)
        if H is None:
            reasons[(k - 1, k)] = why
            nput[(k - 1, k)] = 0
        else:
            pred = np.c_[pos_prev, np.ones(len(pos_prev))] @ H.T
            pred = pred[:, :2] / pred[:, 2:3]
            pb, ok = _lk(img_prev, img, pos_prev, pred, opt, opt.levels)
            ok &= val[np.clip(np.round(pb[:, 1]).astype(int), 0, img.shape[0] - 1),
                      np.clip(np.round(pb[:, 0]).astype(int), 0, img.shape[1] - 1)] if len(pb) else ok
            # refine against the track's first observation (the chained position drifts a little at every step)
            for a in np.unique(live_anchor[ok]):
                if a == k - 1 or a not in anchors:
                    continue
                sel = np.nonzero(ok & (live_anchor == a))[0]
                pr, okr = _lk(anchors[a], img, live_apos[sel], pb[sel], opt, 0)
                close = okr & (np.linalg.norm(pr - pb[sel], axis=1) <= opt.max_drift_px)
                pb[sel[close]] = pr[close]
            if opt.max_incoherence_px > 0:
                ok &= _coherent(pos_prev, pb, H, ok, opt)
            if ok.any():  # the patches must look alike: in frames of pure noise Lucas-Kanade still converges somewhere
                sel = np.nonzero(ok)[0]
                ok[sel[_ncc(img_prev, img, pos_prev[sel], pb[sel], opt.window_px) < opt.min_ncc]] = False
            nput[(k - 1, k)] = int(ok.sum())
            cams = (cameras[k - 1], cameras[k]) if cameras is not None else (None, None)
            good = np.nonzero(ok)[0]
            if len(good) >= opt.min_inliers:
                inl = _verify(pos_prev[good], pb[good], cams[0], cams[1], opt)
                good = good[inl]
            if len(good) >= opt.min_inliers:
                kept_prev = good
                new_feats = pb[good]
                reasons[(k - 1, k)] = ""
            else:
                reasons[(k - 1, k)] = f"{len(good)} verified tracks < {opt.min_inliers}"
        # features of frame k: the tracks carried on, then new corners where they thin out
        n_keep = len(new_feats)
        fresh = _corners(img, val, opt, existing=new_feats, n=max(opt.max_corners - n_keep, 0))
        xy[k] = np.vstack([new_feats, fresh]) if len(fresh) else new_feats
        if n_keep:
            matches[(k - 1, k)] = np.stack([live_idx[kept_prev], np.arange(n_keep)], axis=1).astype(np.int32)
        live_anchor = np.r_[live_anchor[kept_prev], np.full(len(fresh), k)].astype(int)
        live_apos = np.vstack([live_apos[kept_prev], fresh]) if len(fresh) else live_apos[kept_prev]
        live_idx = np.arange(len(xy[k]))
        anchors[k] = img
        used = set(np.unique(live_anchor).tolist())
        for a in [a for a in anchors if a not in used or a < k - ANCHOR_FRAMES]:
            del anchors[a]
        img_prev, val_prev = img, val
    return SequenceTracks(xy, matches, reasons, nput)


@dataclass
class PlaneParallax:
    """Whether an oriented block reconstructs flat what its frames show flat (:func:`plane_parallax`).

    Attributes
    ----------
    pairs : list of (i, j, n_common, homography_share, median_parallax_px)
        Consecutive oriented frames of the block with enough common points.
    median_parallax_px : float
        Median over the pairs of the median plane parallax (px); NaN without a usable pair.
    residual_rms_px : float
        RMS reprojection residual (length of the residual vector) of the block's valid observations.
    ratio : float
        ``median_parallax_px / residual_rms_px`` (NaN when either is undefined).
    planar_share : float
        Mean over the pairs of the share of their common 3D points within ``depth_band`` x the median depth of one
        plane (RANSAC, fixed seed); NaN without a usable pair.
    """

    pairs: list
    median_parallax_px: float
    residual_rms_px: float
    ratio: float
    planar_share: float = float("nan")


def plane_parallax(cameras, image_camera, R, t, points, track, image, feature, obs_valid, xy, images, *,
                   tol_px: float = 2.0, min_points: int = 30, depth_band: float = 0.01, seed: int = 0) -> PlaneParallax:
    """Plane parallax of image-coplanar points: do the block's 3D points lie flat where its frames say they are flat?

    For each pair of consecutive oriented frames (i, j) of the block (in index order, i.e. acquisition order of a
    sequence), the points observed in both are split by the frames alone: those whose observations agree with one
    homography (MAGSAC++, ``tol_px``, fixed seed) are coplanar in the scene as far as the images can tell (a wall).
    Their 3D points are fitted with a plane (iteratively reweighted, 3 MAD); each point's *plane parallax* is the
    distance in frame j between the point and its twin on that plane along the ray of frame i. In a right block it
    is the triangulation noise of the observations (measured on the synthetic low-texture walks, 0.15 K, seeds 0-3:
    0.31-0.42 px for residuals of 0.74 px RMS, ratio 0.42-0.57); a block that bends to fit wrong intrinsics or
    inconsistent tracks (the windowed facade, glass reflections, focal length a guess 40 % short) puts the same
    points off their plane: 0.93 px for 0.72 px RMS, ratio 1.29.

    The *planar share* asks the same of all common points with a fixed band: the share within ``depth_band`` of the
    median depth of one plane (RANSAC, 200 samples). Right walk blocks 0.76-0.85 (the ground in view is the rest);
    wrong blocks, which explain a walk as a turn with short baselines so that their depths scatter, 0.25-0.40 (also
    where the parallax ratio does not see them: a single plane at 320x256 px, ratio 0.60-0.63). It measures the
    triangulation's strength as well: a right block with depth noise above about ``depth_band`` scores low too.

    Parameters
    ----------
    cameras : list of Camera ; image_camera : (N_images,) int
    R : (N_images, 3, 3) ; t : (N_images, 3), cam_from_world
    points : (N_tracks, 3) world points (NaN = not triangulated)
    track, image, feature : (N_obs,) int, the observations ; obs_valid : (N_obs,) bool
    xy : list of (N_k, 2) feature positions per image (px)
    images : sequence of int, the block's oriented images
    tol_px : float, homography inlier threshold
    min_points : int, fewer common points: the pair is skipped
    depth_band : float, half-width of the plane band of ``planar_share`` as a share of the pair's median depth

    Returns
    -------
    PlaneParallax
    """
    import cv2

    images = sorted(int(i) for i in images)
    inb = np.zeros(len(R), bool)
    inb[images] = True
    P = np.asarray(points, float)
    sel = np.asarray(obs_valid, bool) & inb[image] & np.all(np.isfinite(P[track]), axis=1)
    tk, im, ft = np.asarray(track)[sel], np.asarray(image)[sel], np.asarray(feature)[sel]
    res2 = []
    obs: dict = {}
    for k in images:
        m = im == k
        if not m.any():
            continue
        x = np.asarray(xy[k], float)[ft[m]]
        X = P[tk[m]]
        pc = X @ np.asarray(R[k]).T + np.asarray(t[k])
        v = cameras[int(image_camera[k])].project(pc) - x
        res2.append(np.sum(v ** 2, axis=1)[np.isfinite(v).all(axis=1)])
        obs[k] = dict(zip(tk[m].tolist(), x))
    rms = float(np.sqrt(np.mean(np.concatenate(res2)))) if res2 and sum(map(len, res2)) else float("nan")
    pairs, shares = [], []
    rng = np.random.default_rng(seed)
    for i, j in zip(images[:-1], images[1:]):
        common = sorted(set(obs.get(i, {})) & set(obs.get(j, {})))
        if len(common) < min_points:
            continue
        Y = P[np.asarray(common)]
        band = depth_band * float(np.median(np.linalg.norm(Y + np.asarray(R[i]).T @ np.asarray(t[i]), axis=1)))
        best = 0
        for _ in range(200):
            a = Y[rng.choice(len(Y), 3, replace=False)]
            nv = np.cross(a[1] - a[0], a[2] - a[0])
            ln = np.linalg.norm(nv)
            if ln > 0:
                best = max(best, int(np.sum(np.abs((Y - a[0]) @ (nv / ln)) <= band)))
        shares.append(best / len(Y))
        xa = np.array([obs[i][c] for c in common])
        xb = np.array([obs[j][c] for c in common])
        cv2.setRNGSeed(int(seed))
        H, mask = cv2.findHomography(np.ascontiguousarray(xa), np.ascontiguousarray(xb), cv2.USAC_MAGSAC, float(tol_px),
                                     maxIters=4000, confidence=0.9999)
        if H is None or mask is None:
            continue
        hin = mask.ravel().astype(bool)
        if hin.sum() < min_points // 3:
            continue
        X = P[np.asarray(common)[hin]]
        w = np.ones(len(X))
        for _ in range(5):
            mu = (X * w[:, None]).sum(0) / w.sum()
            n = np.linalg.svd((X - mu) * np.sqrt(w)[:, None], full_matrices=False)[2][2]
            r = np.abs((X - mu) @ n)
            w = (r <= 3.0 * 1.4826 * np.median(r) + 1e-12).astype(float) + 1e-6
        Ci = -np.asarray(R[i]).T @ np.asarray(t[i])
        d = X - Ci
        den = d @ n
        ok = np.abs(den) > 1e-12 * np.linalg.norm(d, axis=1)
        Xp = Ci + (((mu - Ci) @ n) / np.where(ok, den, 1.0))[:, None] * d
        cam = cameras[int(image_camera[j])]
        par = np.linalg.norm(cam.project(X @ np.asarray(R[j]).T + t[j]) - cam.project(Xp @ np.asarray(R[j]).T + t[j]), axis=1)
        par = par[ok & np.isfinite(par)]
        if len(par):
            pairs.append((i, j, len(common), float(hin.mean()), float(np.median(par))))
    med = float(np.median([p[4] for p in pairs])) if pairs else float("nan")
    ratio = med / rms if np.isfinite(med) and rms > 0 else float("nan")
    return PlaneParallax(pairs, med, rms, float(ratio), float(np.mean(shares)) if shares else float("nan"))
