"""``survey``: thermal frames (and RGB images) -> one oriented, georeferenced block with its accuracy report.

The workflow is a list of small steps (:mod:`thermogrammetry.pipeline.steps`) over a project store; each
reads what the previous wrote and writes a small report under ``reports/``:

================  ==================================================================================
``inputs``        decode every input (radiometric files, 8-bit renderings, float TIFFs, video frames) to
                  ``frames/<name>.tif`` (float32 K, uint16 counts or uint8 display numbers) and
                  ``work/inputs.json`` (unit, size, GNSS, camera guess per image; failures by name)
``features``      ``features/<name>.npz`` per image (dask tasks); a camera display burned into the 8-bit
                  thermal frames found first and kept out (``features/overlay.npz``, ``work/overlay.json``)
``matching``      candidate pairs from GNSS/sequence, ``matches/<i>_<j>.npz`` verified (dask tasks)
``orient``        tracks + incremental orientation -> ``work/reconstruction.npz``
``georef``        similarity to GNSS/GCPs, final adjustment with GNSS priors and weighted GCPs, images with
                  too few ties for a resection added at their RTK GNSS positions, check points intersected
                  afterwards -> ``cameras.json``, ``survey.json``, exports, report
================  ==================================================================================

Outputs (OUT): ``cameras.json`` (:mod:`thermogrammetry.io.oriented`), ``survey.json``, ``report.html``,
``colmap/`` (cameras.txt, images.txt, points3D.txt), ``sparse.ply``, ``sparse.las``, ``frames/``,
``features/``, ``matches/``, ``reports/``.

``survey.json`` keys: ``images_total``, ``images_oriented``, ``components`` (images per oriented block,
largest first), ``reprojection_rms_px`` (root mean square of the residual vector length of the tie
observations, px), ``gcps`` / ``checkpoints`` (``n, rmse_x.., mae_x.., min_x.., max_x..`` in metres; n = 0
and nulls when none), ``crs``, ``seconds`` and more detail (per image, per step, camera; per block ``blocks``:
datum, σ0, self-calibration and its steps, ``added_at_gnss``: images added at their GNSS positions; a rejected
block's ``rejected`` reason and ``moved_to_blocks``: block -> its images that a later pass added there), ``overlay``
(a display burned into 8-bit frames: ``share`` of the frame masked, ``frames`` it was found from, ``images`` of that
``size`` it applies to; null when none was found or the frames are radiometric). Rig mode
(``--rig``) adds ``rig`` (file, pairs, blocks with R*, t, σ, own observations per thermal image, or the reason an
estimate was refused; ``rig_only``: thermal images posed by the rig alone; ``registration``: R*, t and the thermal
focal scale from image registration when the rig is to be estimated and < 3 thermal frames tie to their RGB
partners -- success or the reason, σ, spread, NCC and offset per pair, see :mod:`thermogrammetry.sfm.rigreg`) and
``images_rig_only``; those images count in ``images_oriented`` (R*, t given, estimated from enough evidence, or
registered) and carry ``rig_only: true`` and a ``reason`` in ``images`` (see :mod:`thermogrammetry.sfm.rig`).

Tie-point coordinates follow the pixel-centre convention (:mod:`thermogrammetry.sfm.keypoints`: OpenCV's SIFT
offset of +0.25 px removed).
"""

from __future__ import annotations

import contextlib

import io
import itertools
import json
import os
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .._memory import release_free_heap
from ..enums import StrChoice
from ..errors import ConfigError, DataFileError, ThermogrammetryError, UnsupportedFormatError
from ..sfm.features import FeatureOptions
from ..sfm.matching import MatchOptions
from ..sfm.lsm import LsmOptions
from ..sfm.globalsfm import GlobalOptions, reconstruct_global
from ..sfm.reconstruction import ReconstructionOptions
from .project import FolderProject, ProjectStore
from .._validate import config_keys

__all__ = ["SurveyOptions", "SurveyInput", "survey_steps", "run_survey", "VIDEO_SUFFIXES", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".tif", ".tiff", ".png", ".seq", ".csq", ".fff", ".csv", ".npy", ".bmp", ".is2"}
#: a block whose final tie-point reprojection RMS exceeds this is rejected (reported, not exported)
BLOCK_RMS_GATE_PX = 3.0
#: an image whose adjusted antenna position is more than this many GNSS σ from its GNSS position (on any axis) is
#: named in survey.json (``gnss_flagged``) and in the notes: its orientation or its GNSS tag is wrong
GNSS_FLAG_SIGMA = 5.0

#: a GNSS-georeferenced block whose final adjustment stops at its iteration limit with more than this share of its
#: camera centres beyond GNSS_FLAG_SIGMA from their GNSS positions is rejected: on a synthetic 40-station building
#: ring (seed 0, default options) a 20-image block 5.6 deg RMS / 19 deg max off its true rotations ended so (8 of 20
#: centres at 5-100 σ, 50 iterations); right blocks converge with their centres within ~4 σ (48-station ring, M3T)
BLOCK_GNSS_FAR_SHARE = 0.25
#: a block georeferenced on RTK-grade GNSS (median horizontal σ <= PRECISE_GNSS_SIGMA_M) or on GCPs whose cameras'
#: rotation σ (median over its images of the largest axis) exceeds this is rejected: its datum (positions nearly on a
#: line or a short arc, GCPs close together) does not fix its rotation, and the block's own shape errors then tilt
#: it by several σ. 40-station building rings (RTK σ 3/5 cm): a 4-image block on a 27 deg arc, σ 5.3 deg, 6.6-7.3
#: deg off; a 7-image block on a 63 deg arc, σ 1.5 deg, 4.9-6.7 deg off; right blocks of the same rings σ 0.2-0.7 deg
#: and 0.2-1.6 deg off; the M3T flight 0.04 deg. With coarse GNSS (σ of metres) the rotation σ is the GNSS's and is
#: reported, not gated
BLOCK_ROTATION_SIGMA_DEG = 1.0
PRECISE_GNSS_SIGMA_M = 0.10


def _tie_rms(v) -> float:
    """Root mean square of the lengths of residual vectors ``v`` (K, 2) px (NaN rows skipped; NaN when empty)."""
    v = np.asarray(v, float)
    return float(np.sqrt(np.nanmean(np.sum(v**2, axis=1)))) if len(v) else float("nan")


def _precise_datum(datum, ctrl, images) -> bool:
    """Whether a block's datum (:class:`~thermogrammetry.sfm.georef.Datum`) is precise enough for the rotation-σ
    gate: GCPs, or RTK-grade GNSS."""
    if not datum.from_gnss:
        return True
    if datum.from_attitude:  # the rotation about a GNSS line comes from the gimbal: its σ is reported, not gated
        return False
    s = np.asarray(ctrl.gnss_sigma, float)[np.asarray(images, np.int64)][:, :2]
    s = s[np.isfinite(s)]
    return bool(len(s)) and float(np.median(s)) <= PRECISE_GNSS_SIGMA_M


def _block_rotation_sigma(fa, images) -> float:
    """Median over the block's images of their largest rotation σ (degrees); 0 when no σ was computed."""
    r = np.asarray(fa.rotation_std_deg, float)[np.asarray(images, np.int64)]
    m = np.max(r, axis=1) if len(r) else np.zeros(0)
    m = m[np.isfinite(m)]
    return float(np.median(m)) if len(m) else 0.0


def _gnss_far_share(rec, images, ctrl) -> float:
    """Share of the block's images with GNSS whose adjusted centre is more than GNSS_FLAG_SIGMA from it (any axis)."""
    from ..sfm.georef import gnss_misfit

    z = [float(np.max(zz)) for _, zz in gnss_misfit(rec, images, ctrl).values()]
    return float(np.mean(np.array(z) > GNSS_FLAG_SIGMA)) if z else 0.0


#: self-calibration steps down this ladder (each rung intersected with the parameters asked for) while the
#: block cannot carry it: the adjustment stops rank deficient, a free parameter's σ is not finite, or the
#: estimate is implausible (below)
SELF_CALIBRATION_LADDER = (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), ("fx", "fy", "k1", "k2"), ("fx", "fy", "k1"),
                           ("fx", "fy"), ())
#: ... and the rungs a camera takes instead once its focal length was refused as implausible (more than
#: INTRINSICS_PLAUSIBLE["focal"] from the file's EXIF value): the block does not determine its interior orientation
#: (a single strip or a facade pass over flat ground without GCPs: focal length and ground distance trade freely),
#: so focal length and principal point stay at their start and only the distortion, which the ties determine in
#: the image, is self-calibrated. Measured on the M3T flight's frames 0008-0023 alone (one E-W strip on RTK, no
#: camera file): the focal length ran to 2007-2577 px on the first three rungs, and the (fx, fy) rung was accepted
#: at 738.6/714.9 px (the full flight's 783.2/781.0) with the orientation's distortion held: rotations 2.33 deg
#: RMS from the full flight's block, the full flight's tie points re-intersected through the strip's cameras
#: 0.59/3.03/6.16 m RMS off in X/Y/Z; on (k1, k2, p1, p2) with the EXIF focal length 758.3 px: 0.28 deg,
#: 1.06/0.25/2.28 m (Z: the EXIF focal length is 3 % short; with the full flight's camera file 0.03/0.57/0.16 m)
FIXED_INTERIOR_LADDER = (("k1", "k2", "p1", "p2"), ("k1", "k2"), ("k1",), ())
#: plausibility of self-calibrated intrinsics against their start (EXIF focal length and pixel pitch, or the
#: image centre): focal length within ±30 % (only when the start is the file's EXIF focal length), fy/fx within ±5 % (thermal and RGB sensors have square pixels to
#: well under 1 %), principal point within 15 % of the frame, radial distortion at the frame corner below 20 %
#: of the radius. Measured on the Thermitage fresco walls (thermal only, 6 frames tied by wrong matches): fy/fx
#: 1.26 and a rank-deficient solve, reported as an oriented block before this check.
INTRINSICS_PLAUSIBLE = {"focal": 0.30, "aspect": 0.05, "principal_point": 0.15, "corner_distortion": 0.20}

#: below this share of images with a verified pair, the low-texture features are tried as well
LOW_TEXTURE_SHARE = 0.8
#: SurveyOptions.mapper's choices (the orientation from the tracks)
MAPPERS = ("auto", "incremental", "global")
#: ``mapper="auto"``: the global orientation is tried when the incremental one's largest block holds fewer than this
#: share of the images (issue 10's "at least 80 % of the frames in one block"), and kept when its largest block is larger
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

# thermal cores whose pixel pitch the files do not state (µm); focal length comes from EXIF
_PITCH_UM = {"M3T": 12.0, "M30T": 12.0, "H20T": 12.0, "H20N": 12.0, "H30T": 12.0, "M4T": 12.0, "M3TD": 12.0,
             "XT2": 17.0, "ZH20T": 12.0, "MAVIC2-ENTERPRISE-ADVANCED": 12.0, "M2EA": 12.0}


class GnssMode(StrChoice):
    AUTO = "auto"
    NONE = "none"


@dataclass(frozen=True)
class SurveyOptions:
    """What ``survey`` does and how (typed; :meth:`from_dict` refuses unknown keys).

    Attributes
    ----------
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
        with the primary features (``features``), or when the orientation leaves fewer than 80 % of them in one
        block (descriptor matches on noise and on the sensor's pattern verify pairs no orientation can use); kept
        only when they connect more frames / give a larger block, else everything stays as it was. With positions
        (GNSS): the sensor's fixed pattern estimated from the frames and subtracted
        (:func:`~thermogrammetry.sfm.features.fixed_pattern`), SIFT with a low contrast threshold and matches guided
        by a homography (:func:`~thermogrammetry.sfm.matching.guided_matches`). Without positions: the frames are
        taken as a sequence in input order and tracked frame to frame (:mod:`thermogrammetry.sfm.lowtexture`: the
        pattern's fine part removed, phase correlation + Lucas-Kanade, forward-backward, coherence, NCC and
        essential-matrix checks); such a block is oriented with a bundle adjustment after every added image and
        self-calibrates only k1, k2 (and fx, fy without an EXIF focal length).

        Guard (why ``auto`` is the default): every block of a tracked sequence must reconstruct flat what its frames
        show flat -- the points of each consecutive pair that agree with one homography must lie on a plane in 3D
        within a share of the block's reprojection RMS (:data:`LOW_TEXTURE_MAX_PLANE_PARALLAX`), and on average
        :data:`LOW_TEXTURE_MIN_PLANAR_SHARE` of the points of consecutive frames must lie within 1 % of their depth
        of one plane (:func:`~thermogrammetry.sfm.lowtexture.plane_parallax`); a refused block is reported in survey.json
        (``low_texture``, the notes and every frame's reason) and its frames are not oriented (or the primary result
        is kept when the fallback ran after it). In the final adjustment, a tracked block whose limited
        self-calibration is refused by the plausibility checks is rejected as well. The fallback only runs when fewer
        than 80 % of the thermal frames have a verified pair or end in one block, so normally textured surveys are
        unchanged. Measured (``benchmarks/survey_lowtexture.py --synthetic``, plain wall, 0.15 K smooth contrast,
        0.08 K pattern, 0.04 K NETD, 30 frames; pycolmap 0 models, ``off`` 0/30): see benchmarks/README.md; the
        windowed facade of ``synthetic.facade`` (15 windows with glass reflecting the sky, 14 stations at 12 m, no
        EXIF focal length; ``off`` orients nothing) gave ``auto`` a 14/14 block 25 deg off before the guard, which now
        refuses it (plane parallax 1.28 x the RMS, planar share 0.29; right walk blocks 0.42-0.58 and 0.76-0.85);
        so are the wrong blocks of the same facade with 10 and 20 stations and with the true camera, and of the
        plain wall at 320x256 px without ground (a single plane, 20/20 frames 36 deg off). When the final adjustment
        rejects every block of the primary orientation, the fallback runs then (:func:`run_survey`): walk seed 4's
        primary orientation builds a 30/30 block on SIFT matches of noise that no adjustment can determine; the
        fallback then orients 30/30 in one block (2.59 deg RMS).
    mapper : "auto" (default) | "incremental" | "global"
        How the block is oriented from the tracks: ``incremental`` (:func:`~thermogrammetry.sfm.reconstruction.reconstruct`:
        initial pair, resection, triangulation, bundle adjustments), ``global``
        (:func:`~thermogrammetry.sfm.globalsfm.reconstruct_global`: rotation averaging over the verified pairs that
        close triangles, camera centres from the rays with the rotations fixed, one bundle adjustment per rigid part)
        or ``auto``: incremental, and global as well when the incremental's largest block holds fewer than
        :data:`AUTO_GLOBAL_BELOW` (80 %) of the images; global is kept when its largest block is larger and it orients
        no fewer images over all blocks (else, and on a tie, the incremental). survey.json's ``mapper`` says which one
        built the blocks, ``mapper_auto`` what each gave.
        Global orients frames whose tracks rarely reach a third frame but whose pairs close loops (synthetic walk
        past a wall, 16 frames, tracks of 2-3 frames: 16/16 in two rigid parts against the incremental 9,
        ``tests/test_sfm_global.py``), the real M3T nadir flight as the incremental does (32/32, centres against RTK
        1.7/1.3/1.6 cm RMS against 1.9/1.4/1.6 cm; orientation step 22 s against 8 s) and a synthetic 64-station
        building ring with more frames (56/64 against 52/64, rotations 0.76 deg RMS against 0.51,
        ``benchmarks/survey_building.py --mapper incremental global``). Global alone is not the default because it
        needs pairs whose relative rotations close loops within 5 deg: the 40-station ring (9 deg steps) keeps 19 of
        50 pairs and orients 0/40 (incremental 28/40); the real frescoes' thermal frames (ASIFT; the pairs' rotations
        10 deg median off, 3 of 45 pairs close a triangle) 0/40 (incremental 4/40). ``auto`` keeps the incremental
        block on both and costs nothing where the incremental block holds >= 80 % (M3T).
    global_orientation : GlobalOptions
        Settings of the global orientation (:class:`~thermogrammetry.sfm.globalsfm.GlobalOptions`: pair inliers,
        loop closure, rigid parts), used by ``mapper="global"`` and ``"auto"``.
    tie_refinement : LsmOptions or None
        Least-squares matching of every tie observation against its track's reference patch before the
        orientation (:func:`~thermogrammetry.sfm.lsm.refine_tracks`); None (default) keeps the keypoint
        positions. Off by default because the measurements are mixed (2026-11-25, ``benchmarks/survey_building.py``
        and ``benchmarks/survey.py --no-colmap``, each with ``--refine-ties off|lsm``): synthetic building ring,
        rotation error RMS 64 stations 1.00° → 0.43° (59 → 64/64 oriented), 96 stations 0.71° → 0.47°,
        40 stations 2.3° → 1.9° (13/40 either way); real DJI M3T flight: RMS 0.452 → 0.325 px, but camera
        centres against RTK X/Y/Z 4.1/2.2/4.3 → 7.4/3.5/4.4 cm, self-calibrated fx 981 ± 5 → 964 ± 4 px, and
        the orientation step 18.6 → 36.4 s (loaded machine).
    workers : int
        0 = in-process; N = local dask cluster of N worker processes.
    scheduler : str or None
        Address of an existing dask scheduler (overrides ``workers``).
    """

    input_unit: str | None = None
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


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
def _name_list(names: Sequence[str], k: int = 3) -> str:
    """The first ``k`` names, comma-separated, with " ..." when there are more (for notes)."""
    return ", ".join(names[:k]) + (" ..." if len(names) > k else "")


def expand_inputs(items: Sequence, *, kind: str = "thermal") -> tuple[list[Path], list[str]]:
    """Files from files/folders (folders: their image and video files, sorted; subfolders not entered; a CSV
    that is no temperature matrix — GCPs, GNSS, measurements kept next to the images — is skipped with a note,
    :func:`thermogrammetry.io.matrix.looks_like_matrix`).

    Returns (files, notes): notes say what was skipped and why.
    """
    from ..io.matrix import looks_like_matrix

    files, notes = [], []
    for it in items:
        p = Path(it)
        if p.is_dir():
            entries = sorted(p.iterdir())  # listed once (a flight folder may hold thousands of frames)
            inside, side, other = [], [], []
            for q in (q for q in entries if q.is_file()):
                sfx = q.suffix.lower()
                if sfx in IMAGE_SUFFIXES | VIDEO_SUFFIXES and (sfx != ".csv" or looks_like_matrix(q)):
                    inside.append(q)
                elif not q.name.startswith("."):
                    (side if sfx == ".csv" else other).append(q.name)
            subs = [q.name for q in entries if q.is_dir()]
            if side:
                notes.append(f"{p}: {len(side)} CSV file(s) that are not temperature matrices skipped "
                             f"({_name_list(side)}; GCPs, GNSS and measurements go to their own options)")
            if other:
                notes.append(f"{p}: {len(other)} file(s) that are not images or videos skipped ({_name_list(other)})")
            if subs:
                notes.append(f"{p}: subfolder(s) not entered: {_name_list(subs)} (name them to include them)")
            files += inside
        elif p.exists():
            files.append(p)
        else:
            files.append(p)  # reported as failed by the decode step, with the reason
    return files, notes


def _geotag_dict(gt) -> dict:
    if gt is None or gt.latitude_deg is None or gt.longitude_deg is None:
        return {}
    return {"lat": gt.latitude_deg, "lon": gt.longitude_deg, "alt": gt.altitude_m, "rtk_flag": gt.rtk_flag,
            "rtk_std_m": list(gt.rtk_std_m) if gt.rtk_std_m else None,
            "gimbal_yaw_deg": gt.gimbal_yaw_deg, "gimbal_pitch_deg": gt.gimbal_pitch_deg,
            "gimbal_roll_deg": gt.gimbal_roll_deg}


def _attitudes(inputs: dict, crs: str | None) -> np.ndarray | None:
    """(n, 3, 3) cam_from_world rotations in ``crs`` from the files' gimbal angles (NaN where an image has none;
    :mod:`thermogrammetry.sfm.attitude`), or None when no image has all three angles or there is no CRS."""
    from ..sfm.attitude import cam_from_world_from_gimbal, meridian_convergence_deg

    keys = ("gimbal_yaw_deg", "gimbal_pitch_deg", "gimbal_roll_deg", "lon", "lat")
    a = np.array([[(im.get("geotag") or {}).get(k) for k in keys] for im in inputs["images"]], dtype=float)
    have = np.all(np.isfinite(a), axis=1)
    if crs is None or not have.any():
        return None
    out = np.full((len(a), 3, 3), np.nan)
    gam = meridian_convergence_deg(crs, a[have, 3], a[have, 4])
    out[have] = cam_from_world_from_gimbal(a[have, 0], a[have, 1], a[have, 2], gam)
    return out


