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

The package: :mod:`.options` (what is given and how), :mod:`.store` (the artefacts' keys), one module per step
(:mod:`.inputs`, :mod:`.features`, :mod:`.matching`, :mod:`.orient` with :mod:`.lowtexture`, :mod:`.georef` with
:mod:`.controls` and :mod:`.outputs`), :mod:`.tasks` (dask), :mod:`.workflow` (:func:`survey_steps`,
:func:`run_survey`) and :mod:`.report`. The block policy (self-calibration ladder, block gates, GNSS pruning, rig
blocks) is in :mod:`thermogrammetry.sfm.selfcal_ladder`, :mod:`thermogrammetry.sfm.block_gates` and
:mod:`thermogrammetry.sfm.rig_block`. Every name of the former single module stays importable from here; a test
that patches one patches the module that looks it up (e.g. ``pipeline.survey.orient.AUTO_GLOBAL_BELOW``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace  # noqa: F401
from pathlib import Path  # noqa: F401
from typing import Any, Callable, Sequence  # noqa: F401

from ..._memory import release_free_heap  # noqa: F401
from ..._validate import config_keys  # noqa: F401
from ...enums import StrChoice  # noqa: F401
from ...errors import ConfigError, DataFileError, ThermogrammetryError, UnsupportedFormatError  # noqa: F401
from ...sfm.features import FeatureOptions  # noqa: F401
from ...sfm.globalsfm import GlobalOptions, reconstruct_global  # noqa: F401
from ...sfm.lsm import LsmOptions  # noqa: F401
from ...sfm.matching import MatchOptions  # noqa: F401
from ...sfm.reconstruction import ReconstructionOptions, restore_to, snapshot_of  # noqa: F401
from ...store import FolderProject, ProjectStore  # noqa: F401
from ...sfm.block_gates import (ATTITUDE_FLAG_DEG, BLOCK_GNSS_FAR_SHARE, BLOCK_RMS_GATE_PX, BLOCK_ROTATION_SIGMA_DEG,
                                GNSS_FLAG_SIGMA, GNSS_RESECTION_MAX_DEG, PRECISE_GNSS_SIGMA_M)
from ...sfm.block_gates import attitude_check as _attitude_check
from ...sfm.block_gates import block_rotation_sigma as _block_rotation_sigma
from ...sfm.block_gates import check_gnss_offset as _gnss_offset
from ...sfm.block_gates import extend_with_gnss
from ...sfm.block_gates import gnss_far_share as _gnss_far_share
from ...sfm.block_gates import precise_datum as _precise_datum
from ...sfm.block_gates import prune_gnss_contradicting as _prune_gnss_contradicting
from ...sfm.block_gates import tie_rms as _tie_rms
from ...sfm.block_gates import unregister_images as _unregister
from ...sfm.rig_block import rig_by_registration
from ...sfm.rig_block import rig_own_before as _rig_own_before
from ...sfm.rig_block import rig_refuse as _rig_refuse
from ...sfm.rig_block import rig_scale_local as _rig_scale_local
from ...sfm.rig_block import scaled_focal_params as _scaled_focal_params
from ...sfm.selfcal_ladder import FIXED_INTERIOR_LADDER, INTRINSICS_PLAUSIBLE, SELF_CALIBRATION_LADDER
from ...sfm.selfcal_ladder import adjust_block as _adjust_block
from ...sfm.selfcal_ladder import fixed_interior_rungs as _fixed_interior_rungs
from ...sfm.selfcal_ladder import intrinsics_check as _intrinsics_check
from ...sfm.selfcal_ladder import intrinsics_problem as _intrinsics_problem
from ...sfm.selfcal_ladder import ladder_sets as _ladder_sets
from .controls import _gnss_xyz, _read_manual_ties, _read_markers
from .features import (_evenly_spaced, _fixed_pattern, _initial_cameras, _is_thermal_rendering, _largest_size_group,
                       _masked_overlay, _overlay_keys, _overlay_mask, feature_task, step_features)
from .georef import _focal_from_exif, step_georef
from .inputs import (_PITCH_UM, RADIOMETRIC_JPEG_READERS, SEQUENCE_SUFFIXES, VIDEO_FALLBACK_INTERVAL_S, _attitudes,
                     _camera_guess, _decode, _decode_video, _geotag_dict, _name_list, _radiometric_jpeg, expand_inputs,
                     frame_values, step_inputs)
from .lowtexture import (_largest_thermal_block, _low_texture_check, _low_texture_orient_options,
                         _low_texture_self_calibration, _low_texture_sequence_used, _low_texture_unregister,
                         _low_texture_verdict, step_orient_low_texture)
from .matching import SEQUENCE_ORDER_RATIO, _sequence_order_ratio, _track_thermal_sequence, match_task, step_matching
from .options import (AUTO_GLOBAL_BELOW, IMAGE_SUFFIXES, LOW_TEXTURE_BA_GROWTH, LOW_TEXTURE_GUIDED_RADIUS_PX,
                      LOW_TEXTURE_MAX_PLANE_PARALLAX, LOW_TEXTURE_MIN_PLANAR_SHARE, LOW_TEXTURE_PATTERN_SIGMA_PX,
                      LOW_TEXTURE_SELF_CALIBRATION, LOW_TEXTURE_SHARE, MAPPERS, SELF_CALIBRATION, VIDEO_SUFFIXES, GnssMode,
                      SurveyInput, SurveyOptions)
from .orient import _auto_global, step_orient
from .outputs import _point_values, _write_clouds, _write_colmap, _write_outputs
from .store import (_NPZ_CACHE, _NPZ_CACHE_SIZE, _load_npz, _load_npz_cached, _load_reconstruction, _read_frame, _save_npz,
                    _tie_xy, _write_lines)
from .tasks import _TASK_STEPS, _TASKS_IN_FLIGHT, _local_cluster, _release_task_state, _run_tasks
from .workflow import SurveyRun, _retry_low_texture, _survey_camera, run_survey, survey_steps, survey_to_folder

__all__ = ["SurveyOptions", "SurveyInput", "survey_steps", "run_survey", "survey_to_folder", "SurveyRun", "VIDEO_SUFFIXES",
           "IMAGE_SUFFIXES"]


# the former private helpers whose signature changed when they moved (kept for old callers)
def _restore(rec, snap) -> None:
    """Put ``rec`` back as :func:`_rig_snapshot` saw it (:meth:`~thermogrammetry.sfm.reconstruction.Reconstruction.restore`)."""
    restore_to(rec, snap)


def _rig_snapshot(rec) -> dict:
    """:meth:`~thermogrammetry.sfm.reconstruction.Reconstruction.snapshot`."""
    return snapshot_of(rec)


def _extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw, opt, adjusted, rms, far):
    """:func:`~thermogrammetry.sfm.block_gates.extend_with_gnss` with the survey's options (``opt.reconstruction``)."""
    return extend_with_gnss(rec, xy, images, ctrl, names, ci, self_cal, adjust_kw, opt.reconstruction, adjusted, rms, far)


def _rig_by_registration(project: ProjectStore, rec, rig, master: dict, names: list, comps: list, **kw) -> tuple:
    """:func:`~thermogrammetry.sfm.rig_block.rig_by_registration` with the frames read from ``project``."""
    return rig_by_registration(lambda nm: _read_frame(project, nm), rec, rig, master, names, comps, **kw)
