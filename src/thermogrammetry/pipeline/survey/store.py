"""The survey's artefacts in the project store: every key the survey reads or writes, and :class:`SurveyStore`
(one ``load_X`` / ``save_X`` per artefact over a :class:`~thermogrammetry.store.ProjectStore`).

The keys are those of the project folder (OUT) as documented in :mod:`thermogrammetry.pipeline.survey`: the
inputs manifest ``work/inputs.json``, ``frames/<name>.tif``, ``features/<name>.npz``, ``matches/<i>_<j>.npz``,
``work/pairs.json``, ``work/reconstruction.npz`` / ``.json``, ``work/tie_xy/<name>.npz``, the low-texture
fallback's ``lowtexture/...`` and the outputs (``cameras.json``, ``survey.json``, ``colmap/``, ``sparse.*``).
"""

from __future__ import annotations

import io
import os

import numpy as np

from ...store import FolderProject, ProjectStore

# --- keys (the project folder's layout; byte for byte what earlier versions wrote) -------------------------------
INPUTS_KEY = "work/inputs.json"  # decoded inputs: unit, size, GNSS, camera guess per image; failures; notes
FEATURE_COUNTS_KEY = "work/features.json"  # image name -> number of features
OVERLAY_KEY = "work/overlay.json"  # the burned-in display found by the features step ({"found": false} when none)
OVERLAY_MASK_KEY = "features/overlay.npz"  # its mask
PAIRS_KEY = "work/pairs.json"  # [[i, j, putative, verified, reason]] and the features' description
RECONSTRUCTION_NPZ_KEY = "work/reconstruction.npz"  # poses, points, tracks of the orientation
RECONSTRUCTION_JSON_KEY = "work/reconstruction.json"  # its cameras, status, log
LOW_TEXTURE_KEY = "work/low_texture.json"  # the low-texture fallback's verdict (-> survey.json "low_texture")
LOW_TEXTURE_PREFIX = "lowtexture/"  # the fallback's features and matches (same layout below it)
LOW_TEXTURE_PATTERN_KEY = "lowtexture/pattern.npz"  # the sensor's fixed pattern (guided matching)
LOW_TEXTURE_PATTERN_FINE_KEY = "lowtexture/pattern_fine.npz"  # ... its fine part (the tracker)
PRIMARY_PREFIX = "lowtexture/primary/"  # the primary matching's files, put aside while the fallback is judged
CAMERAS_KEY = "cameras.json"
SURVEY_KEY = "survey.json"
REPORT_KEY = "report.html"
SPARSE_PLY_KEY = "sparse.ply"
SPARSE_LAS_KEY = "sparse.las"
COLMAP_CAMERAS_KEY = "colmap/cameras.txt"
COLMAP_IMAGES_KEY = "colmap/images.txt"
COLMAP_POINTS_KEY = "colmap/points3D.txt"


def frame_key(name: str) -> str:
    """``frames/<name>.tif``: a decoded frame."""
    return f"frames/{name}.tif"


def features_key(name: str, prefix: str = "") -> str:
    """``<prefix>features/<name>.npz``: an image's features (``prefix`` ``lowtexture/``: the fallback's)."""
    return f"{prefix}features/{name}.npz"


def matches_key(i: int, j: int, prefix: str = "") -> str:
    """``<prefix>matches/<i>_<j>.npz``: a verified pair's matches."""
    return f"{prefix}matches/{i}_{j}.npz"


def tie_xy_key(name: str) -> str:
    """``work/tie_xy/<name>.npz``: the tie-point positions the orientation used."""
    return f"work/tie_xy/{name}.npz"


def primary_key(key: str) -> str:
    """Where the primary matching's ``key`` is put aside (``lowtexture/primary/<key>``)."""
    return f"{PRIMARY_PREFIX}{key}"


def _read_frame(project: ProjectStore, name: str) -> np.ndarray:
    import tifffile

    return tifffile.imread(io.BytesIO(project.read_bytes(frame_key(name))))


