"""Tracks by union-find (sfm.tracks): inconsistent tracks split."""

from __future__ import annotations

import numpy as np

from thermogrammetry.sfm.tracks import build_tracks


def _as_sets(tr):
    return sorted(sorted(zip(tr.image[tr.track == t].tolist(), tr.feature[tr.track == t].tolist()))
                  for t in range(tr.n_tracks))


def test_wrong_match_chain_is_split():
    # 0:0 - 1:0 - 2:0 and 0:1 - 2:0: image 0 twice in one track -> its observations dropped, the rest kept
    pairs = [(0, 1, np.array([[0, 0]])), (1, 2, np.array([[0, 0]])), (0, 2, np.array([[1, 0]]))]
    tr = build_tracks([2, 1, 1], pairs)
    assert tr.n_split == 1
    assert _as_sets(tr) == [[(1, 0), (2, 0)]]
