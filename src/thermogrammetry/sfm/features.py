"""Tie-point features on the full dynamic range of thermal frames.

Thermal frames are 16-bit counts, float kelvin or 8-bit renderings with a few tens of useful grey
levels. Detectors want 8-bit input with contrast, so each frame is mapped by a robust *per-image*
stretch (:func:`detector_input`): percentiles of the finite values to 0..255, optionally followed by
CLAHE (local contrast) or a high-pass (background removal by a large blur). Keypoints are in OpenCV's
pixel convention ((0, 0) is the centre of the top-left pixel), the project's convention.

Detectors: OpenCV SIFT (default; descriptors converted to RootSIFT, Arandjelović & Zisserman 2012, so
Euclidean matching compares Hellinger distances) and ORB (oriented FAST + rotated BRIEF, binary,
Hamming distance) as the measured alternative (``benchmarks/survey.py``), and ASIFT (:func:`asift_views`:
SIFT run on simulated views of the frame tilted by t = √2, 2, 2√2 … ≤ ``asift_max_tilt`` and rotated in
steps of 72°/t, keypoints mapped back to the frame; Morel & Yu 2009) for frames taken 30–60° apart, where
SIFT's descriptors no longer agree (a hand-held facade or fresco set). OpenCV's own ``cv2.AffineFeature``
subsamples the tilted view with nearest-neighbour sampling, which moves keypoints by up to (t − 1)/2 px;
ours warps each view with one exact affine map (pixel centres at integers, OpenCV's convention) after the
anti-aliasing blur and maps keypoints back through its inverse, after SIFT's own 0.25 px upscale offset is
removed in the view (:mod:`thermogrammetry.sfm.keypoints`), so ASIFT keypoints come out in the project's
convention. OpenCV 5 moved AKAZE out of the main package, and its learned detectors (ALIKED, DISK) need
model weights we cannot ship.

References
----------
Lowe, D. G. (2004). Distinctive image features from scale-invariant keypoints. IJCV 60(2), 91-110.
Arandjelović, R., Zisserman, A. (2012). Three things everyone should know to improve object retrieval. CVPR.
Morel, J.-M., Yu, G. (2009). ASIFT: a new framework for fully affine invariant image comparison. SIAM J.
Imaging Sciences 2(2), 438-469.
Rublee, E., Rabaud, V., Konolige, K., Bradski, G. (2011). ORB: an efficient alternative to SIFT or SURF. ICCV.
Zuiderveld, K. (1994). Contrast limited adaptive histogram equalization. Graphics Gems IV, 474-485.
Harris, J. G., Chiang, Y.-M. (1999). Nonuniformity correction of infrared image sequences using the
constant-statistics constraint. IEEE Trans. Image Processing 8(8), 1148-1151.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._sampling import fill_smooth
from ..enums import StrChoice
from ..errors import ConfigError, ShapeError
from .._validate import config_keys

__all__ = ["ASIFT_MAX_FEATURES", "Detector", "Enhancement", "FeatureOptions", "Features", "asift_views",
           "detector_input", "extract_features", "fixed_pattern", "static_overlay", "OVERLAY_MIN_FRAMES"]


ASIFT_MAX_FEATURES = 6000

"""Feature budget the survey CLI gives ASIFT (its views share one budget): twice SIFT's default, measured on the
frescoes' thermal frames (3000: 30 verified pairs, 29 consistent with the RGB reference; 6000: 51 and 43)."""


class Detector(StrChoice):
    SIFT = "sift"
    ORB = "orb"
    ASIFT = "asift"  # SIFT on simulated affine views (tilts and rotations), for large viewpoint changes


class Enhancement(StrChoice):
    """Per-image mapping of the frame to the detector's 8-bit input."""

    STRETCH = "stretch"  # percentile stretch only
    CLAHE = "clahe"  # percentile stretch, then CLAHE
    HIGHPASS = "highpass"  # subtract a large blur (flat-field), then percentile stretch
    LOCAL = "local"  # local contrast normalisation: (a - blur) / local std, with a noise floor (low-texture frames)


