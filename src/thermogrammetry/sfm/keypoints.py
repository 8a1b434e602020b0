"""Keypoint coordinates in the project's pixel convention: (0, 0) is the centre of the top-left pixel.

OpenCV's SIFT (``cv2.SIFT_create`` with its default ``enable_precise_upscale=False``) doubles the image
with centre-aligned bilinear interpolation (doubled pixel X samples the input at X/2 − 0.25) but maps
keypoints back by X/2: every keypoint is reported 0.25 px right of and below its true position, in every
octave (measured: +0.2496/+0.2507 px, σ 0.005 px, on Gaussian blobs at known centres; OpenCV 5.0.0).
A constant offset of the observations acts like a principal-point error; a self-calibrated camera absorbs
it, but a given camera (``--camera``, a rig file's cameras) and image measurements made in the true
convention (GCPs, manual tie points) do not: in the synthetic rig block it tilted the block by
0.05-0.1 deg and put the tie points 0.1-0.2 m too low (/work/notes/rigfix.md).

The clean fix is ``cv2.SIFT_create(..., enable_precise_upscale=True)`` (OpenCV >= 4.8) inside
:func:`thermogrammetry.sfm.features.extract_features`; until that lands, the survey shifts SIFT keypoints
after extraction with :func:`to_pixel_centre_convention`. ``tests/test_keypoint_convention.py`` fails if
OpenCV's behaviour (or ``extract_features``) changes, so the correction cannot silently double up.

References
----------
Lowe, D. G. (2004). Distinctive image features from scale-invariant keypoints. IJCV 60(2), 91-110
(§3: the image is doubled before the first octave).
OpenCV pull request 23124 (2023), "SIFT: precise upscale" (``enable_precise_upscale``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SIFT_UPSCALE_OFFSET_PX", "to_pixel_centre_convention"]

#: offset (px, x and y) of OpenCV SIFT keypoints relative to the pixel-centre convention
SIFT_UPSCALE_OFFSET_PX = 0.25


def to_pixel_centre_convention(features, options=None):
    """Return ``features`` with keypoints in the pixel-centre convention (a new object; input untouched).

    Parameters
    ----------
    features : thermogrammetry.sfm.features.Features
        As returned by ``extract_features`` (``xy`` (N, 2) px).
    options : thermogrammetry.sfm.features.FeatureOptions, optional
        The options the features were extracted with. Only SIFT is shifted (by −0.25 px in x and y); ORB
        keypoints are returned unchanged (its pyramid levels carry a level-dependent offset −(s−1)/2 px,
        s = 1.2^level, that the stored features do not allow to undo).

    Returns
    -------
    Features
    """
    from dataclasses import replace

    from .features import Detector, FeatureOptions

    opt = options or FeatureOptions()
    if opt.detector is not Detector.SIFT or len(features) == 0:
        return features
    return replace(features, xy=np.asarray(features.xy, dtype=np.float64) - SIFT_UPSCALE_OFFSET_PX)
