"""Low-texture tie points: the sensor's fixed pattern from the sequence, and homography-guided matching.

Ground truth is built in: the fixed pattern is injected, the motion between the keypoint sets is a known
homography, and the descriptors repeat (identical windows) so that a global ratio test cannot tell them apart.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.sfm.features import fixed_pattern
from thermogrammetry.sfm.matching import guided_matches, homography_prior, match_descriptors


def _smooth_field(rng, shape, sigma):
    import cv2

    a = rng.normal(0.0, 1.0, shape).astype(np.float32)
    a = cv2.GaussianBlur(a, (0, 0), sigma)
    return a / a.std()


def test_fixed_pattern_is_recovered_from_a_moving_scene():
    """Frames = shifted crops of a weak smooth scene (0.15 K, a low-texture wall) + a fixed pattern (0.1 K
    column stripes and pixel offsets) + 0.02 K noise.

    Per pixel the 60 crops see independent scene values, so the median of (frame - its median) keeps the
    pattern with an error of about 1.25 * 0.15 K / sqrt(60) = 0.024 K RMS (measured 0.019 K: the scene is smooth). The bound,
    0.035 K, is a third of the pattern's 0.1 K: a zero estimate fails it by a factor of 3.
    """
    rng = np.random.default_rng(7)
    h, w = 64, 80
    scene = 280.0 + 0.15 * _smooth_field(rng, (400, 400), 6.0)
    pattern = (0.07 * rng.normal(0, 1, (1, w)) + 0.07 * rng.normal(0, 1, (h, w))).astype(np.float32)
    pattern -= np.median(pattern)
    frames = []
    for _ in range(60):
        y, x = rng.integers(0, 400 - h), rng.integers(0, 400 - w)
        frames.append(scene[y:y + h, x:x + w] + pattern + rng.normal(0, 0.02, (h, w)))
    est = fixed_pattern(frames)
    assert est is not None and est.shape == (h, w)
    # the pattern is known up to a constant (every frame's median is removed)
    err = (est - np.median(est)) - (pattern - np.median(pattern))
    rms = float(np.sqrt(np.mean(err ** 2)))
    assert rms < 0.035, rms
    print(f"fixed-pattern error {rms:.4f} K RMS")
    assert float(np.sqrt(np.mean(pattern ** 2))) > 0.09  # the test pattern is well above the bound
    assert fixed_pattern(frames[:4]) is None  # too few frames for the scene to average out


def _repeated_scene(rng):
    """Keypoints on a 6 x 4 grid of identical 'windows' (4 corners each, one descriptor per corner type)."""
    corner_desc = rng.normal(0, 1, (4, 32)).astype(np.float32)
    xy, desc = [], []
    for gx in range(6):
        for gy in range(4):
            for c, (dx, dy) in enumerate(((0, 0), (30, 0), (0, 40), (30, 40))):
                xy.append((20 + 70 * gx + dx, 20 + 80 * gy + dy))
                desc.append(corner_desc[c] + rng.normal(0, 0.02, 32))  # windows alike within the image noise
    # a few unique features (a door, a downpipe): the only ones a global ratio test keeps
    for k in range(12):
        xy.append((rng.uniform(10, 430), rng.uniform(10, 330)))
        desc.append(rng.normal(0, 1, 32))
    return np.array(xy, float), np.array(desc, np.float32)


def test_guided_matching_resolves_repeated_structure():
    rng = np.random.default_rng(3)
    xy1, d1 = _repeated_scene(rng)
    H = np.array([[1.01, 0.004, -37.0], [-0.003, 0.995, 6.0], [1e-5, -2e-5, 1.0]])
    p = np.c_[xy1, np.ones(len(xy1))] @ H.T
    xy2 = p[:, :2] / p[:, 2:] + rng.normal(0, 0.3, (len(xy1), 2))
    d2 = d1 + rng.normal(0, 0.05, d1.shape).astype(np.float32)
    perm = rng.permutation(len(xy2))  # image 2 lists its keypoints in another order
    xy2, d2 = xy2[perm], d2[perm]
    truth = np.argsort(perm)  # truth[i] = index in image 2 of keypoint i of image 1
    glob = match_descriptors(d1, d2, ratio=0.85)
    # the global ratio test keeps only the unique features: the windows' corners are ambiguous
    assert len(glob) <= 14
    Hp = homography_prior(xy1, xy2, glob, min_inliers=8)
    assert Hp is not None
    g = guided_matches(xy1, d1, xy2, d2, Hp, radius_px=10.0)
    correct = np.sum(truth[g[:, 0]] == g[:, 1])
    assert correct >= 0.95 * len(xy1), (correct, len(xy1))  # 96 window corners + 12 unique features
    assert correct == len(g)  # and no wrong match: the nearest identical window is 30+ px away
    assert len(np.unique(g[:, 1])) == len(g)  # each keypoint of image 2 used once


def test_guided_matching_edge_cases():
    xy = np.array([[10.0, 10.0], [50.0, 50.0]])
    d = np.eye(2, 8, dtype=np.float32)
    assert guided_matches(xy, d, np.zeros((0, 2)), np.zeros((0, 8), np.float32), np.eye(3)).shape == (0, 2)
    far = guided_matches(xy, d, xy + 100.0, d, np.eye(3), radius_px=5.0)
    assert far.shape == (0, 2)  # nothing within the radius: no match rather than a wrong one
    assert homography_prior(xy, xy, np.array([[0, 0], [1, 1]])) is None  # too few matches


@pytest.mark.parametrize("radius", [-1.0, float("nan")])
def test_guided_radius_is_validated(radius):
    from thermogrammetry.errors import ConfigError
    from thermogrammetry.sfm.matching import MatchOptions

    with pytest.raises(ConfigError, match="guided_radius_px"):
        MatchOptions(guided_radius_px=radius)