@dataclass(frozen=True)
class FeatureOptions:
    """How features are extracted (typed; :meth:`from_dict` refuses unknown keys).

    Attributes
    ----------
    detector : Detector
    enhancement : Enhancement
    max_features : int
        Strongest features kept per image (by detector response).
    low_percentile, high_percentile : float
        Percentiles of the finite values mapped to 0 and 255.
    clahe_clip : float
        CLAHE clip limit; tiles of ``clahe_tile_px``.
    contrast_threshold : float
        SIFT contrast threshold (OpenCV default 0.04; lower finds more features on flat thermal frames).
    highpass_sigma_px : float
        Blur removed by ``highpass``.
    asift_max_tilt : float
        ASIFT: the largest simulated tilt (views at t = √2^k ≤ this, k ≥ 1, plus the frame itself; 4√2, 41
        views, as Morel & Yu. Measured on the 40 thermal frescoes frames, 6000 features: t ≤ 2√2 41 verified
        pairs, 37 consistent with the RGB reference; t ≤ 4√2 61 and 50, 1.7x the feature time).
    local_sigma_px, local_noise_factor : float
        ``local``: ``n = (a − G(a)) / sqrt(G((a − G(a))²) + (k·σ_noise)²)`` with Gaussian ``G`` of σ
        ``local_sigma_px`` and σ_noise estimated from the Laplacian (MAD); mapped as 128 + 40·n. Flat walls
        and smooth heat patterns of a facade become texture; where the local std is below ``k·σ_noise`` (sky,
        fixed-pattern noise, which would match at the same pixel in every frame) the input is flat, rising
        to full contrast at ``2k·σ_noise``.
    """

    detector: Detector = Detector.SIFT
    enhancement: Enhancement = Enhancement.CLAHE
    max_features: int = 3000
    low_percentile: float = 0.5
    high_percentile: float = 99.5
    clahe_clip: float = 2.0
    clahe_tile_px: int = 64
    contrast_threshold: float = 0.01
    highpass_sigma_px: float = 25.0
    local_sigma_px: float = 8.0
    local_noise_factor: float = 2.0
    asift_max_tilt: float = 4.0 * 2.0 ** 0.5

    def __post_init__(self):
        object.__setattr__(self, "detector", Detector(self.detector))
        object.__setattr__(self, "enhancement", Enhancement(self.enhancement))
        if not (isinstance(self.max_features, (int, np.integer)) and self.max_features >= 10):
            raise ConfigError(f"FeatureOptions.max_features={self.max_features!r}: expected an integer >= 10")
        if not 0 <= self.low_percentile < self.high_percentile <= 100:
            raise ConfigError(f"FeatureOptions: percentiles {self.low_percentile!r}, {self.high_percentile!r}: "
                              "expected 0 <= low < high <= 100")
        if not (np.isfinite(self.asift_max_tilt) and 1.0 <= self.asift_max_tilt <= 8.0):
            raise ConfigError(f"FeatureOptions.asift_max_tilt={self.asift_max_tilt!r}: expected a tilt in [1, 8]")

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureOptions":
        return cls(**config_keys(cls, d))


@dataclass
class Features:
    """Keypoints and descriptors of one image.

    Attributes
    ----------
    xy : (N, 2) float64, px (OpenCV convention)
    size : (N,) float32, keypoint diameter (px)
    angle : (N,) float32, deg
    descriptors : (N, D) float32 (RootSIFT) or uint8 (ORB)
    """

    xy: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)

    def to_npz_dict(self) -> dict:
        return {"xy": self.xy, "size": self.size, "angle": self.angle, "descriptors": self.descriptors}

    @classmethod
    def from_npz_dict(cls, d) -> "Features":
        return cls(np.asarray(d["xy"], float), np.asarray(d["size"]), np.asarray(d["angle"]), np.asarray(d["descriptors"]))