def _save_npz(project: ProjectStore, key: str, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    project.write_bytes(key, buf.getvalue())


def _load_npz(project: ProjectStore, key: str) -> dict:
    with np.load(io.BytesIO(project.read_bytes(key))) as z:
        return {k: z[k] for k in z.files}


def _tie_xy(project: ProjectStore, name: str) -> np.ndarray:
    """Tie-point positions of an image (px): refined by least-squares matching in ``orient``
    (``work/tie_xy/<name>.npz``), else the keypoints (``features/<name>.npz``)."""
    key = tie_xy_key(name)
    return _load_npz(project, key)["xy"] if project.exists(key) else _load_npz(project, features_key(name))["xy"]


_NPZ_CACHE: "dict[tuple, dict]" = {}
_NPZ_CACHE_SIZE = 48  # files (~1.5 MB each for 3000 RootSIFT features): memory stays bounded


def _load_npz_cached(project: ProjectStore, key: str) -> dict:
    """``_load_npz`` through a small per-process LRU cache (features in matching, the fixed pattern per frame).

    Pairs come image-major, so each image's features would otherwise be read and decompressed once per pair.
    Folder projects key the cache by the file's path, size and modification time (a rewritten file is
    read again); other stores are read every time. The arrays returned are shared: callers must not modify them.
    """
    if not isinstance(project, FolderProject):
        return _load_npz(project, key)
    path = project.root / key
    try:
        st = path.stat()
    except OSError:
        return _load_npz(project, key)  # the store reports the missing file with its own message
    ck = (str(path), st.st_size, st.st_mtime_ns)
    hit = _NPZ_CACHE.pop(ck, None)
    if hit is None:
        hit = _load_npz(project, key)
    _NPZ_CACHE[ck] = hit  # most recently used last
    while len(_NPZ_CACHE) > _NPZ_CACHE_SIZE:
        _NPZ_CACHE.pop(next(iter(_NPZ_CACHE)))
    return hit


def _load_reconstruction(project: ProjectStore):
    from ...camera import Camera
    from ...results import Outcome, Termination
    from ...sfm.reconstruction import ImageStatus, Reconstruction
    from ...sfm.tracks import Tracks

    z = _load_npz(project, RECONSTRUCTION_NPZ_KEY)
    meta = project.read_json(RECONSTRUCTION_JSON_KEY)
    cams = [Camera.from_dict(meta["cameras"][c], source=RECONSTRUCTION_JSON_KEY) for c in meta["camera_ids"]]
    tr = Tracks(z["track"], z["image"], z["feature"])
    rec = Reconstruction(Outcome(Termination(meta["termination"]), meta["reason"]), cams, z["image_camera"], z["R"], z["t"],
                         z["registered"].astype(bool), z["component"], z["points"], tr, z["obs_valid"].astype(bool),
                         [ImageStatus(s["registered"], s["component"], s["reason"]) for s in meta["status"]], meta["log"])
    return rec, meta


def _write_lines(project: ProjectStore, key: str, lines) -> None:
    """Write an iterable of text lines (without their newline) as ``key``: ``"\n".join(lines) + "\n"``.

    Folder projects get the lines streamed to a temporary file renamed into place (atomic, as ``write_bytes``;
    the text of a large block's COLMAP model is never held whole); other stores get the joined text.
    """
    path = project.local_path(key)
    if path is None:
        project.write_text(key, "".join(line + "\n" for line in lines))
        return
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            for line in lines:
                f.write(line)
                f.write("\n")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class SurveyStore:
    """The survey's artefacts over a :class:`~thermogrammetry.store.ProjectStore` (OpenSfM's ``DataSet``): one
    ``load_X`` / ``save_X`` per artefact, the keys above. Stateless: ``SurveyStore(project)`` is cheap."""

    def __init__(self, project: ProjectStore):
        self.project = project

    # the inputs manifest, the features step's records
    def load_inputs(self) -> dict:
        return self.project.read_json(INPUTS_KEY)

    def save_inputs(self, inputs: dict) -> None:
        self.project.write_json(INPUTS_KEY, inputs)

    def load_feature_counts(self) -> dict:
        return self.project.read_json(FEATURE_COUNTS_KEY)

    def save_feature_counts(self, counts: dict) -> None:
        self.project.write_json(FEATURE_COUNTS_KEY, counts)

    def load_overlay(self) -> dict:
        """``work/overlay.json``; ``{}`` when the features step wrote none."""
        return self.project.read_json(OVERLAY_KEY) if self.project.exists(OVERLAY_KEY) else {}

    def save_overlay(self, overlay: dict) -> None:
        self.project.write_json(OVERLAY_KEY, overlay)

    # frames, features, matches, tie points
    def read_frame(self, name: str) -> np.ndarray:
        return _read_frame(self.project, name)

    def load_features(self, name: str, prefix: str = "") -> dict:
        return _load_npz(self.project, features_key(name, prefix))

    def save_features(self, name: str, prefix: str = "", **arrays) -> None:
        _save_npz(self.project, features_key(name, prefix), **arrays)

    def load_matches(self, i: int, j: int, prefix: str = "") -> np.ndarray:
        return _load_npz(self.project, matches_key(i, j, prefix))["idx"]

    def save_matches(self, i: int, j: int, idx: np.ndarray, prefix: str = "") -> None:
        _save_npz(self.project, matches_key(i, j, prefix), idx=idx)

    def load_tie_xy(self, name: str) -> np.ndarray:
        """The tie-point positions of an image: those the orientation used, else the keypoints."""
        return _tie_xy(self.project, name)

    def save_tie_xy(self, name: str, xy: np.ndarray) -> None:
        _save_npz(self.project, tie_xy_key(name), xy=xy)

    # pairs, reconstruction, the low-texture verdict
    def has_pairs(self) -> bool:
        return self.project.exists(PAIRS_KEY)

    def load_pairs(self) -> dict:
        return self.project.read_json(PAIRS_KEY)

    def save_pairs(self, pairs: dict) -> None:
        self.project.write_json(PAIRS_KEY, pairs)

    def load_reconstruction(self):
        """``(Reconstruction, meta dict)`` of the last orientation."""
        return _load_reconstruction(self.project)

    def load_reconstruction_arrays(self) -> dict:
        return _load_npz(self.project, RECONSTRUCTION_NPZ_KEY)

    def save_reconstruction_arrays(self, **arrays) -> None:
        _save_npz(self.project, RECONSTRUCTION_NPZ_KEY, **arrays)

    def load_reconstruction_meta(self) -> dict:
        return self.project.read_json(RECONSTRUCTION_JSON_KEY)

    def save_reconstruction_meta(self, meta: dict) -> None:
        self.project.write_json(RECONSTRUCTION_JSON_KEY, meta)

    def has_low_texture(self) -> bool:
        return self.project.exists(LOW_TEXTURE_KEY)

    def load_low_texture(self) -> dict:
        """``work/low_texture.json``; ``{}`` when the orientation wrote none."""
        return self.project.read_json(LOW_TEXTURE_KEY) if self.project.exists(LOW_TEXTURE_KEY) else {}

    def save_low_texture(self, verdict: dict) -> None:
        self.project.write_json(LOW_TEXTURE_KEY, verdict)

    # outputs
    def has_survey(self) -> bool:
        return self.project.exists(SURVEY_KEY)

    def load_survey(self) -> dict:
        return self.project.read_json(SURVEY_KEY)

    def save_survey(self, summary: dict) -> None:
        self.project.write_json(SURVEY_KEY, summary)
