"""The survey's tie-point cache (``survey --cache DIR``): features and verified matches kept in a folder by content.

A feature file is keyed by the sha256 of the frame as the detector sees it (after the sensor's fixed pattern and a
burned-in display are taken out), the feature options and the software; a pair's verified matches by the digests
of both images' features, both starting cameras, the matching options and the software; the low-texture tracker's
result for a sequence of frames (features and verified consecutive matches) by the digests of all its frames as the
tracker sees them, the sensor's pattern, the cameras, the tracking options and the software. "The software" is the
source of the modules that compute them (:mod:`thermogrammetry.sfm`, :mod:`thermogrammetry.camera`, the survey's
feature and matching steps) with the versions of NumPy and OpenCV: any change there starts a new set of keys, so a
cache never gives what the running code would not compute. A hit is the same bytes the computation would write (the
results are deterministic: seeded RANSAC), so a survey that reads the cache gives the same outputs as one that does
not; only the time differs.

What it is for: a second survey of the same frames -- other GNSS, GCPs or check points, another CRS, a subset of
the frames, a different orientation or adjustment option -- skips the detection and the matching of every image
and pair it has seen, and the frame-to-frame tracking of a sequence it has tracked. Entries are written atomically (several surveys may share one cache at once); the folder is
never cleaned by the survey (delete it to free the space: ~1.5 MB per frame with 3,000 SIFT features).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
from pathlib import Path

import numpy as np

from ...errors import ConfigError
from ...store import FolderProject

__all__ = ["TieCache", "open_cache", "check_cache_path", "software_digest", "CACHE_FORMAT"]

#: bumped when the layout of a cache entry changes
CACHE_FORMAT = 1

#: the sources whose change changes features or matches (relative to the package folder)
_SOURCES = ("sfm", "camera", "pipeline/survey/features.py", "pipeline/survey/matching.py", "pipeline/survey/store.py",
            "pipeline/survey/cache.py")


@functools.lru_cache(maxsize=1)
def software_digest() -> str:
    """sha256 (hex) of the sources that compute features and matches, NumPy's and OpenCV's versions and
    :data:`CACHE_FORMAT`."""
    import cv2

    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256(f"tie-cache {CACHE_FORMAT} numpy {np.__version__} opencv {cv2.__version__}".encode())
    files = []
    for rel in _SOURCES:
        p = root / rel
        files += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    for p in files:
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def _update_arrays(h, *arrays) -> None:
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())


#: ``{id(features dict): (the dict, its digest)}`` of :meth:`TieCache.features_digest` (oldest first)
_DIGESTS: dict = {}
_DIGESTS_SIZE = 64


def _camera_text(cam) -> str:
    return "none" if cam is None else json.dumps(cam.to_dict(), sort_keys=True, default=str)


class TieCache:
    """A cache folder (:class:`~thermogrammetry.store.FolderProject` at ``root``): ``features/<key>.npz`` and
    ``matches/<key>.npz``. Picklable (sent with the tasks to dask workers)."""

    def __init__(self, root):
        self.root = Path(root)
        self._store = FolderProject(self.root, durable=False)

    def __reduce__(self):
        return (TieCache, (str(self.root),))

    # -- keys ----------------------------------------------------------------------------------------------------
    @staticmethod
    def features_key(frame: np.ndarray, options) -> str:
        """Key of the features of ``frame`` (the array the detector gets) with ``options`` (FeatureOptions)."""
        h = hashlib.sha256(f"features {software_digest()} {options!r}".encode())
        _update_arrays(h, frame)
        return h.hexdigest()

    @staticmethod
    def features_digest(features: dict) -> str:
        """Digest of one image's features (the arrays of its ``features/<name>.npz``). Remembered for the last
        dicts seen (by identity, the dict held alive beside its digest): the matching's pairs come image-major and
        read each image's features through one shared, read-only dict (``store._load_npz_cached``)."""
        hit = _DIGESTS.get(id(features))
        if hit is not None and hit[0] is features:
            return hit[1]
        h = hashlib.sha256()
        for k in sorted(features):
            h.update(k.encode())
            _update_arrays(h, features[k])
        digest = h.hexdigest()
        _DIGESTS[id(features)] = (features, digest)
        while len(_DIGESTS) > _DIGESTS_SIZE:
            _DIGESTS.pop(next(iter(_DIGESTS)))
        return digest

    @staticmethod
    def matches_key(fi: dict, fj: dict, cam_i, cam_j, options) -> str:
        """Key of the verified matches of a pair: both images' features, both starting cameras (or None),
        ``options`` (MatchOptions)."""
        text = (f"matches {software_digest()} {TieCache.features_digest(fi)} {TieCache.features_digest(fj)} "
                f"{_camera_text(cam_i)} {_camera_text(cam_j)} {options!r}")
        return hashlib.sha256(text.encode()).hexdigest()

    # -- entries -------------------------------------------------------------------------------------------------
    def get_features(self, key: str) -> bytes | None:
        """The bytes of a feature file, or None."""
        k = f"features/{key}.npz"
        return self._store.read_bytes(k) if self._store.exists(k) else None

    def put_features(self, key: str, data: bytes) -> None:
        self._store.write_bytes(f"features/{key}.npz", data)

    def get_matches(self, key: str) -> tuple[np.ndarray, int, int, str] | None:
        """``(verified index pairs (K, 2) int32, putative count, verified count, reason)`` or None."""
        k = f"matches/{key}.npz"
        if not self._store.exists(k):
            return None
        with np.load(io.BytesIO(self._store.read_bytes(k))) as z:
            return (z["inliers"], int(z["n_putative"]), int(z["n_verified"]), str(z["reason"]))

    def put_matches(self, key: str, inliers: np.ndarray, n_putative: int, n_verified: int, reason: str) -> None:
        buf = io.BytesIO()
        np.savez(buf, inliers=np.asarray(inliers, np.int32).reshape(-1, 2), n_putative=np.int64(n_putative),
                 n_verified=np.int64(n_verified), reason=np.array(reason))
        self._store.write_bytes(f"matches/{key}.npz", buf.getvalue())

    # -- a tracked sequence (the low-texture tracker) -----------------------------------------------------------------
    @staticmethod
    def tracks_key(frames, pattern, cameras, options) -> str:
        """Key of a tracked sequence: ``frames`` an iterable of the (H, W) arrays the tracker gets (read one at a
        time), ``pattern`` the sensor's fixed pattern or None, ``cameras`` one Camera (or None) per frame,
        ``options`` (TrackingOptions)."""
        h = hashlib.sha256(f"tracks {software_digest()} {options!r}".encode())
        n = 0
        for f in frames:
            _update_arrays(h, f)
            n += 1
        h.update(f" {n} frames ".encode())
        if pattern is not None:
            _update_arrays(h, pattern)
        h.update(" ".join(_camera_text(c) for c in (cameras or [])).encode())
        return h.hexdigest()

    def get_tracks(self, key: str):
        """The :class:`~thermogrammetry.sfm.lowtexture.SequenceTracks` kept under ``key``, or None."""
        from ...sfm.lowtexture import SequenceTracks

        k = f"tracks/{key}.npz"
        if not self._store.exists(k):
            return None
        with np.load(io.BytesIO(self._store.read_bytes(k))) as z:
            n = int(z["n_frames"])
            pairs = json.loads(str(z["pairs"]))  # [[a, b, reason, n_putative, has matches], ...]
            xy = [z[f"xy_{a}"] for a in range(n)]
            matches = {(a, b): z[f"m_{a}_{b}"] for a, b, _, _, has in pairs if has}
        return SequenceTracks(xy, matches, {(a, b): r for a, b, r, _, _ in pairs},
                              {(a, b): int(c) for a, b, _, c, _ in pairs})

    def put_tracks(self, key: str, tracks) -> None:
        keys = sorted(set(tracks.reasons) | set(tracks.n_putative) | set(tracks.matches))
        pairs = [[int(a), int(b), str(tracks.reasons.get((a, b), "")), int(tracks.n_putative.get((a, b), 0)),
                  (a, b) in tracks.matches] for a, b in keys]
        arrays = {f"xy_{a}": np.asarray(x, np.float64).reshape(-1, 2) for a, x in enumerate(tracks.xy)}
        arrays.update({f"m_{a}_{b}": np.asarray(m, np.int32).reshape(-1, 2) for (a, b), m in tracks.matches.items()})
        buf = io.BytesIO()
        np.savez(buf, n_frames=np.int64(len(tracks.xy)), pairs=np.array(json.dumps(pairs)), **arrays)
        self._store.write_bytes(f"tracks/{key}.npz", buf.getvalue())


def check_cache_path(path) -> None:
    """Refuse (:class:`~thermogrammetry.errors.ConfigError`) a cache path that exists and is not a folder."""
    if path is not None and Path(path).exists() and not Path(path).is_dir():
        raise ConfigError(f"--cache {path}: is a file; expected a folder (created when absent)")


def open_cache(path) -> TieCache | None:
    """The cache at ``path`` (created when absent), or None for None; a path that is a file or cannot be created is
    refused with a :class:`~thermogrammetry.errors.ConfigError` naming it."""
    if path is None:
        return None
    check_cache_path(path)
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--cache {p}: cannot be created ({exc.strerror or exc})") from None
    return TieCache(p)