def laplacian_noise(image: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Standard deviation of white noise in a frame (its unit), from the MAD of its Laplacian.

    Parameters
    ----------
    image : (H, W) float32 array
    valid : (H, W) bool or None, the pixels to use

    The 3×3 Laplacian has a gain of sqrt(20) on white noise; scene structure is rare enough to leave the
    median of its absolute deviation to the noise (Immerkær 1996 uses the same idea with another kernel).
    """
    import cv2

    lap = cv2.Laplacian(image, cv2.CV_32F)
    lap = lap[valid] if valid is not None else lap.ravel()
    return 1.4826 * float(np.median(np.abs(lap - np.median(lap)))) / np.sqrt(20.0)


def detector_input(image, options: FeatureOptions | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Map a frame (any dtype, 2D or colour) to the detector's 8-bit input and a validity mask.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        uint8/uint16 counts, float kelvin (NaN = invalid) or an 8-bit rendering.
    options : FeatureOptions

    Returns
    -------
    img8 : (H, W) uint8
    valid : (H, W) bool, finite pixels (features are only kept where the 9x9 neighbourhood is valid)
    """
    import cv2

    opt = options or FeatureOptions()
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a[..., :3].astype(np.float32), cv2.COLOR_RGB2GRAY) if a.dtype != np.uint8 else cv2.cvtColor(a[..., :3], cv2.COLOR_RGB2GRAY)
    if a.ndim != 2:
        raise ShapeError(f"image: expected a 2D frame or (H, W, 3) colour image, got shape {a.shape}")
    a = a.astype(np.float32)
    valid = np.isfinite(a)
    if not valid.any():
        return np.zeros(a.shape, np.uint8), valid
    if not valid.all():  # no-data (NaN, a masked display) filled smoothly: no edge at its border
        a = fill_smooth(a, valid)
    if opt.enhancement is Enhancement.HIGHPASS:
        a = a - cv2.GaussianBlur(a, (0, 0), opt.highpass_sigma_px)
    if opt.enhancement is Enhancement.LOCAL:
        d = a - cv2.GaussianBlur(a, (0, 0), opt.local_sigma_px)
        noise = laplacian_noise(a, valid)
        sd2 = cv2.GaussianBlur(d * d, (0, 0), opt.local_sigma_px)
        n = d / np.sqrt(sd2 + (opt.local_noise_factor * noise) ** 2 + 1e-12)
        # where the local signal is noise alone (sky, fixed-pattern noise that moves with the camera and
        # would match at the same pixel in every frame), the input is made flat
        k = opt.local_noise_factor
        n *= np.clip((np.sqrt(sd2) / max(noise, 1e-12) - k) / k, 0.0, 1.0)
        img8 = np.clip(128.0 + 40.0 * n, 0, 255).astype(np.uint8)
        if not valid.all():
            valid = cv2.erode(valid.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        return img8, valid
    lo, hi = np.percentile(a[valid], [opt.low_percentile, opt.high_percentile])
    if not hi > lo:
        hi = lo + 1.0
    img8 = np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    if opt.enhancement is Enhancement.CLAHE:
        h, w = img8.shape
        tiles = (max(1, int(round(w / opt.clahe_tile_px))), max(1, int(round(h / opt.clahe_tile_px))))
        img8 = cv2.createCLAHE(clipLimit=opt.clahe_clip, tileGridSize=tiles).apply(img8)
    if not valid.all():
        valid = cv2.erode(valid.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    return img8, valid


def extract_features(image, options: FeatureOptions | None = None) -> Features:
    """Detect and describe keypoints of one frame.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, any dtype (see :func:`detector_input`)
    options : FeatureOptions

    Returns
    -------
    Features
        At most ``options.max_features``, strongest first; deterministic for a given image.
    """
    import cv2

    opt = options or FeatureOptions()
    img8, valid = detector_input(image, opt)
    mask = valid.astype(np.uint8) * 255
    if opt.detector is Detector.ASIFT:
        return _asift_features(img8, mask, opt)
    if opt.detector is Detector.SIFT:
        det = cv2.SIFT_create(nfeatures=opt.max_features, contrastThreshold=opt.contrast_threshold)
    else:
        det = cv2.ORB_create(nfeatures=opt.max_features, fastThreshold=5, edgeThreshold=19, patchSize=19)
    kps, desc = det.detectAndCompute(img8, mask)
    if desc is None or not kps:
        d = 128 if opt.detector is Detector.SIFT else 32
        return Features(np.zeros((0, 2)), np.zeros(0, np.float32), np.zeros(0, np.float32),
                        np.zeros((0, d), np.float32 if opt.detector is Detector.SIFT else np.uint8))
    resp = np.array([k.response for k in kps])
    order = np.argsort(-resp, kind="stable")[: opt.max_features]
    xy = np.array([kps[i].pt for i in order], dtype=np.float64)
    size = np.array([kps[i].size for i in order], dtype=np.float32)
    angle = np.array([kps[i].angle for i in order], dtype=np.float32)
    desc = desc[order]
    if opt.detector is Detector.SIFT:
        desc = _root_sift(desc)
    return Features(xy, size, angle, desc)


def _root_sift(desc: np.ndarray) -> np.ndarray:
    """(N, 128) SIFT descriptors → RootSIFT (float32): L1-normalised, then the square root (unit L2 norm)."""
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(desc)


def asift_views(max_tilt: float = 4.0 * 2.0 ** 0.5) -> list[tuple[float, float]]:
    """The simulated views of ASIFT: (tilt t, rotation φ in degrees) pairs, the frame itself first.

    Tilts t = √2^k ≤ ``max_tilt`` (k ≥ 1); for each, rotations φ = 0, b/t, 2b/t, … < 180° with b = 72°
    (Morel & Yu 2009, §4: the sampling that keeps neighbouring views within SIFT's own invariance).
    """
    views = [(1.0, 0.0)]
    k = 1
    while 2.0 ** (k / 2) <= max_tilt * (1 + 1e-9):
        t = 2.0 ** (k / 2)
        step = 72.0 / t
        views += [(t, float(phi)) for phi in np.arange(0.0, 180.0 - 1e-9, step)]
        k += 1
    return views


def _asift_features(img8: np.ndarray, mask: np.ndarray, opt: FeatureOptions) -> Features:
    """SIFT on every view of :func:`asift_views`; keypoints mapped back to the frame in the pixel-centre
    convention (SIFT's 0.25 px upscale offset removed in each view). Of the keypoints that land in the frame,
    one per 0.5 px cell and 10° of orientation is kept (the strongest: neighbouring views find the same
    keypoint), then the ``max_features`` strongest overall. ``angle`` is the orientation in the view the
    descriptor was computed in, ``size`` its diameter there times √t (the affine map has no single scale)."""
    import cv2

    from .keypoints import SIFT_UPSCALE_OFFSET_PX

    h, w = img8.shape
    sift = cv2.SIFT_create(nfeatures=opt.max_features, contrastThreshold=opt.contrast_threshold)
    xy_all, size_all, ang_all, resp_all, desc_all = [], [], [], [], []
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    for t, phi in asift_views(opt.asift_max_tilt):
        if t == 1.0:
            view, vmask, A = img8, mask, np.array([[1.0, 0, 0], [0, 1.0, 0]])
        else:
            c, s_ = np.cos(np.radians(phi)), np.sin(np.radians(phi))
            rot2 = np.array([[c, -s_], [s_, c]])
            q = corners @ rot2.T
            R = np.c_[rot2, -q.min(axis=0)]  # the frame rotated by φ, shifted into view
            rsize = np.ceil(np.ptp(q, axis=0)).astype(int) + 1
            rot = cv2.warpAffine(img8, R, (int(rsize[0]), int(rsize[1])), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
            rmask = cv2.warpAffine(mask, R, (int(rsize[0]), int(rsize[1])), flags=cv2.INTER_NEAREST, borderValue=0)
            # anti-aliasing before x is compressed by t: σ = 0.8 sqrt(t² − 1) in x (Morel & Yu 2009, §4)
            rot = cv2.GaussianBlur(rot, (0, 0), sigmaX=0.8 * np.sqrt(t * t - 1.0), sigmaY=0.01)
            # x' = x / t with pixel centres at integers in both images: one affine map, bilinear
            S = np.array([[1.0 / t, 0, 0], [0, 1.0, 0]])
            vsize = (int(np.floor((rsize[0] - 1) / t)) + 1, int(rsize[1]))
            view = cv2.warpAffine(rot, S, vsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            vmask = cv2.warpAffine(rmask, S, vsize, flags=cv2.INTER_NEAREST, borderValue=0)
            vmask = cv2.erode(vmask, np.ones((3, 3), np.uint8))
            A = (np.vstack([S, [0, 0, 1]]) @ np.vstack([R, [0, 0, 1]]))[:2]
        kps, desc = sift.detectAndCompute(view, vmask)
        if desc is None or not kps:
            continue
        p = np.array([k.pt for k in kps], float) - SIFT_UPSCALE_OFFSET_PX
        Ainv = cv2.invertAffineTransform(A)
        xy_all.append(p @ Ainv[:, :2].T + Ainv[:, 2])
        size_all.append(np.array([k.size for k in kps], np.float32) * np.float32(np.sqrt(t)))
        ang_all.append(np.array([k.angle for k in kps], np.float32))
        resp_all.append(np.array([k.response for k in kps]))
        desc_all.append(desc)
    if not xy_all:
        return Features(np.zeros((0, 2)), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros((0, 128), np.float32))
    xy = np.concatenate(xy_all)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    resp = np.concatenate(resp_all)
    order = np.argsort(-np.where(inside, resp, -np.inf), kind="stable")[: int(inside.sum())]
    # the same keypoint seen from near-identity views: keep the strongest per 0.5 px cell and 10° of angle
    ang = np.concatenate(ang_all)
    key = np.c_[np.floor(xy[order] * 2.0).astype(np.int64), np.floor(ang[order] / 10.0).astype(np.int64)]
    _, first = np.unique(key, axis=0, return_index=True)
    order = order[np.sort(first)][: opt.max_features]
    desc = _root_sift(np.concatenate(desc_all)[order])
    return Features(xy[order], np.concatenate(size_all)[order], ang[order], desc)


def fixed_pattern(frames, *, max_frames: int = 60, highpass_sigma_px: float = 0.0) -> np.ndarray | None:
    """Fixed pattern of a sensor (offset non-uniformity, column stripes, vignetting) from its own frames.

    Scene-based non-uniformity estimate in the spirit of the constant-statistics constraint (Harris &
    Chiang 1999): when the scene moves between frames, the per-pixel median of ``frame − median(frame)``
    over the sequence keeps what stays at the same pixel in every frame -- the sensor's pattern -- and
    averages the scene away. Subtracting it before detection stops features from locking onto the
    pattern (they would "match" at the same pixel in every pair, a false zero motion) and lets the weak
    scene texture of low-contrast thermal frames through.

    Parameters
    ----------
    frames : sequence of (H, W) arrays
        Frames of one sensor (same shape), any numeric dtype; NaN = invalid. At most ``max_frames``,
        evenly spaced, are used.

    Returns
    -------
    (H, W) float32 or None
        The pattern in the frames' unit (zero median), or None with fewer than 5 frames (too few for
        the scene to average out).
    highpass_sigma_px : float
        0: the whole pattern (each frame minus its median). > 0: only the pattern's part finer than a Gaussian
        blur of this σ (each frame minus its blur). The scene leaks into the per-pixel median by about
        1.25 σ_scene / sqrt(frames) -- for a plain wall's coarse heat pattern and 30 frames, more than the
        sensor's pattern itself in the band a tracker uses (measured on the synthetic low-texture facade:
        residual 0.090 K against 0.019 K of true pattern in that band; 0.007 K with σ = 8 px). The fine part is
        what locks features at the same pixel in every frame.
    """
    frames = list(frames)
    if len(frames) < 5:
        return None
    shape = np.asarray(frames[0]).shape
    if any(np.asarray(f).shape != shape for f in frames) or len(shape) != 2:
        return None
    pick = np.linspace(0, len(frames) - 1, min(len(frames), max_frames)).round().astype(int)
    stack = np.empty((len(pick), *shape), np.float32)
    for k, i in enumerate(pick):
        a = np.asarray(frames[i], np.float32)
        if highpass_sigma_px > 0:
            import cv2

            ok = np.isfinite(a)
            fill = np.where(ok, a, np.float32(np.median(a[ok])) if ok.any() else np.float32(0.0))
            stack[k] = np.where(ok, fill - cv2.GaussianBlur(fill, (0, 0), float(highpass_sigma_px)), np.nan)
            continue
        med = np.nanmedian(a) if np.isfinite(a).any() else 0.0
        stack[k] = a - med
    with np.errstate(all="ignore"):
        pat = np.nanmedian(stack, axis=0)
    pat = np.where(np.isfinite(pat), pat, 0.0).astype(np.float32)
    return pat - np.float32(np.median(pat))


#: :func:`static_overlay`: the fewest frames from which a burned-in display is told from the scene
OVERLAY_MIN_FRAMES = 8

#: :func:`static_overlay` holds two float32 stacks of the frames it uses: at most this many pixels per stack (60
#: frames of 640x512; 9 of 1920x1080), ~160 MB for both
OVERLAY_PIXEL_BUDGET = 20_000_000


def static_overlay(frames, *, max_frames: int = 60, highpass_sigma_px: float = 2.0, top_share: float = 0.02,
                   min_frequency: float = 0.25, dilate_px: float | None = None) -> np.ndarray | None:
    """Pixels of a display burned into 8-bit renderings (text, cross-hair, colour bar, logo), found from the frames.

    Exported JPEGs and screen recordings of hand-held thermal cameras carry the camera's display: the maker's
    name, the spot meter's reading and cross-hair, a colour bar with the frame's range, the date. Those stay at
    the same pixels while the scene moves, so their features "match" at zero motion in every pair (consistent with
    any pure translation, they pass an essential-matrix check) and drag the camera model: the 32 M3T frames as 8-bit
    palette JPEGs without EXIF focal length self-calibrate a focal length of 686 px, 402 px with a display burned in,
    855 px with it masked (783 px from the radiometric frames; benchmarks/README.md, "A camera display burned into
    8-bit frames"). A pixel is taken as display when, in the high-pass of the frames (frame − Gaussian blur of
    ``highpass_sigma_px``):

    * its per-pixel median over the frames is strong and steady -- ``|P| > 6 σ`` of both the median's spread over
      the frame (a sensor's fixed pattern) and the typical frame-to-frame variation, and its median absolute
      deviation over the frames below ``|P| / 2`` (static text and marks; the local background may change with
      the camera's gain), or
    * it is among the ``top_share`` strongest high-pass pixels of a frame in at least ``min_frequency`` of the
      frames (and in at least 4): readings whose digits change from frame to frame stay in their box. A moving
      scene puts a pixel there in ~``top_share`` of the frames.

    Components of fewer than 3 (steady) or 16 (frequent) pixels are dropped (a sensor's strongest fixed-pattern
    pixels are frequent too, in specks; a changing reading's box is larger). What is left grows into the still
    pixels it touches -- whose value varies over the frames by less than a tenth of the typical pixel's (a colour
    bar's inside, flat behind its edges) -- unless a quarter of the frame is still, and is dilated by ``dilate_px``
    (default 8 px per 640 px of width: a feature's support region).

    Parameters
    ----------
    frames : sequence of (H, W) arrays of one sensor (same shape), any numeric dtype; at most ``max_frames`` (and
        :data:`OVERLAY_PIXEL_BUDGET` pixels), evenly spaced, are used. Meant for 8-bit renderings: raw radiometric
        data carries no display.

    Returns
    -------
    (H, W) bool (True = display, no tie points there) or None: fewer than :data:`OVERLAY_MIN_FRAMES` frames,
    frames of different shapes, nothing found, or more than a quarter of the frame found (the frames hardly move:
    the scene cannot be told from a display).
    """
    import cv2

    frames = list(frames)
    if len(frames) < OVERLAY_MIN_FRAMES:
        return None
    shape = np.asarray(frames[0]).shape
    if len(shape) != 2 or any(np.asarray(f).shape != shape for f in frames):
        return None
    n_use = max(OVERLAY_MIN_FRAMES, min(int(max_frames), OVERLAY_PIXEL_BUDGET // max(1, shape[0] * shape[1])))
    pick = np.linspace(0, len(frames) - 1, min(len(frames), n_use)).round().astype(int)
    hp = np.empty((len(pick), *shape), np.float32)
    raw = np.empty((len(pick), *shape), np.float32)
    for k, i in enumerate(pick):
        a = np.asarray(frames[i], np.float32)
        ok = np.isfinite(a)
        if not ok.all():
            a = np.where(ok, a, np.float32(np.median(a[ok])) if ok.any() else np.float32(0.0))
        raw[k] = a
        hp[k] = a - cv2.GaussianBlur(a, (0, 0), float(highpass_sigma_px))
    # pixels whose value hardly changes while the scene moves: a display's flat parts (a colour bar's inside)
    d_raw = np.median(np.abs(raw - np.median(raw, axis=0)), axis=0)
    still = d_raw <= 0.1 * float(np.median(d_raw))
    del raw
    P = np.median(hp, axis=0)
    D = np.median(np.abs(hp - P), axis=0)
    s_pattern = 1.4826 * float(np.median(np.abs(P - np.median(P))))
    s_motion = 1.4826 * float(np.median(D))
    absP = np.abs(P)
    steady = (absP > max(6.0 * s_pattern, 6.0 * s_motion, 1e-12)) & (D < 0.5 * absP)
    mag = np.abs(hp, out=hp)
    q = np.quantile(mag.reshape(len(pick), -1), 1.0 - float(top_share), axis=1)
    frequent = (mag > q[:, None, None]).mean(axis=0) >= max(float(min_frequency), 4.0 / len(pick))
    m = (_without_small(steady, 3) | _without_small(frequent, 16)).astype(np.uint8)
    if not m.any():
        return None
    if still.mean() < 0.25:  # the marks found grow into the still pixels they touch (unless most of the frame is still)
        m = _grow_into(m, still)
    r = int(round(8.0 * shape[1] / 640.0)) if dilate_px is None else int(round(dilate_px))
    if r > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    out = m.astype(bool)
    return None if out.mean() > 0.25 else out


def _without_small(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    """``mask`` (bool) without its 8-connected components of fewer than ``min_pixels`` pixels."""
    import cv2

    n, lab, st, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = st[:, cv2.CC_STAT_AREA] >= min_pixels
    keep[0] = False
    return keep[lab]


def _grow_into(seed: np.ndarray, region: np.ndarray) -> np.ndarray:
    """uint8 mask: ``seed`` grown (8-connected) into the components of ``region`` that it touches."""
    import cv2

    n, lab = cv2.connectedComponents((region | seed.astype(bool)).astype(np.uint8), connectivity=8)
    hit = np.zeros(n, bool)
    hit[np.unique(lab[seed.astype(bool)])] = True
    hit[0] = False
    return (hit[lab] | seed.astype(bool)).astype(np.uint8)