def _camera_guess(width, height, md) -> dict:
    """Focal length in px from EXIF (35 mm equivalent, or focal + pixel pitch); notes when guessed."""
    exif = getattr(md, "exif", {}) or {}
    raw = exif.get("raw_exif", {}) if isinstance(exif, dict) else {}
    f35 = raw.get(41989)
    model = (getattr(md, "model", None) or "").upper()
    focal = getattr(md, "focal_length_mm", None)
    pitch = getattr(md, "pixel_pitch_um", None)
    pitch = pitch[0] if isinstance(pitch, (tuple, list)) else pitch
    if pitch is None and model in _PITCH_UM:
        pitch = _PITCH_UM[model]
    if focal and pitch:
        return {"f_px": focal / (pitch * 1e-3), "source": f"EXIF focal {focal:g} mm / pitch {pitch:g} µm", "pitch_um": pitch}
    if f35:
        try:
            f35 = float(f35)
        except (TypeError, ValueError):
            f35 = None
    if f35:
        return {"f_px": f35 * np.hypot(width, height) / 43.2666, "source": f"EXIF 35 mm-equivalent focal {f35:g} mm", "pitch_um": pitch}
    if focal:
        return {"f_px": focal / 0.017, "source": f"EXIF focal {focal:g} mm, pixel pitch assumed 17 µm", "pitch_um": 17.0}
    return {"f_px": 1.0 * max(width, height), "source": "no focal length in the file: 1.0 x image width assumed (self-calibrated)",
            "pitch_um": None}


def frame_values(im, path, counts_dtype=np.uint16) -> tuple[str, np.ndarray, str]:
    """One decoded frame (:func:`thermogrammetry.io.iter_thermal`) -> ``(name suffix, values, unit)``: float32 kelvin
    (``"K"``) when the reader gave temperatures, else the raw counts (``"counts"``, as ``counts_dtype``); the suffix is
    ``_fNNNNN`` for a frame of a sequence, else empty. A temperature frame without one finite value is an
    :class:`UnsupportedFormatError` naming ``path``."""
    if im.temperature_k is not None:
        arr, unit = np.asarray(im.temperature_k, np.float32), "K"
        if not np.isfinite(arr).any():
            raise UnsupportedFormatError(f"{path}: no finite temperature in the frame")
    else:
        arr, unit = np.asarray(im.raw_counts, counts_dtype), "counts"
    fi = im.metadata.frame_index
    return ("" if fi is None else f"_f{fi:05d}"), arr, unit


#: a video whose frame-to-frame motion cannot be measured in most frames is sampled at this interval (s) instead: a
#: walk at 1 m/s 4 m from a wall moves ~20 % of a 40-degree frame in 0.6 s, a UAV at 5 m/s and 60 m in ~1.7 s
VIDEO_FALLBACK_INTERVAL_S = 0.5

#: multi-frame thermal recordings (FLIR SEQ/CSQ): their frames are selected for a forward overlap like a video's
SEQUENCE_SUFFIXES = {".seq", ".csq"}


