"""What ``survey`` is given (:class:`SurveyInput`) and how it runs (:class:`SurveyOptions`), and the survey's constants."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..._validate import config_keys
from ...enums import StrChoice
from ...errors import ConfigError
from ...sfm.features import FeatureOptions
from ...sfm.globalsfm import GlobalOptions
from ...sfm.lsm import LsmOptions
from ...sfm.matching import MatchOptions
from ...sfm.reconstruction import ReconstructionOptions


IMAGE_SUFFIXES = {".jpg", ".jpeg", ".tif", ".tiff", ".png", ".seq", ".csq", ".fff", ".csv", ".npy", ".bmp", ".is2"}


#: below this share of images with a verified pair, the low-texture features are tried as well
LOW_TEXTURE_SHARE = 0.8


#: SurveyOptions.mapper's choices (the orientation from the tracks)
MAPPERS = ("auto", "incremental", "global")


#: ``mapper="auto"``: the global orientation is tried when the incremental one's largest block holds fewer than this
#: share of the images (the survey's aim: at least 80 % of the frames in one block), and kept when its largest block is larger
AUTO_GLOBAL_BELOW = 0.8


LOW_TEXTURE_BA_GROWTH = 1.0  # tracked low-texture sequences: a bundle adjustment after every added image


LOW_TEXTURE_SELF_CALIBRATION = ("k1", "k2")  # ... and only radial distortion self-calibrated (+ fx, fy without EXIF focal)


LOW_TEXTURE_PATTERN_SIGMA_PX = 8.0  # the tracker removes the sensor pattern's part finer than this blur (fixed_pattern)


LOW_TEXTURE_GUIDED_RADIUS_PX = 10.0  # search radius of guided matching in the low-texture fallback


#: a block of a tracked low-texture sequence is refused when the points its frames show coplanar (one homography per
#: consecutive pair) lie off their plane by more than this share of the block's reprojection RMS (median plane
#: parallax, :func:`~thermogrammetry.sfm.lowtexture.plane_parallax`). Measured: right blocks of the synthetic walk
#: (0.15 K, seeds 0-3, 0.5-3.2 deg off in rotation; seed 5 at 0.2 K) 0.36-0.58; the wrong blocks of the windowed
#: synthetic facade (6-25 deg off) 0.66-1.30, of the 320x256 wall without ground 0.60-0.71 (caught by the planar
#: share below).
LOW_TEXTURE_MAX_PLANE_PARALLAX = 0.85


#: ... and when, on average over its consecutive pairs, less than this share of the points two consecutive frames
#: share lie within 1 % of their depth of one plane (a wall seen by a walk; the ground in front of it is the rest).
#: Wrong blocks explain the walk as a turn with short baselines and their depths scatter. Measured: right blocks of
#: the synthetic walk (seeds 0-3 at 0.15 K, seed 5 at 0.2 K) 0.76-0.91; wrong blocks, 6-36 deg off (windowed facade
#: with 10/14/20 stations, seeds 0-2, with the true camera; the plain wall at 320x256 without ground, seeds 0-1, with
#: the true camera) 0.25-0.40. It is also a test of triangulation strength: a right block with depth noise above ~1 %
#: (short baselines, low resolution) is refused too, and so may be a right block whose frames are mostly NOT one
#: plane (half the points on a second plane: 0.59, tests/test_lowtexture_guard.py).
LOW_TEXTURE_MIN_PLANAR_SHARE = 0.55


VIDEO_SUFFIXES = {".mp4", ".mkv", ".mov", ".avi", ".ts", ".m4v", ".webm"}


SELF_CALIBRATION = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


class GnssMode(StrChoice):
    AUTO = "auto"
    NONE = "none"


@dataclass(frozen=True)
class SurveyOptions:
    """What ``survey`` does and how (typed; :meth:`from_dict` refuses unknown keys).

    Attributes
    ----------
    dji_sdk : str or None
        Path of DJI's Thermal SDK library (``libdirp.so``) for DJI R-JPEGs: their frames become temperatures (K);
        None: ``$THERMOGRAMMETRY_DJI_TSDK`` if set, else raw counts (:mod:`thermogrammetry.io.dji`).
    input_unit : "K" | "C" | None
        Unit of float TIFFs that carry none.
    gnss : "auto" | "none" | path of a gnss.csv
    crs : str or None
        Output CRS (``EPSG:N``); None: the UTM zone of the GNSS positions, or a local frame.
    self_calibrate : tuple of str
        Camera parameters estimated in the final adjustment (ignored when a camera file is given).
    tie_sigma_px : float
        A-priori σ of a tie observation.
    gcp_sigma_m, marker_sigma_px : float
        Defaults when the GCP / measurement files have no σ columns.
    gnss_sigma_m : (3,) or None
        Overrides the σ of every GNSS position (default: RTK σ from the files, or by fix type).
    lever_arm_m : (3,)
        GNSS antenna offset in the camera frame (x right, y down, z forward), metres.
    video_overlap : float
        Target forward overlap of frames extracted from a video or a FLIR SEQ/CSQ recording
        (:class:`~thermogrammetry.io.video.OverlapSelector`).
    low_texture : "auto" (default) | "off"
        ``auto``: low-texture tie points for the thermal frames when fewer than 80 % of them have a verified pair
        with the primary features, or when the orientation leaves fewer than 80 % of them in one block: with positions,
        the sensor's fixed pattern removed (:func:`~thermogrammetry.sfm.features.fixed_pattern`), low-contrast SIFT and
        homography-guided matches (:func:`~thermogrammetry.sfm.matching.guided_matches`); without, the frames tracked
        as a sequence (:mod:`thermogrammetry.sfm.lowtexture`), oriented with a bundle adjustment after every added image
        and self-calibrating only k1, k2 (and fx, fy without an EXIF focal length). Kept only when they connect more
        frames / give a larger block. Guard: every block of a tracked sequence must reconstruct flat what its frames
        show flat (:data:`LOW_TEXTURE_MAX_PLANE_PARALLAX`, :data:`LOW_TEXTURE_MIN_PLANAR_SHARE`); a refused block is
        reported in survey.json (``low_texture``) and its frames are not oriented. The fallback also runs when the
        final adjustment rejects every primary block (:func:`run_survey`). Normally textured surveys are unchanged;
        the measurements behind the default: see the survey page of the docs (docs/verbs/survey.md).
    mapper : "auto" (default) | "incremental" | "global"
        How the block is oriented from the tracks: ``incremental`` (:func:`~thermogrammetry.sfm.reconstruction.reconstruct`),
        ``global`` (:func:`~thermogrammetry.sfm.globalsfm.reconstruct_global`: rotation averaging over the verified
        pairs that close triangles, centres from the rays, one bundle adjustment per rigid part) or ``auto``:
        incremental, and global as well when the incremental's largest block holds fewer than
        :data:`AUTO_GLOBAL_BELOW` (80 %) of the images; global is kept when its largest block is larger and it orients
        no fewer images over all blocks. survey.json's ``mapper`` says which one built the blocks, ``mapper_auto``
        what each gave. Global alone needs pairs whose relative rotations close loops within 5 deg; where each is
        better: see the survey page of the docs (docs/verbs/survey.md).
    global_orientation : GlobalOptions
        Settings of the global orientation (:class:`~thermogrammetry.sfm.globalsfm.GlobalOptions`: pair inliers,
        loop closure, rigid parts), used by ``mapper="global"`` and ``"auto"``.
    tie_refinement : LsmOptions or None
        Least-squares matching of every tie observation against its track's reference patch before the
        orientation (:func:`~thermogrammetry.sfm.lsm.refine_tracks`); None (default) keeps the keypoint positions.
        Off by default because the measurements are mixed: see the survey page of the docs (docs/verbs/survey.md).
    workers : int
        0 or 1 = in this process; N >= 2 = a local dask cluster of N worker processes (:mod:`thermogrammetry.tasks`).
    scheduler : str or None
        Address of an existing dask scheduler (overrides ``workers``).
    cache : str or None
        A folder of features and verified matches kept by content (:mod:`~thermogrammetry.pipeline.survey.cache`;
        created when absent): a later survey of the same frames with the same feature and matching options reads
        them from there instead of computing them again (same outputs, less time). None (default): no cache.
    """

    input_unit: str | None = None
    dji_sdk: str | None = None
    gnss: str = "auto"
    crs: str | None = None
    self_calibrate: tuple = SELF_CALIBRATION
    tie_sigma_px: float = 1.0
    gcp_sigma_m: float = 0.02
    marker_sigma_px: float = 0.5
    gnss_sigma_m: tuple | None = None
    lever_arm_m: tuple = (0.0, 0.0, 0.0)
    video_overlap: float = 0.8
    low_texture: str = "auto"
    mapper: str = "auto"
    features: FeatureOptions = field(default_factory=FeatureOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    reconstruction: ReconstructionOptions = field(default_factory=ReconstructionOptions)
    global_orientation: GlobalOptions = field(default_factory=GlobalOptions)
    tie_refinement: LsmOptions | None = None
    workers: int = 0
    scheduler: str | None = None
    cache: str | None = None

    def __post_init__(self):
        if self.input_unit is not None and str(self.input_unit).upper() not in ("K", "C"):
            raise ConfigError(f"input_unit={self.input_unit!r}: expected 'K' or 'C'")
        if self.crs is not None:
            from pyproj import CRS
            from pyproj.exceptions import CRSError

            try:
                CRS.from_user_input(self.crs)
            except CRSError:
                raise ConfigError(f"crs={self.crs!r}: not a coordinate reference system pyproj knows; expected e.g. EPSG:2056") from None
        if self.cache is not None and not isinstance(self.cache, (str, os.PathLike)):
            raise ConfigError(f"cache={self.cache!r}: expected a folder path or None")
        if not (isinstance(self.workers, (int, np.integer)) and self.workers >= 0):
            raise ConfigError(f"workers={self.workers!r}: expected an integer >= 0")
        for name in ("tie_sigma_px", "gcp_sigma_m", "marker_sigma_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"{name}={v!r}: expected a number > 0")
        if not 0 <= self.video_overlap < 1:
            raise ConfigError(f"video_overlap={self.video_overlap!r}: expected a fraction in [0, 1)")
        if str(self.low_texture).lower() not in ("auto", "off"):
            raise ConfigError(f"low_texture={self.low_texture!r}: expected 'auto' or 'off'")
        object.__setattr__(self, "low_texture", str(self.low_texture).lower())
        if str(self.mapper).lower() not in MAPPERS:
            raise ConfigError(f"mapper={self.mapper!r}: expected one of {', '.join(repr(m) for m in MAPPERS)}")
        object.__setattr__(self, "mapper", str(self.mapper).lower())

    @classmethod
    def from_dict(cls, d: dict) -> "SurveyOptions":
        d = config_keys(cls, d)
        for k, sub in (("features", FeatureOptions), ("matching", MatchOptions), ("reconstruction", ReconstructionOptions),
                       ("global_orientation", GlobalOptions),
                       ("tie_refinement", LsmOptions)):  # tie_refinement: a dict turns it on
            if isinstance(d.get(k), dict):
                d[k] = sub.from_dict(d[k])
        return cls(**d)


@dataclass
class SurveyInput:
    """Everything the user gave (paths as given)."""

    images: list  # files/folders (thermal)
    rgb: list = field(default_factory=list)  # files/folders (RGB)
    camera: Any = None  # thermogrammetry.Camera (fixed intrinsics) or None
    gcps: str | None = None
    gcp_measurements: str | None = None
    checkpoints: str | None = None
    check_measurements: str | None = None
    rig: Any = None  # thermogrammetry.sfm.rig.RigFile (rig mode) or None
    camera_file: dict | None = None  # where ``camera`` came from: io.camera_file.CameraFile.to_dict()
