"""Tracks: verified pairwise matches joined by union-find; inconsistent tracks split.

A track is the set of (image, feature) observations of one object point. Joining pairwise matches
transitively can put two different features of the same image into one track (a wrong match somewhere
along the chain); such a track is *inconsistent*. It is split: the observations of every image that
appears more than once are removed, and the rest is kept when it still has two or more images.

References
----------
Moulon, P., Monasse, P. (2012). Unordered feature tracking made fast and easy. CVMP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Tracks", "build_tracks"]


@dataclass
class Tracks:
    """Observations of tracks, flat.

    Attributes
    ----------
    track : (K,) int, track id (0..n_tracks-1)
    image : (K,) int, image index
    feature : (K,) int, feature index in that image
        (:func:`build_tracks` gives int32 arrays when the block has fewer than 2^31 features)
    n_split : int, tracks that were inconsistent and split
    """

    track: np.ndarray
    image: np.ndarray
    feature: np.ndarray
    n_split: int = 0

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    def lengths(self) -> np.ndarray:
        return np.bincount(self.track, minlength=self.n_tracks)

    def by_image(self, n_images: int) -> list[dict[int, int]]:
        """Per image: feature index -> track id."""
        out: list[dict[int, int]] = [dict() for _ in range(n_images)]
        for t, i, f in zip(self.track.tolist(), self.image.tolist(), self.feature.tolist()):
            out[i][f] = t
        return out


def build_tracks(n_features: list[int], pairs: list[tuple[int, int, np.ndarray]]) -> Tracks:
    """Union-find over verified matches.

    Parameters
    ----------
    n_features : list of int
        Number of features per image.
    pairs : list of (i, j, idx)
        ``idx`` (M, 2): feature indices in images i and j of verified matches.

    Returns
    -------
    Tracks
        Consistent tracks of length >= 2 (each image at most once per track).
    """
    offset = np.concatenate([[0], np.cumsum(n_features)]).astype(np.int64)
    n = int(offset[-1])
    parent = np.arange(n, dtype=np.int64)

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j, idx in pairs:
        if len(idx) == 0:
            continue
        a = offset[i] + idx[:, 0].astype(np.int64)
        b = offset[j] + idx[:, 1].astype(np.int64)
        for u, v in zip(a.tolist(), b.tolist()):
            ru, rv = root(u), root(v)
            if ru != rv:
                if ru < rv:
                    parent[rv] = ru
                else:
                    parent[ru] = rv
    # every node's root by pointer jumping (vectorised; the same roots as root(k) for each k, without a
    # Python int per feature)
    roots = parent
    while True:
        nxt = roots[roots]
        if np.array_equal(nxt, roots):
            break
        roots = nxt
    del parent
    node_img = np.repeat(np.arange(len(n_features)), n_features)
    node_feat = np.arange(n) - offset[node_img]
    size = np.bincount(roots, minlength=n)
    sel = np.nonzero(size[roots] >= 2)[0]
    r, im, ft = roots[sel], node_img[sel], node_feat[sel]
    # inconsistent: an image twice in one track -> drop that image's observations of the track
    key = r * (len(n_features) + 1) + im
    uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    dup = cnt[inv] > 1
    n_split = int(len(np.unique(r[dup])))
    r, im, ft = r[~dup], im[~dup], ft[~dup]
    # keep tracks with >= 2 distinct images, renumber
    ur, tinv, tcnt = np.unique(r, return_inverse=True, return_counts=True)
    keep = tcnt[tinv] >= 2
    r, im, ft = tinv[keep], im[keep], ft[keep]
    _, r = np.unique(r, return_inverse=True)
    order = np.lexsort((im, r))
    # int32 when the counts allow (12 B per observation less than int64; a block has far fewer than 2^31 features)
    dt = np.int32 if max(n, 1) < 2**31 - 1 else np.int64
    return Tracks(r[order].astype(dt), im[order].astype(dt), ft[order].astype(dt), n_split)