def _decode(path: Path, input_unit: str | None, overlap: float | None = None):
    """One input file -> list of (name suffix, array, unit, geotag dict, camera guess dict, note).

    A FLIR SEQ/CSQ recording with several frames keeps only those that :class:`~thermogrammetry.io.video.OverlapSelector`
    picks for ``overlap`` (a recording at 30 Hz holds frames that overlap by > 99 %; all of them would be near-duplicate
    images and an unbounded memory), after a first pass that estimates the sensor's static pattern; ``overlap=None``
    keeps every frame."""
    from ..io import iter_thermal

    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        raise UnsupportedFormatError(f"{path}: video input is decoded by the inputs step (io.video)")
    try:
        select, n_frames = None, None
        if suffix in SEQUENCE_SUFFIXES and overlap is not None:
            from ..io.video import OverlapSelector, static_pattern_of

            count = [0]

            def values():
                for im in iter_thermal(path, unit=input_unit):
                    count[0] += 1
                    yield frame_values(im, path)[1]

            static = static_pattern_of(values())
            n_frames = count[0]
            if n_frames > 1:
                select = OverlapSelector(overlap, static)

        def decoded(select):
            out = []
            for im in iter_thermal(path, unit=input_unit):
                sfx, arr, unit = frame_values(im, path)
                if select is not None and not select(arr):
                    continue
                md = im.metadata
                h, w = arr.shape
                notes = ["raw counts (no documented conversion): geometry and products labelled as counts"] if unit == "counts" else []
                if select is not None:
                    notes.append(f"frame {md.frame_index} of {n_frames} in the recording (frames kept for "
                                 f"{overlap:.0%} forward overlap)")
                out.append((sfx, arr, unit, _geotag_dict(md.geotag), _camera_guess(w, h, md), "; ".join(notes)))
            return out

        out = decoded(select)
        if select is not None and not select.motion_measured:
            # most consecutive frames show no measurable motion: not a video-rate recording (an interval recording
            # whose frames do not overlap, or noise only), every frame is kept
            out = decoded(None)
        return out
    except UnsupportedFormatError as exc:
        not_radiometric = "radiometric" in str(exc) or "no reader" in str(exc).lower() or "not a" in str(exc).lower()
        if not not_radiometric or suffix not in (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"):
            raise
    # plain image: 8-bit rendering (geometry only) or 16-bit grey without a unit
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UnsupportedFormatError(f"{path}: neither a radiometric thermal file nor an image OpenCV can decode")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    unit = "dn" if img.dtype == np.uint8 else "counts"
    if img.dtype not in (np.uint8, np.uint16):
        raise UnsupportedFormatError(f"{path}: {img.dtype} image without a unit; give --input-unit K|C for float temperature TIFFs")
    geo, md = {}, None
    try:
        from ..io.exif import read_exif

        ex = read_exif(bytes(data[: 1 << 20])) if suffix in (".jpg", ".jpeg") else {}
        if ex.get("latitude_deg") is not None:
            geo = {"lat": ex["latitude_deg"], "lon": ex["longitude_deg"], "alt": ex.get("altitude_m"), "rtk_flag": None, "rtk_std_m": None}

        class _Md:  # what _camera_guess reads
            exif = ex
            model = ex.get("model")
            focal_length_mm = ex.get("focal_length_mm")
            pixel_pitch_um = ex.get("pixel_pitch_um")  # EXIF FocalPlane resolution, when written
        md = _Md
    except Exception:  # noqa: BLE001 - EXIF is optional for a plain image; its absence is noted below
        md = None
    h, w = img.shape
    note = "8-bit rendering: geometry only, these frames carry no temperatures" if unit == "dn" else \
        "16-bit image without a declared mapping: values kept as counts"
    return [("", img, unit, geo, _camera_guess(w, h, md) if md else _camera_guess(w, h, None), note)]


def _decode_video(path: Path, overlap: float):
    try:
        from ..io.video import read_video_frames
    except ImportError:
        raise UnsupportedFormatError(f"{path}: video input needs thermogrammetry.io.video, which this installation lacks") from None
    def decoded(note, **how):
        out = []
        for fr in read_video_frames(path, **how):
            h, w = fr.image.shape[:2]
            out.append((f"_f{fr.index:06d}", fr.image, fr.unit, {}, _camera_guess(w, h, None),
                        f"video frame at {fr.time_s:.2f} s" + (f" ({note})" if note else "")))
        return out

    stats: dict = {}
    out = decoded("", forward_overlap=overlap, stats=stats)
    sel = stats.get("selector")
    if sel is not None and not sel.motion_measured:
        # the motion between frames could not be measured in most of the video (too little texture left once the
        # static pattern is out): frames at a fixed interval instead of none after the first
        fps = stats["fps"] if np.isfinite(stats["fps"]) and stats["fps"] > 0 else 25.0
        every = max(1, int(round(fps * VIDEO_FALLBACK_INTERVAL_S)))
        out = decoded(f"the frame-to-frame motion was measurable in {sel.measured} of {sel.pairs} frames: frames "
                      f"taken every {every / fps:.2f} s instead of for {overlap:.0%} overlap", every=every)
    return out


#: readers of radiometric JPEGs (:func:`thermogrammetry.io.thermal.sniff_reader`): such a file is a thermal frame
RADIOMETRIC_JPEG_READERS = ("flir_rjpeg", "workswell_rjpeg", "dji_rjpeg")


def _radiometric_jpeg(path: Path) -> bool:
    """Whether ``path`` is a JPEG that one of the radiometric readers accepts (a DJI _T / FLIR R-JPEG)."""
    from ..io.thermal import sniff_reader

    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return False
    try:
        return sniff_reader(path).name in RADIOMETRIC_JPEG_READERS
    except (ThermogrammetryError, OSError, ValueError):
        return False


def step_inputs(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions, progress: Callable | None = None) -> dict:
    """Decode every input to ``frames/<name>.tif``; ``work/inputs.json``."""
    import tifffile

    t0 = time.perf_counter()
    items = []
    notes = []
    for kind, src in (("thermal", inp.images), ("rgb", inp.rgb)):
        files, nts = expand_inputs(src, kind=kind)
        notes += nts
        items += [(kind, f) for f in files]
    def skipped() -> str:  # what the inputs left out, for the errors below
        return f" ({'; '.join(notes)})" if notes else ""

    if not items:
        raise DataFileError(f"no input images: the files/folders given hold no image or video files{skipped()}")
    failed: list[dict] = []
    slots: list[list] = [[] for _ in items]  # the decoded frames of each input, in the inputs' order
    used_names: set[str] = set()
    plain: list[tuple] = []  # (k, path, sizes): 8-bit renderings among the thermal inputs, written at the end

    def emit(k, kind, path, decoded):
        for sfx, arr, unit, geo, guess, note in decoded:
            name = path.stem + sfx
            base, n = name, 1
            while name in used_names:
                n += 1
                name = f"{base}_{n}"
            used_names.add(name)
            buf = io.BytesIO()
            tifffile.imwrite(buf, arr, photometric="rgb" if arr.ndim == 3 else "minisblack",
                             metadata={"unit": unit, "source": str(path)})
            project.write_bytes(f"frames/{name}.tif", buf.getvalue())
            slots[k].append({"name": name, "source": str(path.resolve()) if path.exists() else str(path), "sensor": kind,
                             "unit": unit, "width": int(arr.shape[1]), "height": int(arr.shape[0]), "geotag": geo,
                             "camera_guess": guess, "note": note})

    def fail(path, exc):
        reason = str(exc)
        if "pass unit='K' or unit='C'" in reason:
            reason = reason.replace("pass unit='K' or unit='C'", "give --input-unit K or C")
        failed.append({"file": str(path), "reason": reason})

    rgb_thermal = []  # radiometric thermal files given among the RGB images (a DJI folder given to --rgb)
    for k, (kind, path) in enumerate(items):
        if kind == "rgb" and _radiometric_jpeg(path):
            rgb_thermal.append(path.name)
            if progress:
                progress(k + 1, len(items))
            continue
        try:
            if not path.exists():
                raise DataFileError(f"{path}: no such file")
            if path.suffix.lower() in VIDEO_SUFFIXES:
                decoded = _decode_video(path, opt.video_overlap)
            elif kind == "rgb":
                import cv2

                img = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise UnsupportedFormatError(f"{path}: not an image OpenCV can decode (RGB input)")
                from ..io.exif import read_exif

                ex = {}
                if path.suffix.lower() in (".jpg", ".jpeg"):
                    try:
                        ex = read_exif(path.read_bytes()[: 1 << 20])
                    except ThermogrammetryError:
                        ex = {}
                geo = {"lat": ex["latitude_deg"], "lon": ex["longitude_deg"], "alt": ex.get("altitude_m"), "rtk_flag": None,
                       "rtk_std_m": None} if ex.get("latitude_deg") is not None else {}

                class _Md:
                    exif = ex
                    model = ex.get("model")
                    focal_length_mm = ex.get("focal_length_mm")
                    pixel_pitch_um = ex.get("pixel_pitch_um")  # EXIF FocalPlane resolution, when written
                h, w = img.shape[:2]
                decoded = [("", img[..., ::-1].copy(), "dn", geo, _camera_guess(w, h, _Md), "RGB image")]
            else:
                decoded = _decode(path, opt.input_unit, opt.video_overlap)
        except (ThermogrammetryError, OSError, ValueError, MemoryError) as exc:
            fail(path, exc)
            if progress:
                progress(k + 1, len(items))
            continue
        if kind == "thermal" and path.suffix.lower() not in VIDEO_SUFFIXES and decoded \
                and all(d[2] == "dn" for d in decoded):
            # an 8-bit rendering: kept only if no radiometric frame says the thermal frames have another size (a
            # DJI folder holds the visible _V/_W/_Z photographs next to the _T thermal frames); decoded again then
            plain.append((k, path, {(int(d[1].shape[1]), int(d[1].shape[0])) for d in decoded}))
        else:
            emit(k, kind, path, decoded)
        if progress:
            progress(k + 1, len(items))
    if rgb_thermal:
        notes.append(f"{len(rgb_thermal)} radiometric thermal file(s) among the RGB images ({_name_list(rgb_thermal)}): "
                     "not used as RGB images")
    thermal_sizes = {(im["width"], im["height"]) for ims in slots for im in ims
                     if im["sensor"] == "thermal" and im["unit"] != "dn"}  # (not an 8-bit video's frames)
    others = {k for k, path, sizes in plain if thermal_sizes and not sizes & thermal_sizes}
    if others:
        names = [path.name for k, path, _ in plain if k in others]
        notes.append(f"{len(others)} ordinary 8-bit image(s) of another size than every radiometric or 16-bit thermal "
                     f"frame ({_name_list(names)}): visible photographs, not used as thermal frames (give them with --rgb "
                     "to use them)")
    for k, path, _ in plain:
        if k in others:
            continue
        try:
            emit(k, "thermal", path, _decode(path, opt.input_unit, opt.video_overlap))
        except (ThermogrammetryError, OSError, ValueError, MemoryError) as exc:
            fail(path, exc)
    images = [im for ims in slots for im in ims]
    if not images:
        raise DataFileError("no usable input image: " + "; ".join(f["reason"] for f in failed[:5])
                            + (f" (and {len(failed) - 5} more)" if len(failed) > 5 else "") + skipped())
    project.write_json("work/inputs.json", {"images": images, "failed": failed, "notes": notes})
    return {"images": len(images), "failed": len(failed), "seconds": time.perf_counter() - t0}


# ------------------------------------------------------------------------------------------------
# features and matching (units of work for dask)
# ------------------------------------------------------------------------------------------------
def _read_frame(project: ProjectStore, name: str) -> np.ndarray:
    import tifffile

    return tifffile.imread(io.BytesIO(project.read_bytes(f"frames/{name}.tif")))


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
    key = f"work/tie_xy/{name}.npz"
    return _load_npz(project, key)["xy"] if project.exists(key) else _load_npz(project, f"features/{name}.npz")["xy"]


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


def feature_task(args) -> tuple[str, int]:
    """Unit of work: features of one frame, written to ``<folder>/<name>.npz`` (``features/`` by default)."""
    project, name, fopt, *rest = args
    folder = rest[0] if rest else "features"
    pattern_key = rest[1] if len(rest) > 1 else None
    overlay_key = rest[2] if len(rest) > 2 else None
    from ..sfm.features import extract_features
    from ..sfm.keypoints import to_pixel_centre_convention

    frame = _read_frame(project, name)
    if pattern_key and frame.ndim == 2:
        pat = _load_npz_cached(project, pattern_key)["pattern"]
        if pat.shape == frame.shape:  # the sensor's fixed pattern, estimated from the sequence
            frame = frame.astype(np.float32) - pat
    frame = _masked_overlay(project, frame, overlay_key)
    # (0, 0) = centre of the top-left pixel, like the camera model, GCP and manual-tie measurements
    f = to_pixel_centre_convention(extract_features(frame, fopt), fopt)
    _save_npz(project, f"{folder}/{name}.npz", **f.to_npz_dict())
    return name, len(f)


def _masked_overlay(project: ProjectStore, frame: np.ndarray, overlay_key: str | None) -> np.ndarray:
    """``frame`` as float32 with the pixels of a burned-in display (``overlay_key``: :func:`_overlay_mask`) set to
    NaN (no tie point there); unchanged without a key or when the mask's size differs."""
    if not overlay_key or frame.ndim != 2:
        return frame
    mask = _load_npz_cached(project, overlay_key)["mask"]
    if mask.shape != frame.shape:
        return frame
    out = frame.astype(np.float32)
    out[mask] = np.nan
    return out


def _overlay_mask(project: ProjectStore, inputs: dict) -> dict | None:
    """A display burned into the 8-bit thermal renderings (``unit`` dn), found from the frames of the most common
    size (:func:`~thermogrammetry.sfm.features.static_overlay`); writes ``features/overlay.npz`` and returns
    ``{"key", "share", "frames", "images", "size"}`` (share of the frame masked, frames it was found from, images of
    that size it applies to, [width, height]), or None."""
    from ..sfm.features import OVERLAY_MIN_FRAMES, static_overlay

    members = _largest_size_group(inputs, _is_thermal_rendering)
    if len(members) < OVERLAY_MIN_FRAMES:
        return None
    # the frames static_overlay uses (it takes at most 60, fewer when they are large)
    frames = [f for f in (_read_frame(project, nm) for nm in _evenly_spaced(members, 60)) if f.ndim == 2]
    mask = static_overlay(frames)
    if mask is None:
        return None
    key = "features/overlay.npz"
    _save_npz(project, key, mask=mask)
    return {"key": key, "share": float(mask.mean()), "frames": len(frames), "images": len(members),
            "size": [int(mask.shape[1]), int(mask.shape[0])]}


def _is_thermal_rendering(im: dict) -> bool:
    """An input image (``work/inputs.json``) that is an 8-bit rendering of a thermal frame (unit dn)."""
    return im.get("sensor", "thermal") == "thermal" and im.get("unit") == "dn"


def _largest_size_group(inputs: dict, keep) -> list:
    """Names of the images that ``keep(image dict)`` accepts, those of the most common frame size (the first such
    size in input order on a tie); [] when none is accepted."""
    groups: dict = {}
    for im in inputs["images"]:
        if keep(im):
            groups.setdefault((int(im["height"]), int(im["width"])), []).append(im["name"])
    return max(groups.values(), key=len) if groups else []


def _evenly_spaced(items: list, n: int) -> list:
    """At most ``n`` of ``items``, evenly spaced from the first to the last: the frames that
    :func:`~thermogrammetry.sfm.features.fixed_pattern` and ``static_overlay`` would pick themselves (only those
    are read)."""
    return [items[k] for k in np.unique(np.linspace(0, len(items) - 1, min(len(items), n)).round().astype(int))]


def _overlay_keys(project: ProjectStore, inputs: dict) -> dict:
    """image name -> key of the burned-in display's mask that the features step found for it (``work/overlay.json``)."""
    ov = project.read_json("work/overlay.json") if project.exists("work/overlay.json") else {}
    if not ov.get("found"):
        return {}
    w, h = ov["size"]
    return {im["name"]: ov["key"] for im in inputs["images"]
            if _is_thermal_rendering(im) and int(im["width"]) == w and int(im["height"]) == h}


def match_task(args) -> tuple[int, int, int, int, str]:
    """Unit of work: match and verify one pair, written to ``matches/<i>_<j>.npz`` (or ``<prefix>matches/``)."""
    project, i, j, ni, nj, cam_i, cam_j, mopt, *rest = args
    pre = rest[0] if rest else ""
    from ..sfm.matching import guided_matches, homography_prior, match_descriptors, verify_pair

    fi = _load_npz_cached(project, f"{pre}features/{ni}.npz")
    fj = _load_npz_cached(project, f"{pre}features/{nj}.npz")
    m = match_descriptors(fi["descriptors"], fj["descriptors"], ratio=mopt.ratio)
    if mopt.guided_radius_px > 0 and fi["descriptors"].dtype != np.uint8:
        H = homography_prior(fi["xy"], fj["xy"], m, seed=mopt.seed)
        if H is not None:
            g = guided_matches(fi["xy"], fi["descriptors"], fj["xy"], fj["descriptors"], H, radius_px=mopt.guided_radius_px)
            if len(g) > len(m):
                m = g
    if cam_i is not None and cam_j is not None and len(m) >= mopt.min_inliers:
        ri = cam_i.unproject(fi["xy"][m[:, 0]])[:, :2]
        rj = cam_j.unproject(fj["xy"][m[:, 1]])[:, :2]
        full_i = np.zeros((len(fi["xy"]), 2))
        full_j = np.zeros((len(fj["xy"]), 2))
        full_i[m[:, 0]] = ri
        full_j[m[:, 1]] = rj
        inl, model, reason = verify_pair(fi["xy"], fj["xy"], m, camera1=cam_i, camera2=cam_j, rays1=full_i, rays2=full_j, options=mopt)
    else:
        inl, model, reason = verify_pair(fi["xy"], fj["xy"], m, options=mopt)
    if not reason:
        _save_npz(project, f"{pre}matches/{i}_{j}.npz", idx=inl)
    return i, j, len(m), len(inl), reason


#: tasks submitted to the cluster and not yet collected, at most (:func:`_run_tasks`)
_TASKS_IN_FLIGHT = 64


def _run_tasks(fn, tasks, opt: SurveyOptions, progress: Callable | None, what: str):
    """Run tasks in-process, on a local dask cluster (``workers``) or on ``scheduler``; results in task order."""
    n = len(tasks)
    if n == 0:
        return []
    if opt.scheduler is None and opt.workers == 0:
        out = []
        for k, t in enumerate(tasks):
            out.append(fn(t))
            if progress:
                progress(k + 1, n)
        return out
    from distributed import Client, as_completed

    with _local_cluster(opt) as run_opt:  # a cluster of its own only when the caller did not start one
        client = Client(run_opt.scheduler)
        try:
            # at most _TASKS_IN_FLIGHT tasks submitted and not yet collected: the scheduler's and the workers'
            # state per task (its arguments, its result) does not grow with the block; tasks are submitted in
            # their order and each result is released as soon as it is collected
            pending = iter(enumerate(tasks))
            pos = {}
            ac = as_completed()

            def submit(count):
                for k, t in itertools.islice(pending, count):
                    f = client.submit(fn, t, pure=False)
                    pos[f.key] = k
                    ac.add(f)

            submit(_TASKS_IN_FLIGHT)
            out = [None] * n
            for done, fut in enumerate(ac, 1):
                out[pos.pop(fut.key)] = fut.result()
                fut.release()
                del fut
                submit(1)
                if progress:
                    progress(done, n)
            return out
        finally:
            client.close()


def _initial_cameras(inputs: dict, camera=None, rgb_camera=None) -> tuple[dict, list]:
    """Camera id -> starting Camera, and the camera id of each image (``rgb_camera``: the rig file's)."""
    from ..camera import Camera

    groups: dict[tuple, str] = {}
    cams, ids = {}, []
    for im in inputs["images"]:
        key = (im["sensor"], im["width"], im["height"], round(im["camera_guess"]["f_px"], 1))
        if key not in groups:
            cid = im["sensor"] if not any(k[0] == im["sensor"] for k in groups) else f"{im['sensor']}{len(groups) + 1}"
            groups[key] = cid
            if camera is not None and im["sensor"] == "thermal":
                if tuple(camera.image_size) != (im["width"], im["height"]):
                    raise ConfigError(f"camera file: image size {camera.image_size} differs from the frames' "
                                      f"{im['width']}x{im['height']} ({im['name']})")
                cams[cid] = camera
            elif rgb_camera is not None and im["sensor"] == "rgb" and tuple(rgb_camera.image_size) == (im["width"], im["height"]):
                cams[cid] = rgb_camera
            else:
                w, h, f = im["width"], im["height"], im["camera_guess"]["f_px"]
                pitch = im["camera_guess"].get("pitch_um")
                cams[cid] = Camera("opencv", (w, h), dict(fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2),
                                   pixel_pitch_um=pitch, name=cid)
        ids.append(groups[key])
    return cams, ids


def step_features(project: ProjectStore, opt: SurveyOptions, progress=None) -> dict:
    inputs = project.read_json("work/inputs.json")
    store = project if not isinstance(project, FolderProject) else FolderProject(project.root, durable=project.durable)
    ov = _overlay_mask(project, inputs)
    project.write_json("work/overlay.json", {"found": False} if ov is None else {"found": True, **ov})
    keys = _overlay_keys(project, inputs)
    res = _run_tasks(feature_task, [(store, im["name"], opt.features, "features", None, keys.get(im["name"]))
                                    for im in inputs["images"]], opt, progress, "features")
    counts = {name: n for name, n in res}
    project.write_json("work/features.json", counts)
    out = {"images": len(counts), "median_features": float(np.median(list(counts.values()))) if counts else 0.0}
    if ov is not None:
        out["overlay_share"] = ov["share"]
    return out


def _gnss_xyz(inputs: dict, opt: SurveyOptions, crs_out: str | None):
    """(n, 3) positions in the output CRS and (n, 3) σ, from EXIF/XMP (``auto``) or a gnss.csv."""
    n = len(inputs["images"])
    xyz = np.full((n, 3), np.nan)
    sig = np.full((n, 3), np.nan)
    notes = []
    mode = opt.gnss
    if str(mode).lower() == "none":
        return xyz, sig, crs_out, ["GNSS not used (--gnss none)"]
    if str(mode).lower() == "auto":
        lat = np.array([im["geotag"].get("lat", np.nan) if im["geotag"] else np.nan for im in inputs["images"]], float)
        lon = np.array([im["geotag"].get("lon", np.nan) if im["geotag"] else np.nan for im in inputs["images"]], float)
        alt = np.array([(im["geotag"].get("alt") if im["geotag"] and im["geotag"].get("alt") is not None else np.nan)
                        for im in inputs["images"]], float)
        have = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
        if not have.any():
            return xyz, sig, crs_out, ["no GNSS positions in the files"]
        from pyproj import CRS, Transformer

        if crs_out is None:
            from ..sfm.plan import utm_epsg

            crs_out = f"EPSG:{utm_epsg(float(np.nanmean(lon[have])), float(np.nanmean(lat[have])))}"
            notes.append(f"no --crs given: positions in the UTM zone of the flight, {crs_out}")
        tf = Transformer.from_crs(CRS.from_epsg(4979), CRS.from_user_input(crs_out), always_xy=True)
        x, y, z = tf.transform(lon[have], lat[have], alt[have])
        xyz[have] = np.column_stack([x, y, z])
        for k in np.nonzero(have)[0]:
            g = inputs["images"][k]["geotag"]
            flag, std = g.get("rtk_flag"), g.get("rtk_std_m")
            if flag == 50 and std:
                s = np.maximum(np.array([std[0], std[1], std[2]], float), [0.01, 0.01, 0.02])
            elif flag == 50:
                s = np.array([0.03, 0.03, 0.05])
            elif flag == 34:
                s = np.array([0.5, 0.5, 1.0])
            elif flag == 16:
                s = np.array([2.0, 2.0, 4.0])
            else:
                s = np.array([3.0, 3.0, 5.0])
            sig[k] = s
        miss = [inputs["images"][k]["name"] for k in np.nonzero(~have)[0]]
        if miss:
            notes.append(f"{len(miss)} image(s) without GNSS: {_name_list(miss, 5)}")
        notes.append("GNSS heights used as written in the files (no geoid/ellipsoid conversion)")
    else:
        from ..io.testfield_csv import read_gnss_csv

        g = read_gnss_csv(mode)
        index = {}
        for k, im in enumerate(inputs["images"]):
            index[im["name"]] = k
            index.setdefault(Path(im["source"]).name, k)
            index.setdefault(Path(im["source"]).stem, k)
        unknown = []
        for r, name in enumerate(g.image):
            k = index.get(name, index.get(Path(name).stem))
            if k is None:
                unknown.append(name)
                continue
            xyz[k] = g.xyz[r]
            sig[k] = g.std[r] if g.std is not None else np.array([0.05, 0.05, 0.10])
        if g.std is None:
            notes.append(f"{g.source}: no sX,sY,sZ columns: σ 0.05 m horizontal, 0.10 m vertical assumed")
        miss = [im["name"] for k, im in enumerate(inputs["images"]) if not np.isfinite(xyz[k]).all()]
        if miss:
            notes.append(f"{len(miss)} image(s) without a GNSS position in {g.source}: {_name_list(miss, 5)}")
        if unknown:
            notes.append(f"{g.source}: {len(unknown)} image name(s) not among the inputs, ignored: {', '.join(unknown[:5])}")
    if opt.gnss_sigma_m is not None:
        sig[np.isfinite(sig).all(1)] = np.asarray(opt.gnss_sigma_m, float)
    return xyz, sig, crs_out, notes


def _fixed_pattern(project: ProjectStore, inputs: dict, names: list, *, highpass_sigma_px: float = 0.0,
                   key: str = "lowtexture/pattern.npz") -> str | None:
    """Estimate the thermal sensor's fixed pattern from its frames (the most common frame size); its key or None."""
    from ..sfm.features import fixed_pattern

    names = set(names)
    members = _largest_size_group(inputs, lambda im: im.get("sensor", "thermal") == "thermal" and im["name"] in names)
    if not members:
        return None
    frames = [f for f in (_read_frame(project, nm) for nm in _evenly_spaced(members, 60)) if f.ndim == 2]
    pat = fixed_pattern(frames, highpass_sigma_px=highpass_sigma_px)
    if pat is None:
        return None
    _save_npz(project, key, pattern=pat)
    return key


#: the low-texture fallback tracks frames with positions as a sequence when the median distance between consecutive
#: frames is at most this multiple of the median nearest-neighbour distance (:func:`_sequence_order_ratio`)
SEQUENCE_ORDER_RATIO = 3.0


def _sequence_order_ratio(xyz) -> float | None:
    """Median distance between consecutive frames (acquisition order) over the median distance of each frame to its
    nearest neighbour; None with fewer than 3 positions or all positions equal.

    A walk along a wall or a flight line in serpentine order gives ~1 (consecutive frames are neighbours): with a
    30-frame walk (0.65 m apart) 1.05 with exact positions, 1.0-1.1 with RTK (3 cm), 1.3-1.7 with 0.3-1 m of GNSS
    noise, 1.8-2.6 with 3 m (positions that cannot order the frames: the acquisition order is the better guess);
    the same frames shuffled 7-11, a shuffled 5 x 10 grid 3.6."""
    from scipy.spatial import cKDTree

    X = np.asarray(xyz, float)
    fin = np.all(np.isfinite(X), axis=1)
    X = X[fin]
    if len(X) < 3:
        return None
    dc = np.linalg.norm(np.diff(X, axis=0), axis=1)
    dn = cKDTree(X).query(X, k=2)[0][:, 1]
    med_n = float(np.median(dn))
    if not med_n > 0:
        return None
    return float(np.median(dc) / med_n)


def _track_thermal_sequence(project: ProjectStore, inputs: dict, thermal: list, cams: dict, cam_ids: list,
                            pattern_key: str | None) -> tuple[dict, list]:
    """Low-texture fallback for a sequence (no positions, or positions in walk order): the thermal frames tracked
    frame to frame (input order).

    Writes ``lowtexture/features/<name>.npz`` (the tracked points; no descriptors: zero rows) and
    ``lowtexture/matches/<i>_<j>.npz`` of the verified consecutive pairs. Returns (feature counts by name, match
    results ``(i, j, n_putative, n_verified, reason)`` of the consecutive pairs).
    """
    from ..sfm.lowtexture import track_sequence

    names = [inputs["images"][k]["name"] for k in thermal]
    pattern = _load_npz(project, pattern_key)["pattern"] if pattern_key else None
    overlay = _overlay_keys(project, inputs)
    shapes = [(int(inputs["images"][k]["height"]), int(inputs["images"][k]["width"])) for k in thermal]
    counts: dict = {}
    res: list = []
    # runs of consecutive frames of one size (a sequence of one sensor); the tracker sees one run at a time
    start = 0
    for end in range(1, len(thermal) + 1):
        if end < len(thermal) and shapes[end] == shapes[start]:
            continue
        run = thermal[start:end]
        pat = pattern if pattern is not None and pattern.shape == shapes[start] else None

        def load(a, run=run):
            nm = inputs["images"][run[a]]["name"]
            return _masked_overlay(project, _read_frame(project, nm), overlay.get(nm))

        st = track_sequence(load, len(run), pattern=pat,
                            cameras=[cams[cam_ids[k]] for k in run])
        for a, k in enumerate(run):
            nm = inputs["images"][k]["name"]
            xy = st.xy[a]
            _save_npz(project, f"lowtexture/features/{nm}.npz", xy=xy, size=np.full(len(xy), 12.0, np.float32),
                      angle=np.zeros(len(xy), np.float32), descriptors=np.zeros((len(xy), 128), np.float32))
            counts[nm] = len(xy)
        for a in range(1, len(run)):
            i, j = run[a - 1], run[a]
            m = st.matches.get((a - 1, a))
            reason = st.reasons.get((a - 1, a), "")
            if m is not None and not reason:
                _save_npz(project, f"lowtexture/matches/{i}_{j}.npz", idx=m)
            res.append((i, j, int(st.n_putative.get((a - 1, a), 0)), 0 if m is None or reason else len(m), reason))
        if end < len(thermal):
            res.append((thermal[end - 1], thermal[end], 0, 0, f"frame size {shapes[end]} differs from the previous frame's"))
        start = end
    return counts, res


def step_matching(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rig=None, *,
                  low_texture_only: bool = False) -> dict:
    """Pairs, matching and verification; with ``low_texture == "auto"`` the low-texture fallback when fewer than
    80 % of the thermal frames find a verified pair. ``low_texture_only``: the primary matching is already in
    ``work/pairs.json`` (its orientation left < 80 % of the thermal frames in one block): only the fallback runs,
    and its ties replace the thermal ones whenever it verifies any pair (the orientation judges them)."""
    from ..sfm.matching import select_pairs

    inputs = project.read_json("work/inputs.json")
    cams, cam_ids = _initial_cameras(inputs, camera, getattr(rig, "rgb_camera", None))
    xyz, _, crs, _ = _gnss_xyz(inputs, opt, opt.crs)
    names = [im["name"] for im in inputs["images"]]
    pairs = select_pairs(len(names), xyz, options=opt.matching)
    rig_pairs: set = set()
    if rig is not None:  # rig mode: every thermal image is matched with its RGB partner (cross-modal ties)
        from ..sfm.rig import pair_rig_images

        master, _, _ = pair_rig_images(rig, inputs["images"])
        rig_pairs = {(min(a, b), max(a, b)) for a, b in master.items()}
        pairs = sorted(set(pairs) | rig_pairs)
    store = project if not isinstance(project, FolderProject) else FolderProject(project.root, durable=project.durable)

    def match(pre, mopt=None, pair_list=None):
        mopt = mopt or opt.matching
        tasks = [(store, i, j, names[i], names[j], cams[cam_ids[i]], cams[cam_ids[j]], mopt, pre)
                 for i, j in (pairs if pair_list is None else pair_list)]
        return _run_tasks(match_task, tasks, opt, progress, "matching")

    def connected(res):
        return len({k for i, j, npu, nv, reason in res if not reason for k in (i, j)})

    if low_texture_only:
        prev = project.read_json("work/pairs.json")
        res = [tuple(r) for r in prev["pairs"]]
        info = dict(prev.get("features", {}))
    else:
        res = match("")
        info = {"features": f"{opt.features.detector.value}/{opt.features.enhancement.value}", "connected": connected(res)}
    n = len(names)
    # the low-texture fallback concerns the thermal frames only: RGB images of a combined block keep their own
    # features and matches (their texture is fine; a sequence-window pair list and thermal preprocessing would
    # only lose their links -- measured on the frescoes, RGB + thermal: the RGB block fell from 40 to 27 images)
    thermal = [k for k, im in enumerate(inputs["images"]) if im.get("sensor", "thermal") == "thermal"]
    is_th = np.zeros(n, bool)
    is_th[thermal] = True
    nt = len(thermal)

    def connected_thermal(res):
        return len({k for i, j, npu, nv, reason in res if not reason for k in (i, j) if is_th[k]})

    if opt.low_texture == "auto" and nt >= 2 and "low_texture" not in info and (
            low_texture_only or connected_thermal(res) < LOW_TEXTURE_SHARE * nt):
        # low-texture frames (facades, walls, water, fields): the sensor's fixed pattern estimated from the
        # sequence and removed, more SIFT features (lower contrast threshold), and matches guided by a
        # homography from the few that pass the global ratio test
        th_names = [names[k] for k in thermal]
        mopt_lt = replace(opt.matching, guided_radius_px=LOW_TEXTURE_GUIDED_RADIUS_PX)
        pairs_lt = [(i, j) for i, j in pairs if is_th[i] and is_th[j]]
        have_pos = xyz is not None and int(np.all(np.isfinite(xyz[thermal]), axis=1).sum()) >= 2
        order_ratio = _sequence_order_ratio(xyz[thermal]) if have_pos else None
        as_sequence = not have_pos or (order_ratio is not None and order_ratio <= SEQUENCE_ORDER_RATIO)
        if not as_sequence:
            pattern_key = _fixed_pattern(project, inputs, th_names)
            lt = replace(opt.features, detector="sift", enhancement="clahe", contrast_threshold=0.005,
                         max_features=max(opt.features.max_features, 4000))
            overlay = _overlay_keys(project, inputs)
            counts_lt = dict(_run_tasks(feature_task, [(store, nm, lt, "lowtexture/features", pattern_key,
                                                        overlay.get(nm)) for nm in th_names],
                                        opt, None, "features"))
            res_lt = match("lowtexture/", mopt_lt, pairs_lt)
            how = "sift/clahe on pattern-corrected thermal frames, guided matching"
        else:
            # no positions, or positions that say the acquisition order is a walk (consecutive frames are neighbours):
            # the frames are taken as a sequence (acquisition order) and tracked frame to frame
            pattern_key = _fixed_pattern(project, inputs, th_names, highpass_sigma_px=LOW_TEXTURE_PATTERN_SIGMA_PX,
                                         key="lowtexture/pattern_fine.npz")
            counts_lt, res_lt = _track_thermal_sequence(project, inputs, thermal, cams, cam_ids, pattern_key)
            how = "pattern-corrected thermal frames tracked frame to frame (KLT), consecutive pairs verified"
        info["low_texture"] = {"features": how, "sequence": as_sequence, "order_ratio": order_ratio,
                               "fixed_pattern": bool(pattern_key), "thermal_connected": connected_thermal(res_lt),
                               "thermal_connected_before": connected_thermal(res), "thermal_images": nt,
                               "trigger": ("orientation: < 80 % of the thermal frames in one block" if low_texture_only
                                           else "matching: < 80 % of the thermal frames with a verified pair")}
        if connected_thermal(res_lt) > (1 if low_texture_only else connected_thermal(res)):
            if not low_texture_only:
                # the primary matching, put aside: the orientation step puts it back when the fallback's blocks are
                # refused (_low_texture_check), so that ``auto`` is never worse than ``off`` there
                prim = [f"features/{nm}.npz" for nm in th_names]
                prim += [f"matches/{i}_{j}.npz" for i, j, npu, nv, reason in res if not reason]
                for k in prim:
                    if project.exists(k):
                        project.write_bytes(f"lowtexture/primary/{k}", project.read_bytes(k))
                project.write_json("lowtexture/primary/work/features.json", project.read_json("work/features.json"))
                project.write_json("lowtexture/primary/work/pairs.json",
                                   {"pairs": [[i, j, npu, nv, reason] for i, j, npu, nv, reason in res],
                                    "features": {k: v for k, v in info.items() if k != "low_texture"}})
                info["primary_kept"] = [k for k in prim if project.exists(k)]
            for nm in th_names:
                project.write_bytes(f"features/{nm}.npz", project.read_bytes(f"lowtexture/features/{nm}.npz"))
            for i, j, npu, nv, reason in res_lt:
                if not reason:
                    project.write_bytes(f"matches/{i}_{j}.npz", project.read_bytes(f"lowtexture/matches/{i}_{j}.npz"))
            project.write_json("work/features.json", {**project.read_json("work/features.json"), **counts_lt})
            # pairs of a thermal frame with an RGB image are matched again: the thermal features changed
            cross = [(i, j) for i, j in pairs if is_th[i] != is_th[j]]
            res_cross = match("", None, cross) if cross else []
            res = sorted([r for r in res if not (is_th[r[0]] or is_th[r[1]])] + list(res_lt) + list(res_cross),
                         key=lambda r: (r[0], r[1]))
            info["used"] = ("low-texture fallback for the thermal frames (fixed pattern removed, SIFT with a low "
                            "contrast threshold, homography-guided matching)" if not as_sequence else
                            "low-texture fallback for the thermal frames (fixed pattern removed, frames tracked as a "
                            "sequence, consecutive pairs verified)")
    kept = [(i, j, nv) for i, j, npu, nv, reason in res if not reason]
    project.write_json("work/pairs.json", {"pairs": [[i, j, npu, nv, reason] for i, j, npu, nv, reason in res], "features": info})
    return {"pairs_tried": len(pairs), "pairs_verified": len(kept), "images_connected": connected(res), "features": info,
            "median_verified_matches": float(np.median([k[2] for k in kept])) if kept else 0.0}


def step_orient(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rgb_camera=None) -> dict:
    from ..sfm.reconstruction import reconstruct
    from ..sfm.tracks import build_tracks

    inputs = project.read_json("work/inputs.json")
    counts = project.read_json("work/features.json")
    names = [im["name"] for im in inputs["images"]]
    cams, cam_ids = _initial_cameras(inputs, camera, rgb_camera)
    cam_list = list(cams)
    image_camera = np.array([cam_list.index(c) for c in cam_ids])
    refine = opt.tie_refinement is not None
    xy, size, angle = [], [], []
    for n in names:  # one read per file; size and angle only for the refinement (descriptors are dropped)
        z = _load_npz(project, f"features/{n}.npz")
        xy.append(z["xy"])
        if refine:
            size.append(z["size"])
            angle.append(z["angle"])
    pairs = []
    pc = {}
    for i, j, npu, nv, reason in project.read_json("work/pairs.json")["pairs"]:
        if reason:
            continue
        idx = _load_npz(project, f"matches/{i}_{j}.npz")["idx"]
        pairs.append((i, j, idx))
        pc[(i, j)] = len(idx)
    tracks = build_tracks([int(counts[n]) for n in names], pairs)
    del pairs  # the matches (8 B per match) are in the tracks now: not held through the reconstruction
    release_free_heap()
    refinement = None
    if refine and len(tracks.track):
        from ..sfm.lsm import refine_tracks

        xy, tracks, refinement = refine_tracks(tracks, xy, lambda i: _read_frame(project, names[i]), size_by_image=size,
                                               angle_by_image=angle, options=opt.tie_refinement)
    del size, angle
    for n, a in zip(names, xy):  # what orient used, for georef and the exports (a rerun starts from the keypoints)
        _save_npz(project, f"work/tie_xy/{n}.npz", xy=a)
    ropt = opt.reconstruction
    if camera is not None:
        ropt = replace(ropt, free_intrinsics=())
    cam_objs = [cams[c] for c in cam_list]
    mapper_auto = None
    if opt.mapper == "global":
        rec = reconstruct_global(cam_objs, image_camera, xy, tracks, pc, ropt, opt.global_orientation, on_progress=progress)
        used = "global"
    else:
        rec = reconstruct(cam_objs, image_camera, xy, tracks, pc, ropt, on_progress=progress)
        used = "incremental"
        if opt.mapper == "auto":
            rec, used, mapper_auto = _auto_global(rec, cam_objs, image_camera, xy, tracks, pc, ropt, progress,
                                                  opt.global_orientation)
    release_free_heap()
    _save_npz(project, "work/reconstruction.npz", R=rec.R, t=rec.t, registered=rec.registered, component=rec.component,
              points=rec.points, track=tracks.track, image=tracks.image, feature=tracks.feature, obs_valid=rec.obs_valid,
              image_camera=image_camera)
    project.write_json("work/reconstruction.json", {
        "cameras": {c: rec.cameras[k].to_dict() for k, c in enumerate(cam_list)}, "camera_ids": cam_list,
        "termination": rec.termination.value, "reason": rec.reason, "log": rec.log,
        "status": [{"registered": bool(s.registered), "component": int(s.component), "reason": s.reason} for s in rec.status],
        "tracks": int(tracks.n_tracks), "tracks_split": int(tracks.n_split), "seconds": rec.seconds,
        "tie_refinement": refinement, "mapper": used, "mapper_auto": mapper_auto})
    return {"oriented": int(rec.registered.sum()), "of": len(names), "components": [len(c) for c in rec.components()],
            "tracks": int(tracks.n_tracks), "reason": rec.reason, "tie_refinement": refinement, "mapper": used,
            "mapper_auto": mapper_auto}


def _auto_global(rec, cameras, image_camera, xy, tracks, pair_counts, ropt, progress, gopt: GlobalOptions | None = None):
    """``mapper="auto"``: the incremental reconstruction ``rec``, or the global one when the incremental one's largest
    block holds fewer than :data:`AUTO_GLOBAL_BELOW` of the images and the global one's largest block is larger while
    it orients at least as many images over all its blocks (the held-out 48-station ring of
    ``tests/test_survey_building_rings.py`` on RTK GNSS: the incremental orients 44 images in blocks of 26 and 18, both
    georeferenced, then 48/48 with the images added at their GNSS positions; keeping global's larger block gave 34/48).

    Returns (reconstruction, mapper used, summary dict or None when global was not tried). The summary has the
    largest block and the images oriented of each, which was kept and the global run's time; the kept
    reconstruction's log says why.
    """
    gopt = gopt or GlobalOptions()
    n = len(image_camera)
    inc = max((len(c) for c in rec.components()), default=0)
    if inc >= AUTO_GLOBAL_BELOW * n or n < gopt.min_part_images:
        return rec, "incremental", None
    t0 = time.perf_counter()
    glob = reconstruct_global(cameras, image_camera, xy, tracks, pair_counts, ropt, gopt, on_progress=progress)
    gl = max((len(c) for c in glob.components()), default=0)
    n_inc, n_gl = int(rec.registered.sum()), int(glob.registered.sum())
    # a larger largest block, and not fewer images oriented over all blocks (with GNSS every block is georeferenced
    # on its own, so blocks that are apart count too)
    keep = "global" if gl > inc and n_gl >= n_inc else "incremental"
    summary = {"incremental_largest_block": int(inc), "global_largest_block": int(gl), "incremental_oriented": n_inc,
               "global_oriented": n_gl, "images": int(n), "kept": keep,
               "global_seconds": round(time.perf_counter() - t0, 3), "global_reason": glob.reason}
    msg = (f"mapper auto: the incremental orientation's largest block holds {inc}/{n} images (< {AUTO_GLOBAL_BELOW:.0%}; "
           f"{n_inc} oriented in all); the global orientation's {gl}/{n} ({n_gl} in all): {keep} kept")
    if keep == "global":
        glob.log.insert(0, msg)
        return glob, "global", summary
    rec.log.append(msg)
    return rec, "incremental", summary


def _largest_thermal_block(project: ProjectStore) -> tuple[int, int]:
    """(thermal images, thermal images in the largest oriented block) of the last orientation."""
    inputs = project.read_json("work/inputs.json")["images"]
    status = project.read_json("work/reconstruction.json")["status"]
    th = [k for k, im in enumerate(inputs) if im.get("sensor", "thermal") == "thermal"]
    count: dict = {}
    for k in th:
        if status[k]["registered"]:
            count[status[k]["component"]] = count.get(status[k]["component"], 0) + 1
    return len(th), max(count.values(), default=0)


def _low_texture_sequence_used(project: ProjectStore) -> bool:
    """Whether the thermal ties are the low-texture fallback's tracked sequence (``work/pairs.json``)."""
    info = project.read_json("work/pairs.json").get("features", {}) if project.exists("work/pairs.json") else {}
    return "used" in info and bool(info.get("low_texture", {}).get("sequence"))


def _low_texture_orient_options(project: ProjectStore, opt: SurveyOptions) -> SurveyOptions:
    """Orientation options for a tracked low-texture sequence: a bundle adjustment after every added image.

    A walk along a plain wall is a long strip of frames whose tracks span 3-5 frames; registered one after the other
    with an adjustment only every 25 % of growth, the strip drifts and its ends flip (the planar-pose ambiguity):
    synthetic low-texture facade, 30 frames, true camera given -- rotations 4.9 deg RMS (max 22) off and the block
    split; with an adjustment after every image 30/30, 0.82 deg RMS (centres 0.3 % of the block's length)."""
    if not _low_texture_sequence_used(project):
        return opt
    return replace(opt, reconstruction=replace(opt.reconstruction, ba_growth=LOW_TEXTURE_BA_GROWTH))


def _low_texture_self_calibration(project: ProjectStore, camera_ids: list, self_cal, focal_known: dict):
    """Self-calibration of the thermal cameras of a tracked low-texture sequence: radial distortion only (and the
    focal length when it is a guess, not the file's EXIF value). Returns ``(self_cal, note or "")``.

    A strip of frames along a plane cannot carry the focal length and the principal point: they trade against the
    block's bending. Synthetic low-texture facade (30 frames, EXIF focal): incremental block 0.64-0.89 deg RMS off
    in rotation; the final adjustment with the 8 parameters bent it to 3.6-5.9 deg (fx +10 %, cy +29 px), with
    k1, k2 only it stays at 0.60-0.92 deg (k1 -0.051 for a true -0.05)."""
    if not _low_texture_sequence_used(project):
        return self_cal, ""
    out, limited, guessed = {}, [], []
    for k, cid in enumerate(camera_ids):
        req = tuple(self_cal.get(k, ())) if isinstance(self_cal, dict) else tuple(self_cal)
        if str(cid).startswith("thermal"):
            allow = LOW_TEXTURE_SELF_CALIBRATION if focal_known.get(k) else ("fx", "fy") + LOW_TEXTURE_SELF_CALIBRATION
            kept = tuple(p for p in req if p in allow)
            if kept != req:
                limited.append(f"{cid}: {', '.join(kept) or 'none'}")
            if "fx" in kept:
                guessed.append(str(cid))
            req = kept
        out[k] = req
    note = ("low-texture sequence: self-calibration limited to " + "; ".join(limited) +
            " (a strip of frames along a wall cannot carry the focal length and principal point)") if limited else ""
    if guessed:
        # synthetic facade walk filmed at 25 fps, 28 frames extracted (benchmarks/survey_lowtexture.py --synthetic
        # --video): fx 933 px for a true 765, rotations 9.6 deg RMS; with the camera file 1.3 deg
        note += ("; " if note else "low-texture sequence: ") + (
            f"the focal length of {', '.join(guessed)} is not known (no EXIF focal length, no camera file; a video "
            "carries none) and a walk along a wall determines it only weakly: expect rotations several degrees off "
            "(give --camera camera.json from `thermogrammetry calibrate`)")
    return out, note


def _low_texture_check(project: ProjectStore) -> dict:
    """The checks of every block of a tracked low-texture sequence: plane parallax of image-coplanar points
    (:data:`LOW_TEXTURE_MAX_PLANE_PARALLAX`) and planar share (:data:`LOW_TEXTURE_MIN_PLANAR_SHARE`).

    Returns ``{"blocks": [{"images", "thermal", "pairs", "median_plane_parallax_px", "residual_rms_px", "ratio",
    "planar_share", "refused"}], "refused_images": [...], "why": {image index: reason}}``; the reconstruction is not
    changed.
    """
    from ..sfm.lowtexture import plane_parallax

    rec, meta = _load_reconstruction(project)
    inputs = project.read_json("work/inputs.json")["images"]
    is_th = np.array([im.get("sensor", "thermal") == "thermal" for im in inputs])
    xy = None
    blocks, refused, why = [], [], {}
    for comp in rec.components():
        th = [int(i) for i in comp if is_th[i]]
        if len(th) < 2:
            continue
        if xy is None:
            xy = [_tie_xy(project, im["name"]) for im in inputs]
        r = plane_parallax(rec.cameras, rec.image_camera, rec.R, rec.t, rec.points, rec.tracks.track, rec.tracks.image,
                           rec.tracks.feature, rec.obs_valid, xy, th)
        bad_par = not (r.ratio <= LOW_TEXTURE_MAX_PLANE_PARALLAX)
        bad_flat = not (r.planar_share >= LOW_TEXTURE_MIN_PLANAR_SHARE)
        bad = bad_par or bad_flat
        fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        blocks.append({"images": len(comp), "thermal": len(th), "pairs": len(r.pairs),
                       "median_plane_parallax_px": fin(r.median_parallax_px), "residual_rms_px": fin(r.residual_rms_px),
                       "ratio": fin(r.ratio), "planar_share": fin(r.planar_share), "refused": bad})
        if bad:
            head = f"low-texture fallback: its block of {len(th)} thermal frames refused: "
            if not np.isfinite(r.ratio):
                reason = head + "no consecutive pair with enough common points to check its geometry"
            elif bad_par:
                reason = head + (f"the points its consecutive frames show coplanar lie off their plane by "
                                 f"{r.median_parallax_px:.2f} px (median plane parallax), {r.ratio:.2f} x the block's "
                                 f"{r.residual_rms_px:.2f} px RMS (> {LOW_TEXTURE_MAX_PLANE_PARALLAX:g}): a bent or wrong "
                                 "block (e.g. reflections on glass, a focal length far from the guess)")
            else:
                reason = head + (f"only {r.planar_share:.0%} of the points of consecutive frames lie within 1 % of their "
                                 f"depth of one plane (< {LOW_TEXTURE_MIN_PLANAR_SHARE:.0%}): the block does not "
                                 "reconstruct a wall (a walk explained as a turn, or depths too uncertain to check)")
            refused += th
            why.update({i: reason for i in th})
    return {"blocks": blocks, "refused_images": refused, "why": why}


def _low_texture_unregister(project: ProjectStore, why: dict) -> None:
    """Mark images of ``why`` (index -> reason) as not oriented in the saved reconstruction."""
    z = dict(_load_npz(project, "work/reconstruction.npz"))
    meta = project.read_json("work/reconstruction.json")
    reg = np.asarray(z["registered"]).astype(bool).copy()
    comp = np.asarray(z["component"]).copy()
    for i, reason in why.items():
        reg[i] = False
        comp[i] = -1
        meta["status"][i] = {**meta["status"][i], "registered": False, "component": -1, "reason": reason}
    z["registered"], z["component"] = reg, comp
    _save_npz(project, "work/reconstruction.npz", **z)
    project.write_json("work/reconstruction.json", meta)


def _low_texture_verdict(project: ProjectStore, out: dict, verdict: dict) -> dict:
    """Record the fallback's outcome for :func:`step_georef` (``work/low_texture.json`` -> survey.json) and the step."""
    project.write_json("work/low_texture.json", verdict)
    out["low_texture"] = {**out.get("low_texture", {}), **verdict}
    return out


def step_orient_low_texture(project: ProjectStore, opt: SurveyOptions, camera=None, progress=None, rgb_camera=None,
                            rig=None, *, primary_rejected: bool = False) -> dict:
    """:func:`step_orient`, then, with ``low_texture == "auto"``, the low-texture fallback when the orientation left
    fewer than 80 % of the thermal frames in one block although the matching did not trigger it (descriptor matches
    on noise and the sensor's pattern verify pairs that no orientation can use: a plain wall's frames were all
    "connected" and none oriented). The fallback's ties replace the thermal ones and the orientation is run again;
    its result is kept only when its largest block holds more thermal frames, else everything is put back as it was.

    Every block of a tracked sequence (from either trigger) must pass :func:`_low_texture_check` (its coplanar points
    lie flat, most points of consecutive frames on one plane); a refused block's thermal frames are not oriented
    (their reason says why) and the primary matching's orientation is put back when its largest thermal block is at
    least as large as what is left of the fallback's: with a refused block ``auto`` gives what ``off`` gives. The
    outcome goes to ``work/low_texture.json`` and survey.json's ``low_texture``.

    ``primary_rejected``: the final adjustment rejected every block of the primary orientation although it held
    enough frames not to trigger the fallback (descriptor matches on noise can connect every frame into a block
    that no adjustment can determine): the fallback runs, and its result is kept when it has any block
    (:func:`run_survey` re-runs ``georef`` on it).
    """
    out = step_orient(project, _low_texture_orient_options(project, opt), camera, progress, rgb_camera)
    if opt.low_texture != "auto":
        return _low_texture_verdict(project, out, {"ran": False})
    feats = project.read_json("work/pairs.json").get("features", {})  # (read once: the checks below do not write it)
    if "low_texture" in feats:
        if not _low_texture_sequence_used(project):
            lt_info = feats["low_texture"]
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": "used" in feats,
                                                       **({"why": lt_info["refused"]} if lt_info.get("refused") else {})})
        chk = _low_texture_check(project)
        if not chk["refused_images"]:
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": True, "check": chk["blocks"]})
        why = sorted(set(chk["why"].values()))[0]
        prim = feats.get("primary_kept")
        if prim is not None and project.exists("lowtexture/primary/work/pairs.json"):
            # a block refused: the primary matching is oriented instead (what ``off`` gives); the refused block's
            # frames are not oriented in the fallback's result, so the primary one is kept unless the fallback's
            # remaining blocks hold more thermal frames
            _low_texture_unregister(project, chk["why"])
            _, best_rest = _largest_thermal_block(project)
            saved = {k: project.read_bytes(k) for k in ["work/pairs.json", "work/features.json", "work/reconstruction.json",
                                                        "work/reconstruction.npz"]}
            saved_ties = {k: project.read_bytes(k) for k in (f"work/tie_xy/{im['name']}.npz"
                                                             for im in project.read_json("work/inputs.json")["images"])
                          if project.exists(k)}
            lt_files = {k: project.read_bytes(k) for k in prim if project.exists(k)}
            for k in prim:
                project.write_bytes(k, project.read_bytes(f"lowtexture/primary/{k}"))
            project.write_json("work/features.json", project.read_json("lowtexture/primary/work/features.json"))
            pp = project.read_json("lowtexture/primary/work/pairs.json")
            # what the fallback did stays on record (without "used": its ties are not the ones in use)
            pp["features"]["low_texture"] = {**json.loads(saved["work/pairs.json"])["features"]["low_texture"], "refused": why}
            project.write_json("work/pairs.json", pp)
            out_p = step_orient(project, opt, camera, progress, rgb_camera)
            _, best_p = _largest_thermal_block(project)
            if best_p >= best_rest:
                names = [im["name"] for im in project.read_json("work/inputs.json")["images"]]
                return _low_texture_verdict(project, out_p, {"ran": True, "trigger": "matching", "kept": False,
                                                             "check": chk["blocks"], "why": why, "primary_block": best_p,
                                                             "refused_images": [names[i] for i in chk["refused_images"]]})
            for k, v in {**lt_files, **saved, **saved_ties}.items():  # the fallback's remaining blocks are larger
                project.write_bytes(k, v)
            out["oriented"] -= len(chk["refused_images"])
            return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": True, "check": chk["blocks"],
                                                       "why": why, "primary_block": best_p})
        _low_texture_unregister(project, chk["why"])
        out["oriented"] -= len(chk["refused_images"])
        return _low_texture_verdict(project, out, {"ran": True, "trigger": "matching", "kept": False,
                                                   "check": chk["blocks"], "why": why})
    nt, best = _largest_thermal_block(project)
    if nt < 2 or (best >= LOW_TEXTURE_SHARE * nt and not primary_rejected):
        return _low_texture_verdict(project, out, {"ran": False})
    trigger = "orientation"
    if primary_rejected:
        trigger, best = "adjustment", 1  # the primary blocks were all rejected: any block of two frames is more
    inputs = project.read_json("work/inputs.json")["images"]
    keep = ["work/pairs.json", "work/features.json", "work/reconstruction.json", "work/reconstruction.npz"]
    keep += [f"work/tie_xy/{im['name']}.npz" for im in inputs]
    keep += [f"features/{im['name']}.npz" for im in inputs if im.get("sensor", "thermal") == "thermal"]
    keep += [f"matches/{i}_{j}.npz" for i, j, _, _, reason in project.read_json("work/pairs.json")["pairs"] if not reason]
    keep = [k for k in keep if project.exists(k)]
    for k in keep:  # the primary result, put aside on disk (features can be large)
        project.write_bytes(f"lowtexture/primary/{k}", project.read_bytes(k))

    def restore():
        for k in keep:
            project.write_bytes(k, project.read_bytes(f"lowtexture/primary/{k}"))

    m = step_matching(project, opt, camera, None, rig, low_texture_only=True)
    if primary_rejected and "low_texture" in m["features"]:
        m["features"]["low_texture"]["trigger"] = "adjustment: the final adjustment rejected every primary block"
        pp = project.read_json("work/pairs.json")
        pp["features"]["low_texture"]["trigger"] = m["features"]["low_texture"]["trigger"]
        project.write_json("work/pairs.json", pp)
    lt = m["features"].get("low_texture", {})
    if "used" not in m["features"]:
        restore()
        out["low_texture"] = lt
        return _low_texture_verdict(project, out, {"ran": True, "trigger": trigger, "kept": False,
                                                   "why": "the fallback verified no consecutive pair"})
    out2 = step_orient(project, _low_texture_orient_options(project, opt), camera, progress, rgb_camera)
    chk = _low_texture_check(project) if _low_texture_sequence_used(project) else {"blocks": [], "refused_images": [], "why": {}}
    if chk["refused_images"]:
        _low_texture_unregister(project, chk["why"])
        out2["oriented"] -= len(chk["refused_images"])
    _, best2 = _largest_thermal_block(project)
    if best2 > best:
        out2["low_texture"] = {**lt, "largest_thermal_block_before": best, "largest_thermal_block": best2}
        return _low_texture_verdict(project, out2, {"ran": True, "trigger": trigger, "kept": True, "check": chk["blocks"],
                                                    **({"why": sorted(set(chk["why"].values()))[0]} if chk["why"] else {})})
    # the primary result stands (its frames keep their own reasons)
    restore()
    out["low_texture"] = lt
    why = (sorted(set(chk["why"].values()))[0] if chk["why"] else
           f"its largest block holds {best2} thermal frames" + (" (the primary's were rejected by the final adjustment)"
                                                                if primary_rejected else f", the primary's {best}"))
    return _low_texture_verdict(project, out, {"ran": True, "trigger": trigger, "kept": False, "check": chk["blocks"],
                                               "why": why})


