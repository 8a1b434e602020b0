"""Descriptor matching (sfm.matching.match_descriptors) against a brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.sfm.matching import match_descriptors, release_scratch


def _reference(d1, d2, ratio):
    """Ratio test both ways and the mutual check, from the full Euclidean distance matrix (float64)."""
    D = np.sqrt(((d1[:, None, :].astype(float) - d2[None, :, :].astype(float)) ** 2).sum(-1))

    def best(D):
        o = np.argsort(D, axis=1, kind="stable")
        r = np.arange(len(D))
        ok = D[r, o[:, 0]] < ratio * D[r, o[:, 1]]
        return np.where(ok, o[:, 0], -1)

    m12, m21 = best(D), best(D.T)
    q = np.nonzero(m12 >= 0)[0]
    keep = q[m21[m12[q]] == q]
    return np.stack([keep, m12[keep]], axis=1)


def _descriptors(rng, n1, n2, n_common, noise):
    """Unit-norm 128-D descriptors (RootSIFT-like, non-negative); the first n_common of d2 are noisy copies of
    shuffled rows of d1."""
    d1 = np.abs(rng.normal(size=(n1, 128)))
    d2 = np.abs(rng.normal(size=(n2, 128)))
    src = rng.permutation(n1)[:n_common]
    d2[:n_common] = np.abs(d1[src] + noise * rng.normal(size=(n_common, 128)))
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    return d1.astype(np.float32), d2.astype(np.float32), src


@pytest.mark.parametrize("n1,n2", [(400, 700), (700, 400), (3, 2)])
def test_unit_descriptors_match_the_brute_force_reference(n1, n2):
    rng = np.random.default_rng(5)
    d1, d2, src = _descriptors(rng, n1, n2, min(n1, n2) // 2, noise=0.25)
    ref = _reference(d1, d2, 0.85)
    # twice: the second call reuses (and must not be confused by) the scratch arrays of the first
    for _ in range(2):
        m = match_descriptors(d1, d2, ratio=0.85)
        np.testing.assert_array_equal(m, ref)
    release_scratch()
    np.testing.assert_array_equal(match_descriptors(d1, d2, ratio=0.85), ref)
    if n1 > 10:
        # the planted correspondences are found and are right: at least 90 % of them, none wrong among them
        found = {int(a): int(b) for a, b in m}
        right = sum(found.get(int(s)) == k for k, s in enumerate(src))
        assert right >= 0.9 * len(src)


def test_general_descriptors_match_the_brute_force_reference():
    rng = np.random.default_rng(6)
    d1, d2, _ = _descriptors(rng, 300, 350, 150, noise=0.25)
    d1, d2 = d1 * 3.0, d2 * 2.0  # not unit rows: the squared-distance path
    np.testing.assert_array_equal(match_descriptors(d1, d2, ratio=0.8), _reference(d1, d2, 0.8))
