"""Synthetic thermal scenes, cameras and rendered images with exact ground truth.

Import-light on purpose: ``import thermogrammetry.synthetic`` loads nothing heavy; the
public names below are resolved lazily from their submodules. Other engineers' modules
(``testfield.py``, ``closerange.py``) sit beside these and are imported by their own path.

Submodules
----------
radiance   Planck band radiance, its inverse, Fresnel directional emissivity (local, exact).
sensor     thermal sensor effects: PSF blur, vignetting, temporal noise (NETD), fixed-pattern noise.
targets    calibration targets (circle grids, chessboards) rendered by supersampled inverse mapping.
coded_circle_grid_set  seed-003-like mask circle grid with ring-coded marks, whole and partial views.
surfaces   radiometrically exact rendering of a flat surface (temperature, emissivity, angle).
terrain    DSM with buildings, temperature and emissivity fields, heightfield ray casting.
survey     UAV survey: flight lines, thermal frames / video, GNSS, GCPs, ground truth in a project.
stereo     rectified thermal pairs with a known disparity field (dense-matching tests, benchmarks).
facade     facade mesh (OBJ) with a temperature field, thermal + RGB cameras on a rig.
lowtexture_facade  a hand-held thermal walk along a plain wall (weak smooth contrast, fixed pattern, NETD), truth.
"""

from __future__ import annotations

import importlib

_LAZY = {
    # targets
    "CircleGridTarget": "targets",
    "ChessboardTarget": "targets",
    "CodedCheckerboardTarget": "targets",
    "TargetTemperatures": "targets",
    "RenderedTarget": "targets",
    "render_target_image": "targets",
    # mask circle grid with seed 003's ring-coded marks
    "CodedCircleGridSet": "coded_circle_grid_set",
    "make_coded_circle_grid_set": "coded_circle_grid_set",
    # sensor
    "SensorEffects": "sensor",
    "apply_sensor_effects": "sensor",
    # radiance
    "band_radiance": "radiance",
    "band_temperature": "radiance",
    "fresnel_emissivity": "radiance",
    # surfaces
    "render_flat_surface": "surfaces",
    "FlatSurface": "surfaces",
    # terrain / survey
    "Terrain": "terrain",
    "make_terrain": "terrain",
    "SurveyConfig": "survey",
    "make_survey": "survey",
    "write_survey": "survey",
    # stereo
    "StereoPair": "stereo",
    "make_stereo_pair": "stereo",
    "FacadeConfig": "facade",
    "make_facade": "facade",
    "write_facade": "facade",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.synthetic' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{mod}", __name__), name)