def _load_reconstruction(project: ProjectStore):
    from ..camera import Camera
    from ..results import Outcome, Termination
    from ..sfm.reconstruction import ImageStatus, Reconstruction
    from ..sfm.tracks import Tracks

    z = _load_npz(project, "work/reconstruction.npz")
    meta = project.read_json("work/reconstruction.json")
    cams = [Camera.from_dict(meta["cameras"][c], source="work/reconstruction.json") for c in meta["camera_ids"]]
    tr = Tracks(z["track"], z["image"], z["feature"])
    rec = Reconstruction(Outcome(Termination(meta["termination"]), meta["reason"]), cams, z["image_camera"], z["R"], z["t"],
                         z["registered"].astype(bool), z["component"], z["points"], tr, z["obs_valid"].astype(bool),
                         [ImageStatus(s["registered"], s["component"], s["reason"]) for s in meta["status"]], meta["log"])
    return rec, meta


def _read_manual_ties(path_meas, names, exclude_ids, default_sigma_px):
    """Rows of the GCP measurement file whose id is neither a GCP nor a check point: manual tie points.

    Returns (tie ids, observations [(image index, tie index, xy, sigma)], notes).
    """
    from ..io.testfield_csv import read_measurements_csv

    if path_meas is None:
        return [], [], []
    meas = read_measurements_csv(path_meas)
    index = {n: k for k, n in enumerate(names)}
    ids: dict[str, int] = {}
    obs = []
    for r in range(len(meas.id)):
        pid = meas.id[r]
        if pid in exclude_ids:
            continue
        k = index.get(meas.image[r], index.get(Path(meas.image[r]).stem))
        if k is None:
            continue  # named by _read_markers' note on images that are not inputs
        s = meas.std[r] if meas.std is not None else np.array([default_sigma_px, default_sigma_px])
        obs.append((k, ids.setdefault(pid, len(ids)), meas.xy[r], s))
    notes = [f"{meas.source}: {len(ids)} id(s) in neither the GCP nor the check-point file used as manual tie points "
             f"(unknown 3D points): {_name_list(list(ids), 5)}"] if ids else []
    return list(ids), obs, notes


def _read_markers(path_pts, path_meas, names, default_sigma_m, default_sigma_px, what, *, unknown_ids_note=True):
    """Control/check CSVs -> ids, xyz, sigma, observations [(image index, point index, xy, sigma)], notes."""
    from ..io.testfield_csv import read_control_csv, read_measurements_csv

    if path_pts is None:
        return [], np.zeros((0, 3)), np.zeros((0, 3)), [], []
    ctrl = read_control_csv(path_pts)
    sig = ctrl.std if ctrl.std is not None else np.full((len(ctrl.ids), 3), default_sigma_m)
    obs, notes = [], []
    if path_meas is None:
        notes.append(f"{what}: no image measurements given ({path_pts} alone cannot be used)")
        return list(ctrl.ids), ctrl.xyz, sig, obs, notes
    meas = read_measurements_csv(path_meas)
    index = {}
    for k, n in enumerate(names):
        index[n] = k
    idmap = {pid: k for k, pid in enumerate(ctrl.ids)}
    unknown_img, unknown_id = set(), set()
    for r in range(len(meas.id)):
        im = meas.image[r]
        k = index.get(im, index.get(Path(im).stem))
        if k is None:
            unknown_img.add(im)
            continue
        g = idmap.get(meas.id[r])
        if g is None:
            unknown_id.add(meas.id[r])
            continue
        s = meas.std[r] if meas.std is not None else np.array([default_sigma_px, default_sigma_px])
        obs.append((k, g, meas.xy[r], s))
    if unknown_img:
        notes.append(f"{meas.source}: measurements in {len(unknown_img)} image(s) that are not inputs, ignored: {', '.join(sorted(unknown_img)[:5])}")
    if unknown_id and unknown_ids_note:
        notes.append(f"{meas.source}: {len(unknown_id)} id(s) not in {ctrl.source}, ignored: {', '.join(sorted(unknown_id)[:5])}")
    return list(ctrl.ids), ctrl.xyz, sig, obs, notes


def step_georef(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions, camera=None, progress=None) -> dict:
    """Georeference the largest block(s), adjust, intersect check points, write every output."""
    from ..results import Termination
    from ..sfm.georef import (MIN_ATTITUDE_IMAGES, ControlInputs, apply_similarity, attitude_images, axis_statistics,
                              intersect_check_points, similarity_start)

    t0 = time.perf_counter()
    inputs = project.read_json("work/inputs.json")
    names = [im["name"] for im in inputs["images"]]
    release_free_heap()  # (what the steps before left in the heap)
    rec, meta = _load_reconstruction(project)
    xy = [_tie_xy(project, n) for n in names]
    gnss, gsig, crs, notes = _gnss_xyz(inputs, opt, opt.crs)
    g_ids, g_xyz, g_sig, g_obs, n1 = _read_markers(inp.gcps, inp.gcp_measurements, names, opt.gcp_sigma_m, opt.marker_sigma_px, "GCPs")
    c_ids, c_xyz, _, c_obs, n2 = _read_markers(inp.checkpoints, inp.check_measurements, names, opt.gcp_sigma_m,
                                               opt.marker_sigma_px, "check points")
    notes += n1 + n2
    # ids of the GCP measurement file in neither gcps.csv nor cp.csv: manual tie points (RGB <-> thermal)
    t_ids, t_obs, n3 = _read_manual_ties(inp.gcp_measurements, names, set(g_ids) | set(c_ids), opt.marker_sigma_px)
    notes += n3
    ctrl = ControlInputs(gnss, np.where(np.isfinite(gsig), gsig, 1.0), np.asarray(opt.lever_arm_m, float),
                         g_ids, g_xyz, g_sig, g_obs, c_ids, c_xyz, c_obs,
                         attitude=_attitudes(inputs, crs) if str(opt.gnss).lower() != "none" else None)
    comps = rec.components()
    results = []
    oriented = np.zeros(len(names), bool)
    second_pass: list = []  # accepted GNSS blocks that may take images left over at the end (_extend_with_gnss)
    rejected_at: dict = {}  # index in results of a rejected block -> its images (the second pass may move them)
    fa_all = []
    rig_master, rig_enabled, rig_out, tie_out = {}, {}, [], []
    rig_only: dict[int, str] = {}  # oriented rig views without observations of their own -> reason
    # intrinsics: a given thermal camera (--camera or the rig's) is held fixed, other sensors self-calibrated
    rgb_cam = getattr(inp.rig, "rgb_camera", None)
    self_cal = opt.self_calibrate if camera is None and rgb_cam is None else {
        k: (() if (camera is not None and str(cid).startswith("thermal")) or (rgb_cam is not None and str(cid).startswith("rgb"))
            else opt.self_calibrate) for k, cid in enumerate(meta["camera_ids"])}
    # the focal-length band of the plausibility test applies only where the start came from the file's EXIF focal
    # length and pixel pitch: a video or an image without them starts from a guess (1 x the width), which
    # self-calibration is there to correct (a factor 2.3 on the synthetic video of tests/test_io_video.py)
    focal_known = {k: _focal_from_exif(inputs, rec, k) for k in range(len(meta["camera_ids"]))}
    self_cal, lt_note = _low_texture_self_calibration(project, meta["camera_ids"], self_cal, focal_known)
    notes += [lt_note] if lt_note else []
    if inp.rig is not None:
        from ..sfm.rig import (RIG_MIN_OWN_OBSERVATIONS, attach_rig_images, own_observations, pair_rig_images,
                               plan_rig_blocks, rig_estimate_accepted, rig_estimation_evidence, rig_report, start_rig)

        rig_master, nts, rig_unpaired = pair_rig_images(inp.rig, inputs["images"])
        rig_used, rig_reg, nts_reg, self_cal = _rig_by_registration(
            project, rec, inp.rig, rig_master, names, comps, thermal_camera_given=camera is not None, xy=xy, ctrl=ctrl,
            self_cal=self_cal, adjust_kw=dict(focal_known=focal_known, tie_sigma_px=opt.tie_sigma_px,
                                              max_error_px=opt.reconstruction.max_error_px))
        nts += nts_reg
        comps, rig_enabled, nts2 = plan_rig_blocks(rec, rig_used, rig_master, comps)
        notes += nts + nts2 + [f"rig: {len(rig_master)} RGB/thermal pair(s) from {inp.rig.source}"]
    lt_seq = _low_texture_sequence_used(project)
    lt_verdict = project.read_json("work/low_texture.json") if project.exists("work/low_texture.json") else {}
    if lt_verdict.get("why"):
        notes.append(f"{lt_verdict['why']}; " + ("its frames are not oriented" if lt_verdict.get("kept") else
                                                 "the primary matching's orientation is kept (what --low-texture off gives)"))
    queue = list(enumerate(comps))
    pruned_blocks: set[int] = set()  # blocks already adjusted again without their GNSS-contradicting images
    attitude_blocks: set[int] = set()  # blocks adjusted again with the camera attitudes (their GNSS left a rotation open)
    while queue:
        ci, images = queue.pop(0)
        if len(images) == 0:
            continue
        S, datum, nts = similarity_start(rec, images, ctrl, attitude_line=ci in attitude_blocks)
        notes += [f"block {ci + 1}: {x}" for x in nts]
        geo = S is not None
        # the block as the orientation left it (for :func:`_prune_gnss_contradicting` and a second adjustment with the
        # camera attitudes): GNSS blocks only, not with a rig (similarity_start changes nothing in ``rec``)
        pre = _rig_snapshot(rec) if geo and datum.from_gnss and ci not in rig_enabled else None
        if not geo and ci > 0:
            # a second block without datum cannot be placed with the first: reported, not exported
            for i in images:
                rec.status[i].reason = f"in block {ci + 1} ({len(images)} images) that has no GNSS/GCP datum and no tie to block 1"
            continue
        rigv = None
        if ci in rig_enabled:
            rigv, nts = start_rig(rec, rig_used, rig_master, images, S.scale if geo else 1.0)
            notes += [f"block {ci + 1}: {x}" for x in nts]
        gnss_off = None
        if geo:
            apply_similarity(rec, images, S)
            if datum.from_gnss and ctrl.gcp_obs and inp.rig is None:
                gnss_off, nts = _gnss_offset(rec, xy, images, ctrl, self_cal, tie_sigma_px=opt.tie_sigma_px,
                                             max_error_px=opt.reconstruction.max_error_px, georeferenced=True)
                notes += [f"block {ci + 1}: {x}" for x in nts]
        elif rigv is not None:
            notes += [f"block {ci + 1}: {x}" for x in _rig_scale_local(rec, images, inp.rig, rig_master, rigv)]
        block_images, snap, refused = images, None, ""
        if rigv is not None:
            snap = _rig_snapshot(rec)
            images, nts = attach_rig_images(rec, images, rigv, xy, max_error_px=opt.reconstruction.max_error_px,
                                            min_tri_angle_deg=opt.reconstruction.min_tri_angle_deg)
            notes += [f"block {ci + 1}: {x}" for x in nts]
            if not rigv.fixed:
                # R*, t estimated only from enough evidence (sfm.rig: >= 3 thermal frames with own observations,
                # spread over the block); a guess held at its start is not an orientation
                ok, why = rig_estimation_evidence(rec, rigv, images, _rig_own_before(rec, rigv, images, t_obs))
                refused = "" if ok else why
        fa = None
        # the final adjustment's options for this block (the images and the rig may change below)
        adjust_kw = dict(focal_known=focal_known, attitude_priors=geo and datum.from_attitude, tie_sigma_px=opt.tie_sigma_px,
                         max_error_px=opt.reconstruction.max_error_px, georeferenced=geo, manual_ties=t_obs or None)
        if rigv is not None and not refused:
            fa, cal_used, cal_steps = _adjust_block(rec, xy, images, ctrl, self_cal, rigv=rigv,
                                                    compute_covariance=len(images) <= 2500, **adjust_kw)
            if not rigv.fixed:
                ok, why = rig_estimate_accepted(rigv, fa)
                refused = "" if ok else why
                if refused:
                    notes += [f"block {ci + 1}: {x}" for x in fa.notes]
        if refused:
            # estimation refused: the block is adjusted without the rig; thermal frames oriented on their own in
            # this block stay (as plain images), the others are not oriented
            images = _rig_refuse(rec, snap, rigv, block_images, names, refused, ci, S if geo else None)
            notes.append(f"block {ci + 1}: rig: R*, t not estimated: {refused}; the thermal frames of this block are "
                         "oriented only where they have an orientation of their own")
            rig_out.append({"block": ci + 1, "estimated": False, "refused": refused, "start": rigv.start,
                            "pairs": len(rigv.master)})
            rigv = None
            fa = None
        if fa is None:
            fa, cal_used, cal_steps = _adjust_block(rec, xy, images, ctrl, self_cal, rigv=rigv,
                                                    compute_covariance=len(images) <= 2500, **adjust_kw)
        release_free_heap()
        notes += [f"block {ci + 1}: {x}" for x in fa.notes]
        notes += [f"block {ci + 1}: {x}" for x in cal_steps]
        if cal_steps and cal_steps[-1].startswith("with the camera held fixed"):
            # not even the orientation alone is determined: not an orientation
            why = (f"in block {ci + 1} ({len(images)} images) rejected: its geometry does not determine the "
                   f"orientation ({cal_steps[-1]})")
            for i in images:
                rec.status[i].reason = why
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum), "rejected": why,
                            "self_calibration_steps": cal_steps})
            continue
        if lt_seq and cal_steps and any(str(meta["camera_ids"][int(rec.image_camera[i])]).startswith("thermal") for i in images):
            # a tracked low-texture sequence self-calibrates only k1, k2 (+ fx, fy without an EXIF focal length); a
            # block that cannot carry even that is in conflict with a physical camera: the windowed synthetic facade's
            # wrong block (25 deg off) asked for fy/fx = 0.87 at every rung
            why = (f"in block {ci + 1} ({len(images)} images) rejected: a low-texture sequence's block whose limited "
                   f"self-calibration was refused ({cal_steps[0]})")
            for i in images:
                rec.status[i].reason = why
            notes.append(f"block {ci + 1}: {why.split(' rejected: ')[1]}")
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum), "rejected": why,
                            "self_calibration_steps": cal_steps})
            continue
        if rigv is not None:
            own = own_observations(rigv, images, fa.tie_obs_image,
                                   [(mt_i,) for mt in fa.manual_ties for mt_i in mt["images"]])
            for s_, n_ in own.items():
                if n_ < RIG_MIN_OWN_OBSERVATIONS:
                    rig_only[s_] = ("pose from the rig only (no own tie points)" if n_ == 0 else
                                    f"pose from the rig only ({n_} own observation(s) < {RIG_MIN_OWN_OBSERVATIONS})")
            rig_out.append({"block": ci + 1, **rig_report(rigv, geo),
                            "own_observations": {names[s_]: n_ for s_, n_ in sorted(own.items())},
                            **({"evidence": rig_estimation_evidence(rec, rigv, images, own)[1]} if not rigv.fixed else {})})
        for mt in fa.manual_ties:
            v_ = mt["residuals_px"]
            tie_out.append({"id": t_ids[mt["tie"]], "block": ci + 1, "xyz": mt["xyz"].tolist(),
                            "images": [names[i] for i in mt["images"]],
                            "sensors": sorted({inputs["images"][i]["sensor"] for i in mt["images"]}),
                            "rms_px": _tie_rms(v_)})
        v = fa.tie_residuals
        rms = _tie_rms(v)
        far = _gnss_far_share(rec, images, ctrl) if geo else 0.0
        if (pre is not None and ci not in pruned_blocks and fa.result.termination is Termination.MAX_ITERATIONS
                and (far > 0 or fa.gnss_rejected)):
            # the adjustment found no minimum and some centres contradict their GNSS: a few wrongly resected images
            # can be the cause. The block as the orientation left it, without the images that no similarity puts
            # near their GNSS (sfm.georef.gnss_consensus), is adjusted once more
            kept, nts = _prune_gnss_contradicting(rec, pre, images, ctrl, names, ci,
                                                  f"the final adjustment did not converge ({fa.result.reason}) with "
                                                  f"{100 * far:.0f} % of the centres > {GNSS_FLAG_SIGMA:g} σ from their "
                                                  f"GNSS and {len(fa.gnss_rejected)} GNSS position(s) rejected")
            if kept is not None:
                notes += nts
                fa = None
                release_free_heap()
                pruned_blocks.add(ci)
                queue.insert(0, (ci, kept))
                continue
        rot_sigma = _block_rotation_sigma(fa, images) if geo and _precise_datum(datum, ctrl, images) else 0.0
        if (rot_sigma > BLOCK_ROTATION_SIGMA_DEG and pre is not None and ci not in attitude_blocks
                and rms <= BLOCK_RMS_GATE_PX and len(attitude_images(ctrl, images)) >= MIN_ATTITUDE_IMAGES):
            # its GNSS does not fix its rotation, the frames' gimbal attitudes can: adjusted again from the orientation
            # with them (sfm.georef.similarity_start(attitude_line=True)) instead of being rejected
            notes.append(f"block {ci + 1}: its camera rotations have σ {rot_sigma:.1f}° on its GNSS alone (> "
                         f"{BLOCK_ROTATION_SIGMA_DEG:g}°): adjusted again with the camera attitudes of the files")
            _restore(rec, pre)
            fa = None
            release_free_heap()
            attitude_blocks.add(ci)
            queue.insert(0, (ci, images))
            continue
        why = ""
        if not rms <= BLOCK_RMS_GATE_PX:
            # a block whose tie points do not fit is not an orientation: it is reported, never exported
            why = (f"reprojection RMS {rms:.2f} px after the final adjustment (> {BLOCK_RMS_GATE_PX:g} px; inconsistent "
                   "tie points, e.g. repeated structure or too little texture)")
        elif far > BLOCK_GNSS_FAR_SHARE and ci in pruned_blocks:
            # already adjusted again without the images that contradicted the GNSS: still contradicting it, converged
            # or not, the rest is no orientation either
            why = (f"after leaving out the images that contradicted their GNSS, {100 * far:.0f} % of its camera centres "
                   f"are still more than {GNSS_FLAG_SIGMA:g} σ from their GNSS positions: its tie points contradict the "
                   "GNSS (a wrong relative orientation)")
        elif rot_sigma > BLOCK_ROTATION_SIGMA_DEG:
            why = (f"its camera rotations have σ {rot_sigma:.1f}° (median over its images, > "
                   f"{BLOCK_ROTATION_SIGMA_DEG:g}°): its GNSS/GCP datum does not fix its rotation (positions nearly on "
                   "a line or a short arc)")
        elif far > BLOCK_GNSS_FAR_SHARE and fa.result.termination is Termination.MAX_ITERATIONS:
            # the tie points and the GNSS disagree across the block and the adjustment finds no minimum: a wrong
            # relative orientation held together by GNSS, not an orientation
            why = (f"the final adjustment did not converge ({fa.result.reason}) and {100 * far:.0f} % of its camera "
                   f"centres are more than {GNSS_FLAG_SIGMA:g} σ from their GNSS positions: its tie points contradict "
                   "the GNSS (a wrong relative orientation)")
        if why:
            for i in images:
                rec.status[i].reason = f"in block {ci + 1} ({len(images)} images) rejected: {why}"
            notes.append(f"block {ci + 1}: {why}")
            results.append({"block": ci + 1, "images": len(images), "datum": str(datum),
                            "rejected": f"in block {ci + 1} ({len(images)} images) rejected: {why}"})
            rejected_at[len(results) - 1] = set(int(i) for i in images)
            continue
        n_own = len(images)
        extendable = geo and datum.from_gnss and rigv is None and not np.any(ctrl.lever_arm_m)
        if extendable:
            images, fa, cal_used, cal_steps, nts = _extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw,
                                                                      opt, (fa, cal_used, cal_steps), rms, far)
            notes += nts
        oriented[images] = True
        fa_all.append((ci, images, fa, datum, geo))
        results.append({"block": ci + 1, "images": len(images), "datum": str(datum), "sigma0": float(fa.result.sigma0),
                        "termination": fa.result.termination.value, "reason": fa.result.reason,
                        "self_calibration": sorted({n for v in cal_used.values() for n in v}),
                        "self_calibration_steps": cal_steps, **({"gnss_offset": gnss_off} if gnss_off else {}),
                        **({"added_at_gnss": [names[i] for i in images[n_own:]]} if len(images) > n_own else {})})
        if extendable:
            second_pass.append((len(fa_all) - 1, len(results) - 1, adjust_kw, cal_used, cal_steps))
    # images of blocks rejected after an accepted block was extended (short arcs, wrong blocks) and images still
    # unregistered: a second chance at their GNSS positions in the accepted blocks (their own orientation is dropped)
    left = np.nonzero(~oriented & np.all(np.isfinite(ctrl.gnss_xyz), axis=1))[0]
    freed = left[rec.registered[left]] if second_pass else left[:0]  # images of rejected blocks (the others were tried)
    _unregister(rec, freed)
    for k_fa, k_res, kw_b, cal_b, steps_b in (second_pass if len(freed) else []):
        ci, images, fa, datum, geo = fa_all[k_fa]
        v = fa.tie_residuals
        rms = _tie_rms(v)
        n_own = len(images)
        images2, fa2, cal2, steps2, nts = _extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, kw_b, opt,
                                                             (fa, cal_b, steps_b), rms, _gnss_far_share(rec, images, ctrl))
        notes += nts
        if len(images2) > n_own:
            oriented[images2] = True
            fa_all[k_fa] = (ci, images2, fa2, datum, geo)
            r = results[k_res]
            r.update({"images": len(images2), "sigma0": float(fa2.result.sigma0), "termination": fa2.result.termination.value,
                      "reason": fa2.result.reason, "self_calibration": sorted({n for v in cal2.values() for n in v}),
                      "self_calibration_steps": steps2,
                      "added_at_gnss": r.get("added_at_gnss", []) + [names[i] for i in images2[n_own:]]})
            for k_rej, members in rejected_at.items():
                # the rejected block's entry says where its images went (it still counts them as its own)
                moved = [names[i] for i in images2[n_own:] if int(i) in members]
                if moved:
                    results[k_rej].setdefault("moved_to_blocks", {})[str(ci + 1)] = moved
    if not fa_all:
        crs = None
    georeferenced = any(g for *_, g in fa_all)
    if not georeferenced:
        crs = None
    # check points (in the block that sees them)
    checks = []
    gcp_errors = []
    gcp_rejected = []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        checks += [c for c in intersect_check_points(rec, fa, ctrl) if c["xyz"] is not None or c["n_images"] > 0]
        gcp_errors += [fa.gcp_residuals_m[g] for g in np.nonzero(fa.gcp_used)[0]]
        gcp_rejected += [{"image": names[i], "id": gid, "residual_px": e} for i, gid, e in fa.gcp_rejected]
    # merge check points seen in several blocks: keep the one with most images
    best = {}
    for c in checks:
        if c["xyz"] is None:
            best.setdefault(c["id"], c)
        elif c["id"] not in best or best[c["id"]]["xyz"] is None or c["n_images"] > best[c["id"]]["n_images"]:
            best[c["id"]] = c
    checks = [best[k] for k in c_ids if k in best]
    extra = {}
    if inp.rig is not None:
        for s_, m_ in rig_master.items():
            if not oriented[s_] and not oriented[m_]:
                rec.status[s_].reason = f"RGB partner {names[m_]} not oriented; on its own: {rec.status[s_].reason or 'not oriented'}"
        for s_, why in rig_unpaired.items():
            if not oriented[s_]:
                rec.status[s_].reason = f"{why}; on its own: {rec.status[s_].reason or 'not oriented'}"
        r_only = sorted(k for k in rig_only if oriented[k])
        extra["rig"] = {"file": inp.rig.source, "pairs": len(rig_master), "fixed": not rig_used.estimate,
                        **({"registration": rig_reg} if rig_reg else {}),
                        "thermal_unpaired": [names[k] for k in sorted(rig_unpaired)], "blocks": rig_out,
                        "rig_only": [names[k] for k in r_only],
                        "rig_only_counted": (
                            "thermal images posed only through the rig (no or too few observations of their own) are "
                            "counted in images_oriented: R*, t is given by the rig file (calibrated), was estimated in "
                            "their block from >= 3 spread thermal frames with a converged adjustment and finite σ, or "
                            "was registered on the edges of >= 3 agreeing RGB/thermal pairs (rig.registration); "
                            "when that evidence is missing R*, t is not estimated and they are not oriented")}
        extra["images_rig_only"] = len(r_only)
    if t_ids:
        extra["manual_ties"] = {"ids": len(t_ids), "used": tie_out}
    extra["mapper"] = meta.get("mapper", "incremental")  # which orientation built the blocks (SurveyOptions.mapper)
    if meta.get("mapper_auto"):
        extra["mapper_auto"] = meta["mapper_auto"]
    ov = project.read_json("work/overlay.json") if project.exists("work/overlay.json") else {"found": False}
    extra["overlay"] = ({k: ov[k] for k in ("share", "frames", "images", "size")} if ov.get("found") else None)
    if ov.get("found"):
        notes.append(f"a display burned into the 8-bit frames (text, marks, colour bar at the same pixels in every "
                     f"frame) was found in {ov['frames']} frames: {100 * ov['share']:.1f} % of each "
                     f"{ov['size'][0]}x{ov['size'][1]} frame masked, no tie points there ({ov['images']} images)")
    if lt_verdict:
        extra["low_texture"] = lt_verdict
        for nm in lt_verdict.get("refused_images", []):  # frames the primary orientation left out: both reasons
            i = names.index(nm)
            if not oriented[i] and lt_verdict["why"] not in rec.status[i].reason:
                rec.status[i].reason = f"{rec.status[i].reason or 'not oriented'}; {lt_verdict['why']}"
    out = _write_outputs(project, inputs, rec, fa_all, names, crs, ctrl, checks, gcp_errors, gcp_rejected, notes, results,
                         extra=extra, rig_only={k: w for k, w in rig_only.items() if oriented[k]})
    out["seconds_georef"] = time.perf_counter() - t0
    return out


# ------------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------------
def _point_values(project, inputs, rec, names, images_used, obs_mask):
    """Mean frame value at the observations of each point (bilinear), and whether it is a temperature."""
    tr = rec.tracks
    units = {inputs["images"][i]["unit"] for i in images_used}
    unit = units.pop() if len(units) == 1 else "mixed"
    vals = np.zeros(len(rec.points))
    cnt = np.zeros(len(rec.points))
    if unit not in ("K", "counts"):
        return None, unit
    for i in images_used:
        o = np.nonzero(obs_mask & (tr.image == i))[0]
        if len(o) == 0:
            continue
        img = _read_frame(project, names[i]).astype(np.float64)
        xy = _tie_xy(project, names[i])[tr.feature[o]]
        import cv2

        v = cv2.remap(img.astype(np.float32), xy[:, 0].astype(np.float32).reshape(-1, 1), xy[:, 1].astype(np.float32).reshape(-1, 1),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
        ok = np.isfinite(v)
        np.add.at(vals, tr.track[o][ok], v[ok])
        np.add.at(cnt, tr.track[o][ok], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return vals / cnt, unit


def _rig_own_before(rec, rigv, images, manual_obs) -> dict:
    """Own observations per rig view before the adjustment: valid observations of triangulated points + manual."""
    from ..sfm.rig import own_observations

    tr = rec.tracks
    ok = rec.obs_valid & np.isfinite(rec.points[tr.track]).all(1)
    return own_observations(rigv, images, tr.image[ok], manual_obs or ())


def _gnss_offset(rec, xy, images, ctrl, self_cal, **kw) -> tuple[dict | None, list[str]]:
    """Look for a constant GNSS-vs-GCP datum offset in a GNSS-placed block with >= 3 GCPs
    (:func:`~thermogrammetry.sfm.georef.gnss_offset`): one adjustment on the GCPs alone (GNSS σ × 1000), the
    block restored afterwards; the GNSS positions (and the block's start) are shifted by the significant axes.
    Returns the report entry and notes."""
    from dataclasses import replace as dc_replace

    from ..sfm.georef import GNSS_OFFSET_MIN_GCPS, apply_similarity, final_adjustment, gnss_offset, similarity_start

    images = np.asarray(images)
    in_block = set(images.tolist())
    gcps = {gi for (i, gi, xy_, s_) in ctrl.gcp_obs if i in in_block}
    if len(gcps) < GNSS_OFFSET_MIN_GCPS:
        return None, []
    if len(images) > 2500:  # the centres' σ need the covariance, which large blocks skip (as the final adjustment does)
        return None, [f"GNSS against the GCPs: not checked for a datum offset ({len(images)} images: no covariance "
                      "above 2500)"]
    snap = _rig_snapshot(rec)
    weak = dc_replace(ctrl, gnss_sigma=ctrl.gnss_sigma * 1e3)
    try:
        # GCP measurement blunders first, on the block with its cameras held: with a datum of a few GCPs and
        # self-calibration, a wrong measurement (a GCP "measured" where it is not) can bend the block until it fits
        # within the rejection threshold (seen: focal length -8 %, the GNSS offset 4.8 m off in Z)
        fa0 = final_adjustment(rec, xy, images, weak, self_calibrate=(), compute_covariance=False, **kw)
        bad = {(int(i), gid) for i, gid, _e in fa0.gcp_rejected}
        fa0 = None  # (its problem and residuals) not held through the next adjustment
        _restore(rec, snap)
        if bad:
            weak = dc_replace(weak, gcp_obs=[o for o in weak.gcp_obs if (int(o[0]), ctrl.gcp_ids[o[1]]) not in bad])
        fa = final_adjustment(rec, xy, images, weak, self_calibrate=self_cal, compute_covariance=True, **kw)
        off = gnss_offset(rec.centers()[images], fa.center_std[images], ctrl.gnss_xyz[images], ctrl.gnss_sigma[images]) \
            if fa.result.success else None
    finally:
        _restore(rec, snap)
    if off is None:
        return None, ["GNSS against the GCPs: not checked for a datum offset (the adjustment on the GCPs alone "
                      "did not give centres with σ)"]
    shift = np.where(off.significant, off.offset_m, 0.0)  # added to the GNSS: GCP datum = GNSS + shift
    fmt = lambda v: "(" + ", ".join(f"{x:+.3f}" for x in v) + ")"  # noqa: E731
    entry = {"offset_m": off.offset_m.tolist(), "std_m": off.std_m.tolist(), "n_gcps": len(gcps),
             "applied_m": shift.tolist(),
             "meaning": "GCP datum minus GNSS datum, from the camera centres of an adjustment on the GCPs alone"}
    if not off.significant.any():
        return entry, [f"GNSS against {len(gcps)} GCPs: no datum offset (GCP − GNSS {fmt(off.offset_m)} m "
                       f"± {fmt(off.std_m)} m)"]
    have = np.all(np.isfinite(ctrl.gnss_xyz[images]), axis=1)
    ctrl.gnss_xyz[images[have]] += shift
    S, _, _ = similarity_start(rec, images, ctrl)
    if S is not None:
        apply_similarity(rec, images, S)
    axes = ", ".join(a for a, f in zip("XYZ", off.significant) if f)
    return entry, [f"GNSS positions differ from the {len(gcps)} GCPs by a constant {fmt(off.offset_m)} m ± "
                   f"{fmt(off.std_m)} m (GCP − GNSS): a datum or height-reference difference (ellipsoidal vs geoid or "
                   f"national heights, take-off altitude) or an antenna offset; the GNSS positions are shifted in "
                   f"{axes} by {fmt(shift)} m before the adjustment"]


def _focal_from_exif(inputs: dict, rec, cam_index: int) -> bool:
    """True when every image of this camera had its starting focal length from EXIF focal length and pixel pitch
    (``camera_guess.source`` "EXIF focal ... / pitch ..." or a 35 mm-equivalent focal), not a guess."""
    srcs = [str(im.get("camera_guess", {}).get("source", "")) for im, c in zip(inputs["images"], rec.image_camera)
            if int(c) == cam_index]
    return bool(srcs) and all(s_.startswith("EXIF") and "assumed" not in s_ for s_ in srcs)


def _intrinsics_problem(fa, start_cams: dict, free_sets: dict, focal_known: dict | None = None) -> tuple[int | None, str]:
    """Why a final adjustment's self-calibration cannot be accepted: ``(camera index, reason)`` for one camera's
    implausible or undetermined intrinsics, ``(None, reason)`` when the solve itself failed, ``(None, "")`` when
    it can be accepted (:func:`_intrinsics_check` also says which check refused it).

    ``start_cams``: camera index -> Camera before the adjustment; ``free_sets``: camera index -> free names;
    ``focal_known``: camera index -> whether the starting focal length is the file's (only then is the focal
    band of :data:`INTRINSICS_PLAUSIBLE` applied; default: for every camera).
    """
    cam, why, _ = _intrinsics_check(fa, start_cams, free_sets, focal_known)
    return cam, why


def _intrinsics_check(fa, start_cams: dict, free_sets: dict, focal_known: dict | None = None) -> tuple[int | None, str, str]:
    """:func:`_intrinsics_problem` and the check that refused: ``"solve"``, ``"sigma"``, ``"focal"``, ``"aspect"``,
    ``"principal_point"``, ``"distortion"`` or ``""``."""
    res = fa.result
    if not res.success or res.termination.value == "rank_deficient":
        return None, f"the adjustment stopped: {res.reason or res.termination.value}", "solve"
    lim = INTRINSICS_PLAUSIBLE
    order = sorted(start_cams)
    for c in order:
        free = {n.lower() for n in free_sets.get(c, ())}
        if not free:
            continue
        cam0, cam = start_cams[c], fa.cameras_after[c]
        p0, p = cam0.param_dict, cam.param_dict
        w, h = cam.image_size
        if res.camera_std and order.index(c) < len(res.camera_std):
            std = dict(zip(cam.param_names, np.asarray(res.camera_std[order.index(c)], float)))
            bad = sorted(n for n in free if n in std and not np.isfinite(std[n]))
            if bad and fa.covariance_asked:
                return c, f"camera {cam.name or c}: σ of {', '.join(bad)} not finite (the block does not determine them)", "sigma"
        if "fx" in p and "fy" in p:
            known = True if focal_known is None else bool(focal_known.get(c, False))
            if known and (abs(p["fx"] / p0["fx"] - 1) > lim["focal"] or abs(p["fy"] / p0["fy"] - 1) > lim["focal"]):
                return c, (f"camera {cam.name or c}: focal length {p['fx']:.1f}/{p['fy']:.1f} px from a start of {p0['fx']:.1f} px "
                        f"(more than {lim['focal']:.0%} apart)"), "focal"
            if abs(p["fy"] / p["fx"] - 1) > lim["aspect"]:
                return c, f"camera {cam.name or c}: fy/fx = {p['fy'] / p['fx']:.3f} (pixels are square to within {lim['aspect']:.0%})", "aspect"
        if "cx" in p and (abs(p["cx"] - p0["cx"]) > lim["principal_point"] * w or abs(p["cy"] - p0["cy"]) > lim["principal_point"] * h):
            return c, (f"camera {cam.name or c}: principal point ({p['cx']:.1f}, {p['cy']:.1f}) px, more than "
                    f"{lim['principal_point']:.0%} of the frame from its start ({p0['cx']:.1f}, {p0['cy']:.1f})"), "principal_point"
        if "k1" in p and "fx" in p:
            r2 = ((w / 2) ** 2 + (h / 2) ** 2) / p["fx"] ** 2
            d = abs(p.get("k1", 0.0) * r2 + p.get("k2", 0.0) * r2**2 + p.get("k3", 0.0) * r2**3)
            if d > lim["corner_distortion"]:
                return c, f"camera {cam.name or c}: radial distortion {d:.0%} of the radius at the frame corner", "distortion"
    return None, "", ""


def _ladder_sets(self_cal, cam_indices) -> dict:
    """Rungs of :data:`SELF_CALIBRATION_LADDER` for the requested self-calibration, per camera index: a list of
    tuples of free names, from the request down to none (no rung repeated)."""
    out = {}
    for c in cam_indices:
        want = tuple(self_cal.get(int(c), ()) if isinstance(self_cal, dict) else self_cal)
        rungs: list = []
        for rung in (None,) + SELF_CALIBRATION_LADDER:
            sets = want if rung is None else tuple(n for n in want if n.lower() in rung)
            if sets not in rungs:
                rungs.append(sets)
        out[int(c)] = rungs
    return out


def _fixed_interior_rungs(want, tried) -> list:
    """:data:`FIXED_INTERIOR_LADDER` intersected with the requested parameters ``want``, without the rungs already
    ``tried``; ends with the camera held fixed."""
    out: list = []
    for rung in FIXED_INTERIOR_LADDER:
        sets = tuple(n for n in want if n.lower() in rung)
        if sets not in out and sets not in tried:
            out.append(sets)
    return out if out and out[-1] == () else out + [()]


def _adjust_block(rec, xy, images, ctrl, self_cal, *, rigv=None, focal_known: dict | None = None, **kw):
    """:func:`~thermogrammetry.sfm.georef.final_adjustment` with a self-calibration the block can carry.

    The requested parameters first. When one camera's intrinsics are implausible (:data:`INTRINSICS_PLAUSIBLE`)
    or a free parameter's σ is not finite, that camera steps one rung down :data:`SELF_CALIBRATION_LADDER`
    (fewer parameters; after an implausible focal length the rungs of :data:`FIXED_INTERIOR_LADDER`, distortion
    only); when the solve itself stops (rank deficient), every camera with free parameters
    steps down. ``rec`` is restored and the block adjusted again, until the solve is accepted or every camera
    is held fixed. (On the frescoes, RGB + thermal through a rig, the thermal camera with 2 frames of its own
    ran to fy = 316 px while the RGB camera, 40 frames, was well determined: only the thermal one steps down.)
    Returns the final adjustment, the free parameters used per camera index and the reasons of every step.
    """
    from ..sfm.georef import final_adjustment

    cams_in = sorted({int(c) for c in rec.image_camera[np.asarray(images)]})
    start = {c: rec.cameras[c] for c in cams_in}
    ladder = _ladder_sets(self_cal, cams_in)
    level = {c: 0 for c in cams_in}
    snap = _rig_snapshot(rec)
    rig0 = (rigv.R.copy(), rigv.t.copy()) if rigv is not None else None
    steps: list[str] = []
    first = True
    names = lambda v: ", ".join(v) or "nothing"  # noqa: E731
    while True:
        sets = {c: ladder[c][level[c]] for c in cams_in}
        if not first:
            _restore(rec, snap)
            if rig0 is not None:
                rigv.R, rigv.t = rig0[0].copy(), rig0[1].copy()
        first = False
        fa = final_adjustment(rec, xy, images, ctrl, self_calibrate=sets, rig=rigv, **kw)
        fa.cameras_after = {c: rec.cameras[c] for c in cams_in}
        fa.covariance_asked = bool(kw.get("compute_covariance", True))
        cam, why, check = _intrinsics_check(fa, start, sets, focal_known)
        if not why:
            return fa, sets, steps
        held = ""
        if check == "focal" and cam is not None:
            # the block does not determine the interior orientation: the rest of this camera's ladder holds focal
            # length and principal point at their start (FIXED_INTERIOR_LADDER)
            ladder[cam] = ladder[cam][: level[cam] + 1] + _fixed_interior_rungs(ladder[cam][0], ladder[cam][: level[cam] + 1])
            held = " (focal length and principal point held at their start from now on: the block does not determine them)"
        down = [c for c in ([cam] if cam is not None else cams_in) if level[c] + 1 < len(ladder[c])]
        if not down:
            steps.append(f"with the camera held fixed: {why}" if all(not v for v in sets.values()) else
                         f"with {', '.join(f'{start[c].name or c}: {names(sets[c])}' for c in cams_in)}: {why}")
            return fa, sets, steps
        for c in down:
            level[c] += 1
        steps.append(f"self-calibration of {', '.join(f'{start[c].name or c}: {names(sets[c])}' for c in down)} refused: {why}; "
                     f"adjusted again with {', '.join(f'{start[c].name or c}: ' + (', '.join(ladder[c][level[c]]) or 'held fixed') for c in down)}"
                     + held)


def _unregister(rec, images) -> None:
    """Drop the orientation of ``images`` (their block was rejected) and the points only they determined (in their
    block's frame, not the CRS's), keeping their status reasons."""
    images = np.asarray(images, np.int64)
    if not len(images):
        return
    tr = rec.tracks
    rec.registered[images] = False
    rec.component[images] = -1
    for i in images:
        rec.status[i].registered, rec.status[i].component = False, -1
    touched = np.unique(tr.track[np.isin(tr.image, images)])
    live = rec.obs_valid & rec.registered[tr.image]
    cnt = np.bincount(tr.track[live], minlength=len(rec.points))
    rec.points[touched[cnt[touched] < 2]] = np.nan


#: an image is added to a georeferenced block at its GNSS position (rotation-only resection) only when its GNSS σ
#: seen from the block's points is at most this angle (degrees): RTK on a UAV or a pole, not metre-level GNSS
GNSS_RESECTION_MAX_DEG = 1.0


def _extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw, opt, adjusted, rms, far):
    """Images the orientation could not add (too few tie points to the block for a resection) placed at their
    GNSS position and turned to the block's points (:func:`~thermogrammetry.sfm.reconstruction.register_with_known_centres`),
    then the block adjusted again with them. Kept when that adjustment converges with a reprojection RMS and a
    GNSS agreement no worse than the block's own and the added images' rotations have σ below 2°; otherwise ``rec``
    is restored. ``adjusted``: the block's ``(fa, cal_used, cal_steps)`` without them. Returns ``(images, fa,
    cal_used, cal_steps, notes)``: the block's own when nothing was added or kept.

    Measured on the 48-station synthetic building ring (seed 3, occluder at 7 m, RTK σ 3/5 cm), where the stations
    T47-T02 share 20-30 verified matches with their neighbours but too few oriented points for PnP (10): see
    benchmarks/README.md (survey_building.py).
    """
    from ..results import Termination
    from ..sfm.reconstruction import register_with_known_centres

    images = np.asarray(images, np.int64)
    fa, cal_used, cal_steps = adjusted
    same = (images, fa, cal_used, cal_steps, [])
    cand = np.nonzero(~rec.registered & np.all(np.isfinite(ctrl.gnss_xyz), axis=1))[0]
    if len(cand) == 0:
        return same
    # the block's typical camera-to-point distance: a GNSS σ that is more than GNSS_RESECTION_MAX_DEG there is too coarse
    tr = rec.tracks
    ob = np.nonzero(rec.obs_valid & np.isin(tr.image, images) & np.isfinite(rec.points[tr.track]).all(1))[0]
    if len(ob) == 0:
        return same
    ob = ob[:: max(1, len(ob) // 20000)]
    dist = float(np.median(np.linalg.norm(rec.points[tr.track[ob]] - rec.centers()[tr.image[ob]], axis=1)))
    sig = np.nanmax(ctrl.gnss_sigma[cand], axis=1)
    cand = cand[sig <= np.tan(np.radians(GNSS_RESECTION_MAX_DEG)) * dist]
    if len(cand) == 0:
        return same
    snap = _rig_snapshot(rec)
    added, _ = register_with_known_centres(rec, xy, images, ctrl.gnss_xyz, cand, options=opt.reconstruction)
    if len(added) == 0:
        _restore(rec, snap)
        return same
    both = np.concatenate([images, added])
    fa2, cal2, steps2 = _adjust_block(rec, xy, both, ctrl, self_cal, compute_covariance=len(both) <= 2500, **adjust_kw)
    release_free_heap()
    v = fa2.tie_residuals
    rms2 = _tie_rms(v)
    far2 = _gnss_far_share(rec, both, ctrl)
    rot = (np.asarray(fa2.rotation_std_deg, float)[added] if fa2.rotation_std_deg is not None
           else np.full((len(added), 3), np.nan))
    nm = ", ".join(names[i] for i in added)
    why = ""
    if not fa2.result.success or fa2.result.termination is Termination.MAX_ITERATIONS:
        why = f"the adjustment with them did not converge ({fa2.result.reason or fa2.result.termination.value})"
    elif {c: tuple(v) for c, v in cal2.items()} != {c: tuple(v) for c, v in cal_used.items()}:
        why = "the block's self-calibration would step down with them"
    elif not rms2 <= max(rms * 1.1, rms + 0.05):
        why = f"reprojection RMS {rms2:.2f} px with them ({rms:.2f} px without)"
    elif far2 > far:
        why = (f"{100 * far2:.0f} % of the centres beyond {GNSS_FLAG_SIGMA:g} σ of their GNSS with them "
               f"({100 * far:.0f} % without)")
    elif not np.all(np.nanmax(rot, axis=1) < 2.0):
        why = f"rotation σ up to {np.nanmax(rot):.1f}° for the added images"
    else:
        # each added image must fit as the block does: enough observations left, residuals like the block's
        from ..sfm.reconstruction import MIN_CENTRE_RESECTION_POINTS

        for i in added:
            vi = v[fa2.tie_obs_image == i] if len(v) else np.zeros((0, 2))
            ri = _tie_rms(vi)
            if len(vi) < MIN_CENTRE_RESECTION_POINTS or not ri <= max(2.0 * rms2, 1.0):
                why = f"{names[i]} keeps {len(vi)} tie observations at {ri:.2f} px RMS (the block {rms2:.2f} px)"
                break
    if why:
        _restore(rec, snap)
        return (*same[:4], [f"block {ci + 1}: {nm} placed at their GNSS positions and turned to the block's points, "
                            f"not kept: {why}"])
    return both, fa2, cal2, steps2, [f"block {ci + 1}: {len(added)} image(s) with too few tie points to the block for "
                                     f"a resection added at their GNSS positions (rotation from the directions to the "
                                     f"block's points, then the block adjusted again): {nm}"]


def _prune_gnss_contradicting(rec, pre, images, ctrl, names, ci, why):
    """Images of a block rejected for contradicting its GNSS that no similarity of the block (as the orientation
    left it, ``pre``) puts near their GNSS positions (:func:`~thermogrammetry.sfm.georef.gnss_consensus`).

    When there are such images and the rest (>= 4 images, >= half of the block) agree, ``rec`` is restored to
    ``pre``, those images are taken out of the block with their reason, and ``(kept images, notes)`` is returned;
    otherwise ``(None, [])`` and ``rec`` is left as it is.
    """
    from ..sfm.georef import gnss_consensus

    images = np.asarray(images, np.int64)
    C = -np.einsum("nji,nj->ni", pre["R"][images], pre["t"][images])
    cons = gnss_consensus(C, ctrl.gnss_xyz[images], ctrl.gnss_sigma[images])
    if cons is None:
        return None, []
    drop = ~cons.inliers
    n_keep = int((~drop).sum())
    if not drop.any() or n_keep < 4 or n_keep < 0.5 * len(images):
        return None, []
    _restore(rec, pre)
    for i, r in zip(images[drop], cons.residuals_m[drop]):
        rec.registered[i] = False
        rec.component[i] = -1
        st = rec.status[i]
        st.registered, st.component = False, -1
        dist = f"{r:.2f} m" if np.isfinite(r) else "an unknown distance (no GNSS)"
        st.reason = (f"left out of block {ci + 1}: after its orientation this image's centre is {dist} from its GNSS "
                     f"position where the other {n_keep} images agree with theirs within {cons.tolerance_m:.2f} m "
                     "(a wrong resection)")
    gone = ", ".join(names[i] for i in images[drop])
    return images[~drop], [f"block {ci + 1}: {why}; {int(drop.sum())} image(s) whose centres the block put "
                           f"{', '.join(f'{r:.2f}' for r in cons.residuals_m[drop])} m from their GNSS while the other "
                           f"{n_keep} agree within {cons.tolerance_m:.2f} m (wrong resections) left out and the block "
                           f"adjusted again: {gone}"]


def _restore(rec, snap) -> None:
    """Put ``rec`` back as :func:`_rig_snapshot` saw it."""
    rec.R[:], rec.t[:], rec.registered[:], rec.component[:] = snap["R"], snap["t"], snap["registered"], snap["component"]
    rec.points[:], rec.obs_valid[:] = snap["points"], snap["obs_valid"]
    rec.cameras[:] = snap["cameras"]
    for st, (r_, c_, w_) in zip(rec.status, snap["status"]):
        st.registered, st.component, st.reason = r_, c_, w_


def _rig_snapshot(rec) -> dict:
    """What attaching rig views and the final adjustment change in ``rec`` (to undo a refused rig)."""
    return {"R": rec.R.copy(), "t": rec.t.copy(), "registered": rec.registered.copy(), "component": rec.component.copy(),
            "points": rec.points.copy(), "obs_valid": rec.obs_valid.copy(), "cameras": list(rec.cameras),
            "status": [(s.registered, s.component, s.reason) for s in rec.status]}


def _rig_refuse(rec, snap, rigv, block_images, names, why, ci, S=None) -> np.ndarray:
    """Undo the rig views of a block; returns its images: the RGB block plus the thermal frames that were oriented
    on their own in the same component (they keep that orientation, moved by the block's datum similarity ``S``
    like the block). Other thermal partners: reason set."""
    _restore(rec, snap)
    block_images = np.asarray(block_images, np.int64)
    comp = int(rec.component[block_images[0]]) if len(block_images) else -1
    keep = []
    for s_, m_ in sorted(rigv.master.items()):
        if m_ not in set(block_images.tolist()):
            continue
        if rec.registered[s_] and int(rec.component[s_]) == comp:
            keep.append(s_)
        else:
            rec.status[s_].reason = (f"rig R*, t not estimated in block {ci + 1} ({why}); no orientation of its own "
                                     f"(partner {names[m_]})")
    if keep and S is not None:  # the block was moved to the datum without them (plan_rig_blocks took them out)
        k = np.asarray(keep, np.int64)
        Cn = S(rec.centers()[k])
        rec.R[k] = rec.R[k] @ S.R.T
        rec.t[k] = -np.einsum("nij,nj->ni", rec.R[k], Cn)
    return np.unique(np.concatenate([block_images, np.asarray(keep, np.int64)]))


def _rig_by_registration(project: ProjectStore, rec, rig, master: dict, names: list, comps: list, *,
                         thermal_camera_given: bool, xy, ctrl, self_cal, adjust_kw: dict) -> tuple:
    """R*, t by image registration where the block cannot estimate it from tie points (:mod:`..sfm.rigreg`).

    Runs when the rig file asks for an estimate and fewer than ``RIG_EST_MIN_FRAMES`` thermal images were
    oriented together with their RGB partners in the largest block that holds RGB partners (low-texture thermal
    frames: their ties do not reach the RGB block). The RGB images of that block are first adjusted on their own
    (self-calibrating, in the model frame: the registration measures the thermal camera against the RGB camera's
    rays, so these must be close to the final ones -- with the orientation's RGB focal length the thermal one came
    out 2.5 % off on the frescoes); the pairs are sampled in that state, ``rec`` is put back as the orientation left
    it (the final adjustment starts from there with its datum), and the pairs are registered on the edges both bands
    see; when that pre-adjustment does not converge below σ0 3 (a 12-frame nadir block without datum: σ0 518) the
    orientation's state is sampled instead. An accepted estimate is held fixed in the final adjustment (``RigFile.registered``), and so is the thermal camera, its focal length scaled by
    the estimated factor unless it was given (a few thermal ties of their own must not self-calibrate it: k1 = -1.4
    from 58 observations on the frescoes). A refused estimate changes nothing (the reason is in the notes and in
    ``survey.json`` ``rig.registration``). At most ``RigRegistrationOptions.max_pairs`` pairs, evenly over the block.

    Returns (rig to use, registration summary or None, notes, self-calibration to use).
    """
    from dataclasses import replace as dc_replace

    from ..geometry.rotations import axis_angle_from_matrix
    from ..sfm.rig import RIG_EST_MIN_FRAMES, _co_pairs, t_with_sigma_text
    from ..sfm.rigreg import RigRegistrationOptions, pair_samples, register_rig

    if not rig.estimate or not master:
        return rig, None, [], self_cal
    block = next((c for c in comps if any(m in set(np.asarray(c).tolist()) for m in master.values())), None)
    if block is None:
        return rig, None, [], self_cal
    co = _co_pairs(rec, master, block)
    if len(co) >= RIG_EST_MIN_FRAMES:
        return rig, None, [], self_cal
    t0 = time.perf_counter()
    inb = set(np.asarray(block).tolist())
    pairs_im = [(s, m) for s, m in sorted(master.items(), key=lambda x: x[1]) if m in inb and rec.registered[m]]
    if not pairs_im:
        return rig, None, [], self_cal
    rgb_block = np.array([i for i in np.asarray(block).tolist() if i not in master], np.int64)
    snap = _rig_snapshot(rec)
    fa0, _, steps0 = _adjust_block(rec, xy, rgb_block, ctrl, self_cal, georeferenced=False, compute_covariance=False,
                                   **adjust_kw)
    pre = [f"rig: the {len(rgb_block)} RGB image(s) adjusted on their own before the registration "
           f"({fa0.result.termination.value}, σ0 {float(fa0.result.sigma0):.2f})"] + [f"rig: {x}" for x in steps0]
    release_free_heap()
    if fa0.result.termination.value != "converged" or not (float(fa0.result.sigma0) < 3.0):
        # (a 12-frame nadir block without datum: stopped at its iteration limit with σ0 518) sampled in the
        # orientation's state instead
        _restore(rec, snap)
        pre.append("rig: the registration samples the orientation's state instead (that adjustment did not converge "
                   "to a σ0 below 3)")
    tcam_k = int(rec.image_camera[pairs_im[0][0]])
    tcam = rec.cameras[tcam_k]
    obs_img, obs_trk = rec.tracks.image, rec.tracks.track
    usable_obs = rec.obs_valid & np.isfinite(rec.points).all(axis=1)[obs_trk]
    samples, why = [], []
    reg_opt = RigRegistrationOptions(estimate_focal=not thermal_camera_given)
    if len(pairs_im) > reg_opt.max_pairs:  # evenly over the block (in image order)
        pick = np.unique(np.round(np.linspace(0, len(pairs_im) - 1, reg_opt.max_pairs)).astype(int))
        pre.append(f"rig: {len(pick)} of {len(pairs_im)} pairs registered (evenly over the block)")
        pairs_im = [pairs_im[k] for k in pick]
    for s_, m_ in pairs_im:
        sel = usable_obs & (obs_img == m_)
        Xc = rec.points[obs_trk[sel]] @ rec.R[m_].T + rec.t[m_]
        p_, w_ = pair_samples(names[m_], _read_frame(project, names[m_]), _read_frame(project, names[s_]),
                              rec.cameras[int(rec.image_camera[m_])], tcam, Xc)
        samples.append(p_)
        if w_:
            why.append(w_)
    # the block goes back to the orientation's state (the final adjustment starts from it, with its datum)
    _restore(rec, snap)
    del snap
    reg = register_rig(samples, tcam, R0=rig.R, options=reg_opt)
    summary = {**reg.summary(), "seconds": round(time.perf_counter() - t0, 2), "skipped_pairs": why,
               "ncc": {k: round(v, 4) for k, v in reg.ncc.items()},
               "pair_offsets_deg": {k: round(v, 3) for k, v in reg.pair_offsets_deg.items()}}
    head = (f"rig: {len(co)} thermal image(s) oriented with their RGB partners (< {RIG_EST_MIN_FRAMES}): R*, t by "
            f"image registration of {len(pairs_im)} pair(s)")
    if not reg.success:
        return rig, summary, pre + [f"{head} refused: {reg.reason}"], self_cal
    notes = pre + [f"{head}: {len(reg.pairs_used)} pair(s) agree, rotation {np.degrees(np.linalg.norm(axis_angle_from_matrix(reg.R))):.2f} deg "
             f"(σ {', '.join(f'{x:.3f}' for x in reg.rotation_std_deg)} deg, spread {reg.spread_deg:.2f} deg), "
             f"thermal focal x {reg.focal_scale:.4f}"
             + (f", t {t_with_sigma_text(reg.t, reg.translation_std)} model units"
                if reg.t_determined else ", t held (pairs at one depth)")
             + "; held fixed in the adjustment"]
    if not thermal_camera_given and abs(reg.focal_scale - 1.0) > 1e-9:
        K = tcam.K
        rec.cameras[tcam_k] = tcam.with_params(_scaled_focal_params(tcam, reg.focal_scale))
        notes.append(f"rig: thermal focal length {np.sqrt(K[0, 0] * K[1, 1]):.1f} -> "
                     f"{np.sqrt(K[0, 0] * K[1, 1]) * reg.focal_scale:.1f} px from the registration, held fixed")
    n_cams = len(rec.cameras)
    self_cal = {k: (() if k == tcam_k else (self_cal.get(k, ()) if isinstance(self_cal, dict) else self_cal))
                for k in range(n_cams)}
    return dc_replace(rig, R=reg.R, t=reg.t, estimate=False, registered=summary), summary, notes, self_cal


def _scaled_focal_params(camera, scale: float) -> np.ndarray:
    """The camera's parameter vector with its focal length(s) multiplied by ``scale``."""
    p = np.array(camera.params, float)
    for k, n in enumerate(camera.param_names):
        if n in ("fx", "fy", "c_mm"):
            p[k] *= scale
    return p


def _rig_scale_local(rec, images, rig, master, rigv) -> list:
    """A block without datum and a rig with a given baseline: scale the model to metres by the baseline of the
    thermal images oriented together with their partners (else the adjustment's rig constraint sets it)."""
    from ..geometry import Similarity
    from ..sfm.georef import apply_similarity
    from ..sfm.rig import _co_pairs, relative_from_poses

    if rig.R is None or np.linalg.norm(rig.t) <= 0:
        return []
    co = _co_pairs(rec, master, images)
    if not co:
        return ["rig: no datum and no thermal image oriented with its partner: the scale comes from the rig baseline "
                "in the adjustment alone"]
    _, t_m, _ = relative_from_poses(rec.R[[m for _, m in co]], rec.t[[m for _, m in co]], rec.R[[s for s, _ in co]],
                                    rec.t[[s for s, _ in co]])
    if not np.linalg.norm(t_m) > 0:
        return []
    k = float(np.linalg.norm(rig.t) / np.linalg.norm(t_m))
    apply_similarity(rec, images, Similarity(k, np.eye(3), np.zeros(3)))
    return [f"rig: no datum: the model is scaled by {k:.4g} so that {len(co)} co-oriented pair(s) match the rig baseline "
            f"{np.linalg.norm(rig.t):.3f} m"]


#: an oriented image whose attitude in its file differs from its adjusted rotation by more than this (degrees) beyond
#: the block's common difference is named (``survey.json`` ``attitude.flagged``): gimbal attitudes are good to ~1-2°
#: (the M3T flight: 0.4-2.2°), a wrong resection is tens of degrees off. A common difference above it (every image) is
#: a convention or mounting the files do not describe, said once, not blamed on each image
ATTITUDE_FLAG_DEG = 10.0


def _attitude_check(rec, fa_all, ctrl, names, status) -> dict:
    """Adjusted rotations of the georeferenced blocks against the camera attitudes in the files (DJI gimbal angles):
    per image ``attitude_deviation_deg`` in ``status``; summary n, median, RMS, max (degrees), ``mean_deg`` the mean of
    the world-frame rotation vectors of ``R_adjᵀ R_att`` (CRS x, y, z ~ east, north, up: a gimbal's common tilt), and
    the images whose ``R_adjᵀ R_att`` is more than :data:`ATTITUDE_FLAG_DEG` from the block's mean rotation (chordal
    mean), with that distance. Empty without attitudes."""
    from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle, mean_rotation
    from ..sfm.georef import attitude_images

    rows = []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        for i in attitude_images(ctrl, images):
            # world-frame rotation E with R_att = R_adj E
            w = np.degrees(axis_angle_from_matrix(rec.R[i].T @ ctrl.attitude[i]))
            status[i]["attitude_deviation_deg"] = float(np.linalg.norm(w))
            rows.append((int(i), w))
    if not rows:
        return {}
    W = np.array([w for _, w in rows])
    dev = np.linalg.norm(W, axis=1)
    E = matrix_from_axis_angle(np.radians(W))
    rel = np.degrees(np.linalg.norm(axis_angle_from_matrix(E @ mean_rotation(E).T), axis=1))
    return {"n": len(rows), "median_deg": float(np.median(dev)), "rms_deg": float(np.sqrt(np.mean(dev**2))),
            "max_deg": float(dev.max()), "mean_deg": [float(x) for x in W.mean(axis=0)],
            "flagged": [{"image": names[i], "deviation_deg": float(dev[k]), "from_common_deg": float(rel[k])}
                        for k, (i, w) in enumerate(rows) if rel[k] > ATTITUDE_FLAG_DEG]}


def _write_outputs(project, inputs, rec, fa_all, names, crs, ctrl, checks, gcp_errors, gcp_rejected, notes, results, extra=None,
                   rig_only=None):
    from ..io.oriented import OrientedCameras, OrientedImage
    from ..sfm.georef import axis_statistics, gnss_misfit

    cam_ids = project.read_json("work/reconstruction.json")["camera_ids"]
    images_out = []
    per_image = []
    rms_all = []
    tie_by_image: dict[int, np.ndarray] = {}
    oriented_idx = []
    for ci, images, fa, datum, geo in fa_all:
        for i in images:
            oriented_idx.append(int(i))
        v = fa.tie_residuals
        for i in images:
            tie_by_image[int(i)] = v[fa.tie_obs_image == i]
        rms_all.append(v)
        for i in images:
            im = inputs["images"][i]
            images_out.append(OrientedImage(names[i], cam_ids[rec.image_camera[i]], rec.R[i], rec.t[i],
                                            center_std=fa.center_std[i], rotation_std_deg=fa.rotation_std_deg[i],
                                            frame=f"frames/{names[i]}.tif", source=im["source"], unit=im["unit"],
                                            sensor=im["sensor"]))
    cams = {cid: rec.cameras[k] for k, cid in enumerate(cam_ids) if any(o.camera_id == cid for o in images_out)}
    # the camera's standard deviations from the last solve of the largest block
    if fa_all:
        fa0 = fa_all[0][2]
        if fa0.result.camera_std:
            for b, (cid) in enumerate(sorted({o.camera_id for o in images_out if True}, key=cam_ids.index)):
                k = cam_ids.index(cid)
                pb_cams = fa0.result.problem.cameras
                # cameras in the problem are added in sorted camera index order
                order = sorted({int(rec.image_camera[i]) for i in fa_all[0][1]})
                if k in order:
                    std = fa0.result.camera_std[order.index(k)]
                    cams[cid] = rec.cameras[k].replace(param_std=np.where(np.isfinite(std), std, np.nan))
    oc = OrientedCameras(cams, images_out, crs=crs,
                         notes="" if crs else "local frame (no GNSS/GCP datum): arbitrary origin, orientation and scale") if images_out else None
    V = np.concatenate(rms_all) if rms_all else np.zeros((0, 2))
    rms = float(np.sqrt(np.mean(np.sum(V**2, axis=1)))) if len(V) else None
    n_total = len(names) + len(inputs["failed"])
    status = []
    for i, n in enumerate(names):
        s = rec.status[i]
        ok = i in set(oriented_idx)
        v = tie_by_image.get(i)
        status.append({"name": n, "oriented": ok, "block": int(rec.component[i]) + 1 if ok else None,
                       "reason": ((rig_only or {}).get(i, "") if ok else (s.reason or "not oriented")),
                       "tie_points": int(len(v)) if v is not None else 0,
                       "rms_px": float(np.sqrt(np.mean(np.sum(v**2, 1)))) if v is not None and len(v) else None,
                       "unit": inputs["images"][i]["unit"], "sensor": inputs["images"][i]["sensor"],
                       **({"rig_only": True} if ok and i in (rig_only or {}) else {})})
    # GNSS misfit per image: adjusted antenna position − given GNSS position (a surveyor's check of every centre)
    gnss_d, flagged = [], []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        for i, (d, z) in sorted(gnss_misfit(rec, images, ctrl).items()):
            st = status[i]
            st["gnss_residual_m"] = [float(x) for x in d]
            st["gnss_residual_sigma"] = float(np.max(z))
            used = i not in fa.gnss_rejected
            if used:
                gnss_d.append(d)
            else:
                st["gnss_used"] = False
            if np.max(z) > GNSS_FLAG_SIGMA:
                flagged.append((i, d, float(np.max(z)), used))
    if flagged:
        if len(flagged) > max(3, 0.1 * len(gnss_d)):
            notes = notes + [f"{len(flagged)} of {len(gnss_d)} adjusted camera centres are more than {GNSS_FLAG_SIGMA:g} σ "
                             "from their GNSS positions (gnss_flagged): the GNSS σ given is too optimistic for this "
                             "flight, or the GNSS and the images do not belong together"]
        else:
            notes = notes + [f"{names[i]}: adjusted camera centre {np.linalg.norm(d):.3f} m from its GNSS position "
                             f"({z:.1f} σ{'' if used else '; that GNSS position was left out of the final adjustment'}): "
                             "its orientation (e.g. tie points on occluding edges or repeated structure) or its GNSS tag "
                             "is wrong; check it before using its products" for i, d, z, used in flagged]
    att_summary = _attitude_check(rec, fa_all, ctrl, names, status)
    if att_summary.get("median_deg", 0.0) > ATTITUDE_FLAG_DEG:
        notes = notes + [f"the camera attitudes in the files differ from the adjusted rotations by {att_summary['median_deg']:.1f}° "
                         "(median over the images): a convention or camera mounting the files do not describe, not a "
                         "fault of the orientation"]
    if att_summary.get("flagged"):
        notes = notes + [f"{f['image']}: adjusted rotation {f['from_common_deg']:.1f}° from the camera attitude in its file "
                         "beyond the block's common difference: its orientation (a wrong resection) or its attitude tag is "
                         "wrong; check it before using its products" for f in att_summary["flagged"]]
    for f in inputs["failed"]:
        status.append({"name": Path(f["file"]).name, "oriented": False, "block": None, "reason": f["reason"], "tie_points": 0,
                       "rms_px": None, "unit": None, "sensor": None})
    # sparse cloud of the exported blocks
    tr = rec.tracks
    used = np.zeros(len(names), bool)
    used[oriented_idx] = True
    obs_mask = rec.obs_valid & used[tr.image] & np.isfinite(rec.points[tr.track]).all(1)
    cnt = np.bincount(tr.track[obs_mask], minlength=len(rec.points))
    pts_ok = (cnt >= 2) & np.isfinite(rec.points).all(1)
    if oriented_idx and pts_ok.any():
        # points run away to near infinity (nearly parallel rays left after outlier removal) are not exported
        d = np.linalg.norm(rec.points[pts_ok] - rec.centers()[oriented_idx].mean(axis=0), axis=1)
        far = np.zeros(len(pts_ok), bool)
        far[np.nonzero(pts_ok)[0]] = d > 50.0 * max(float(np.median(d)), 1e-9)
        pts_ok &= ~far
    values, unit = _point_values(project, inputs, rec, names, oriented_idx, obs_mask)
    mult = cnt[pts_ok]
    units = sorted({inputs["images"][i]["unit"] for i in oriented_idx})
    summary = {
        "images_total": n_total,
        "images_oriented": int(len(oriented_idx)),
        "components": [int(len(images)) for ci, images, fa, datum, geo in fa_all],
        "reprojection_rms_px": rms,
        "gcps": axis_statistics(gcp_errors),
        "checkpoints": axis_statistics([c["error"] for c in checks if c.get("error") is not None]),
        "gnss": axis_statistics(gnss_d),
        "gnss_flagged": [{"image": names[i], "dx": float(d[0]), "dy": float(d[1]), "dz": float(d[2]), "sigma": z,
                          "used": used} for i, d, z, used in flagged],
        "attitude": att_summary,
        "crs": crs,
        "seconds": None,
        "georeferenced": bool(crs),
        "frame_units": units,
        "temperatures": units == ["K"],
        "points": int(pts_ok.sum()),
        "tie_point_multiplicity": {"mean": float(mult.mean()) if len(mult) else None,
                                   "histogram": np.bincount(mult).tolist() if len(mult) else []},
        "blocks": results,
        "images": status,
        "cameras": {cid: {"params": c.param_dict, "std": dict(zip(c.param_names, [None if not np.isfinite(x) else float(x)
                                                                                   for x in (c.param_std if c.param_std is not None else [np.nan] * len(c.param_names))]))}
                    for cid, c in cams.items()},
        "gcp_residuals": [{"id": ctrl.gcp_ids[g], "dx": float(e[0]), "dy": float(e[1]), "dz": float(e[2])}
                          for g, e in zip([g for *_, fa, datum, geo in fa_all for g in np.nonzero(fa.gcp_used)[0]], gcp_errors)],
        "gcp_rejected_measurements": gcp_rejected,
        "checkpoint_errors": [{"id": c["id"], "n_images": c["n_images"], "reason": c.get("reason", ""),
                               **({"dx": float(c["error"][0]), "dy": float(c["error"][1]), "dz": float(c["error"][2]),
                                   "sx": float(c["std"][0]), "sy": float(c["std"][1]), "sz": float(c["std"][2])}
                                  if c.get("error") is not None else {})} for c in checks],
        "failed_inputs": inputs["failed"],
        "notes": inputs.get("notes", []) + notes + sorted({im["note"] for im in inputs["images"] if im.get("note")}),
        **(extra or {}),
    }
    if oc is not None:
        project.write_text("cameras.json", json.dumps(oc.to_dict(), indent=1) + "\n")
        _write_colmap(project, oc, rec, names, oriented_idx, obs_mask, pts_ok, values)
        _write_clouds(project, rec.points[pts_ok], None if values is None else values[pts_ok], unit, mult, crs)
    project.write_json("survey.json", summary)
    return {"images_oriented": summary["images_oriented"], "components": summary["components"], "rms_px": rms, "crs": crs}


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


def _write_colmap(project, oc, rec, names, oriented_idx, obs_mask, pts_ok, values):
    from ..io.colmap import ColmapImage, ColmapPoints3D, colmap_camera_line
    from ..geometry.rotations import quaternion_from_matrix

    cam_keys = list(oc.cameras)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for k, cid in enumerate(cam_keys):
        cam = oc.cameras[cid]
        if cam.model.value == "photogrammetric":
            from ..camera import convert_camera

            cam = convert_camera(cam, "opencv").camera
        lines.append(colmap_camera_line(k + 1, cam))
    project.write_text("colmap/cameras.txt", "\n".join(lines) + "\n")
    tr = rec.tracks
    pid = np.full(len(rec.points), -1, np.int64)
    pid[pts_ok] = np.arange(1, int(pts_ok.sum()) + 1)
    name_to_idx = {n: i for i, n in enumerate(names)}
    # the tracks of points3D.txt as arrays (point id, image id, index in the image's POINTS2D), in the order the
    # images are written (12 B per observation instead of a string each)
    t_pid, t_img, t_n2d = [], [], []

    def image_lines():
        yield "# Image list with two lines of data per image:"
        yield "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
        yield "#   POINTS2D[] as (X, Y, POINT3D_ID)"
        # COLMAP text models hold coordinates as written: large CRS coordinates keep their precision in %.17g
        for k, o in enumerate(oc.images):
            i = name_to_idx[o.name]
            q = quaternion_from_matrix(o.R)
            sel = np.nonzero(obs_mask & (tr.image == i) & pts_ok[tr.track])[0]
            xy = _tie_xy(project, names[i])[tr.feature[sel]]
            yield " ".join([str(k + 1)] + [repr(float(v)) for v in q] + [repr(float(v)) for v in o.t]
                           + [str(cam_keys.index(o.camera_id) + 1), f"{o.name}.tif"])
            ps = pid[tr.track[sel]]
            yield " ".join(f"{x + 0.5!r} {y + 0.5!r} {int(t)}" for (x, y), t in zip(xy.tolist(), ps.tolist()))
            t_pid.append(ps.astype(np.int32))
            t_img.append(np.full(len(sel), k + 1, np.int32))
            t_n2d.append(np.arange(len(sel), dtype=np.int32))

    _write_lines(project, "colmap/images.txt", image_lines())
    P = rec.points[pts_ok]
    if values is not None:
        v = values[pts_ok]
        lo, hi = np.nanpercentile(v, [1, 99]) if np.isfinite(v).any() else (0.0, 1.0)
        g = np.clip((np.nan_to_num(v, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(int)
    else:
        g = np.full(len(P), 128)
    cat = (lambda a: np.concatenate(a) if a else np.zeros(0, np.int32))  # noqa: E731
    t_pid, t_img, t_n2d = cat(t_pid), cat(t_img), cat(t_n2d)
    order = np.argsort(t_pid, kind="stable")  # per point, its elements in the order they were written
    t_img, t_n2d = t_img[order], t_n2d[order]
    bounds = np.searchsorted(t_pid[order], np.arange(1, len(P) + 2))
    del order, t_pid

    def point_lines():
        yield "# 3D point list with one line of data per point:"
        yield "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
        for k in range(len(P)):
            a, b = bounds[k], bounds[k + 1]
            yield (f"{k + 1} {float(P[k, 0])!r} {float(P[k, 1])!r} {float(P[k, 2])!r} {int(g[k])} {int(g[k])} {int(g[k])} 0 "
                   + " ".join(f"{im} {n2d}" for im, n2d in zip(t_img[a:b].tolist(), t_n2d[a:b].tolist())))

    _write_lines(project, "colmap/points3D.txt", point_lines())


def _write_clouds(project, P, values, unit, mult, crs):
    """sparse.ply (plyfile) and sparse.las (laspy) with the mean frame value of each point."""
    import laspy
    from plyfile import PlyData, PlyElement

    name = "temperature_k" if unit == "K" else ("raw_counts" if unit == "counts" else None)
    dt = [("x", "f8"), ("y", "f8"), ("z", "f8"), ("views", "u2")] + ([(name, "f4")] if name and values is not None else [])
    arr = np.empty(len(P), dtype=dt)
    arr["x"], arr["y"], arr["z"] = P[:, 0], P[:, 1], P[:, 2]
    arr["views"] = np.minimum(mult, 65535)
    if name and values is not None:
        arr[name] = values.astype(np.float32)
    buf = io.BytesIO()
    PlyData([PlyElement.describe(arr, "vertex")], text=False,
            comments=[f"crs {crs or 'local'}", f"value {name or 'none'}"]).write(buf)
    project.write_bytes("sparse.ply", buf.getvalue())
    header = laspy.LasHeader(point_format=6, version="1.4")
    if name and values is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.float32,
                                                    description="kelvin" if unit == "K" else "raw sensor counts"))
    header.add_extra_dim(laspy.ExtraBytesParams(name="views", type=np.uint16, description="images observing the point"))
    if len(P):
        header.offsets = np.floor(P.min(axis=0))
    header.scales = np.array([0.001, 0.001, 0.001])
    if crs:
        from pyproj import CRS

        try:
            header.add_crs(CRS.from_user_input(crs))
        except Exception:  # noqa: BLE001 - a CRS laspy cannot encode is recorded in the report instead
            pass
    las = laspy.LasData(header)
    las.x, las.y, las.z = P[:, 0], P[:, 1], P[:, 2]
    if name and values is not None:
        setattr(las, name, values.astype(np.float32))
    las.views = np.minimum(mult, 65535).astype(np.uint16)
    buf = io.BytesIO()
    las.write(buf)
    project.write_bytes("sparse.las", buf.getvalue())


# ------------------------------------------------------------------------------------------------
# the workflow
# ------------------------------------------------------------------------------------------------
def _survey_camera(inp: SurveyInput):
    """The thermal camera held fixed: ``--camera``, else the rig file's thermal camera, else None."""
    cam = inp.camera
    if cam is None and inp.rig is not None and inp.rig.thermal_camera is not None:
        cam = inp.rig.thermal_camera  # the rig file's thermal camera, held fixed like --camera
    return cam


def _retry_low_texture(project: ProjectStore, opt: SurveyOptions, reports) -> bool:
    """True when ``georef`` ran and oriented nothing although ``orient`` gave blocks, with ``--low-texture auto``
    and the fallback not yet run (:func:`step_orient_low_texture` ``primary_rejected``)."""
    if opt.low_texture != "auto" or not reports or reports[-1].name != "georef" or not reports[-1].ok:
        return False
    if reports[-1].summary.get("images_oriented", 1) != 0 or not project.exists("work/low_texture.json"):
        return False
    orient = next((r for r in reports if r.name == "orient"), None)
    if orient is None or not orient.summary.get("oriented"):
        return False
    return not project.read_json("work/low_texture.json").get("ran", True)


def survey_steps(inp: SurveyInput, opt: SurveyOptions, progress: Callable | None = None):
    """The survey as a list of :class:`~thermogrammetry.pipeline.steps.Step`."""
    from .steps import Step

    cam = _survey_camera(inp)

    def prog(name):
        return (lambda k, n: progress(name, k, n)) if progress else None

    return [
        Step("inputs", lambda p: step_inputs(p, inp, opt, prog("inputs")), "decode inputs to frames/"),
        Step("features", lambda p: step_features(p, opt, prog("features")), "tie-point features per image"),
        Step("matching", lambda p: step_matching(p, opt, cam, prog("matching"), rig=inp.rig), "pairs, matching, geometric verification"),
        Step("orient", lambda p: step_orient_low_texture(p, opt, cam, prog("orient"), rgb_camera=getattr(inp.rig, "rgb_camera", None),
                                                         rig=inp.rig),
             "tracks and incremental orientation"),
        Step("georef", lambda p: step_georef(p, inp, opt, cam, prog("georef")), "georeferencing, final adjustment, exports"),
    ]


#: the survey's steps that run tasks on the local cluster (:func:`run_survey`), in their order
_TASK_STEPS = ("inputs", "features", "matching")


def _release_task_state() -> None:
    """After the steps that run tasks: this process's feature cache and matching work arrays, the cluster's and the tasks' freed objects
    (``gc``), and the heap's free pages (:func:`thermogrammetry._memory.release_free_heap`)."""
    import gc

    from ..sfm.matching import release_scratch

    _NPZ_CACHE.clear()
    release_scratch()
    gc.collect()
    release_free_heap()


@contextlib.contextmanager
def _local_cluster(opt: SurveyOptions):
    """One local dask cluster for every step that runs tasks (started once, not per step: ~2-4 s each).

    Yields the options with ``scheduler`` set to its address; unchanged when ``workers`` is 0 or a
    scheduler was given.
    """
    if opt.scheduler is not None or opt.workers == 0:
        yield opt
        return
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=int(opt.workers), threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=40)
    try:
        yield replace(opt, scheduler=cluster.scheduler_address)
    finally:
        cluster.close()


def run_survey(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions | None = None, *, progress: Callable | None = None,
               on_step: Callable | None = None):
    """Run every step; writes ``report.html`` and the step reports. Returns the list of StepReport."""
    from .steps import run_steps
    from .survey_report import write_survey_report

    opt = opt or SurveyOptions()
    t0 = time.perf_counter()
    # the steps that run tasks share one local cluster; it is closed before the orientation, whose memory then
    # starts without the cluster's state and what the earlier steps left in the process (a later step that runs
    # tasks again, e.g. the low-texture fallback of ``orient``, starts a cluster of its own)
    plain = survey_steps(inp, opt, progress)
    n_tasks = next((k for k, s in enumerate(plain) if s.name not in _TASK_STEPS), len(plain))
    with _local_cluster(opt) as opt_run:
        reports = run_steps(project, survey_steps(inp, opt_run, progress)[:n_tasks], on_step=on_step)
    _release_task_state()
    if all(r.ok for r in reports) and n_tasks < len(plain):
        reports += run_steps(project, plain[n_tasks:], on_step=on_step)
    if _retry_low_texture(project, opt, reports):
        # the final adjustment rejected every block of the primary orientation: the low-texture fallback, then the
        # georeferencing again on its blocks (steps of their own, reported beside the first ones)
        from .steps import Step

        cam = _survey_camera(inp)
        retry = [Step("orient_low_texture", lambda p: step_orient_low_texture(
                     p, opt, cam, (lambda k, n: progress("orient", k, n)) if progress else None,
                     rgb_camera=getattr(inp.rig, "rgb_camera", None), rig=inp.rig, primary_rejected=True),
                      "low-texture fallback after the final adjustment rejected the primary blocks")]
        reports += run_steps(project, retry, on_step=on_step)
        if reports[-1].ok:  # (also when the fallback was not kept: survey.json then says why)
            reports += run_steps(project, [Step("georef_low_texture", plain[-1].run, plain[-1].description)], on_step=on_step)
    if project.exists("survey.json"):
        s = project.read_json("survey.json")
        s["seconds"] = time.perf_counter() - t0
        s["steps"] = [{"name": r.name, "seconds": r.seconds, "status": r.status} for r in reports]
        project.write_json("survey.json", s)
        write_survey_report(project)
    return reports
