"""The files a surveyor hands to ``thermogrammetry survey``, made from a synthetic survey.

:func:`write_user_files` writes, beside the rendered frames of :func:`~.survey.write_survey`, what a
user would have measured — never the truth itself:

==============================  ====================================================================
``user/gnss.csv``               image,X,Y,Z,sX,sY,sZ: the noisy GNSS positions of the scene (σ as simulated)
``user/gcps.csv``               id,X,Y,Z,sX,sY,sZ: surveyed GCPs (true coordinates + ``gcp_sigma_m`` noise)
``user/checkpoints.csv``        id,X,Y,Z: check points (true coordinates; they are the reference)
``user/gcp_measurements.csv``   image,id,x,y: marker centres measured in the frames (exact projection +
``user/check_measurements.csv`` Gaussian noise of ``marker_sigma_px``; OpenCV pixel convention)
==============================  ====================================================================
"""

from __future__ import annotations

import numpy as np

from .survey import SurveyScene, _csv_text, marker_observations

__all__ = ["UAV_THERMAL_TEST_CONFIG", "uav_thermal_config", "write_user_files"]


def uav_thermal_config(seed: int = 0, **overrides):
    """A small block shaped like a DJI M3T flight (61° field of view, 12 µm pitch) at half resolution:
    320x256 px, 4.55 mm, 50 m above ground (GSD 0.132 m), 80 % forward overlap, 60 % sidelap, 6 GCPs,
    8 check points — the set-up of Khodaei et al.'s survey (80/60 %) with today's most common thermal drone."""
    from .sensor import SensorEffects
    from .survey import SurveyConfig
    from .terrain import TerrainConfig

    kw = dict(terrain=TerrainConfig(width_m=130.0, height_m=100.0, n_buildings=5, n_trees=10, n_roads=1),
              image_size=(320, 256), focal_mm=4.55, pixel_pitch_um=12.0, flight_height_m=50.0, overlap=0.8, sidelap=0.6,
              n_gcp=6, n_check=8, marker_size_m=1.0, supersample=1, seed=seed,
              sensor=SensorEffects(psf_sigma_px=0.5, netd_k=0.05, fpn_k=0.03, vignetting=0.01, fpn_seed=11))
    kw.update(overrides)
    return SurveyConfig(**kw)


UAV_THERMAL_TEST_CONFIG = uav_thermal_config


def write_user_files(project, scene: SurveyScene, *, prefix: str = "survey", marker_sigma_px: float = 0.3,
                     gcp_sigma_m: float = 0.01, seed: int = 0) -> dict:
    """Write the user's files (see the module docstring) under ``prefix/user/``; returns counts."""
    rng = np.random.default_rng([seed, 0x05E5])
    cfg = scene.config
    p = prefix.rstrip("/") + "/user/"
    project.write_text(f"{p}gnss.csv", _csv_text(
        ["image", "X", "Y", "Z", "sX", "sY", "sZ"],
        [[f.name, f"{f.gnss_enh[0]:.4f}", f"{f.gnss_enh[1]:.4f}", f"{f.gnss_enh[2]:.4f}", cfg.gnss_sigma_h_m, cfg.gnss_sigma_h_m,
          cfg.gnss_sigma_v_m] for f in scene.frames]))
    project.write_text(f"{p}gcps.csv", _csv_text(
        ["id", "X", "Y", "Z", "sX", "sY", "sZ"],
        [[k, *(f"{c + rng.normal(0, gcp_sigma_m):.4f}" for c in v), gcp_sigma_m, gcp_sigma_m, gcp_sigma_m]
         for k, v in scene.gcps.items()]))
    project.write_text(f"{p}checkpoints.csv", _csv_text(["id", "X", "Y", "Z"],
                                                        [[k, *(f"{c:.4f}" for c in v)] for k, v in scene.checks.items()]))
    obs = marker_observations(scene)
    noisy = [(im, nm, x + rng.normal(0, marker_sigma_px), y + rng.normal(0, marker_sigma_px)) for im, nm, x, y in obs]
    for fname, ids in (("gcp_measurements.csv", scene.gcps), ("check_measurements.csv", scene.checks)):
        project.write_text(f"{p}{fname}", _csv_text(["image", "id", "x", "y"],
                                                    [[im, nm, f"{x:.4f}", f"{y:.4f}"] for im, nm, x, y in noisy if nm in ids]))
    return {"gcp_measurements": sum(1 for o in noisy if o[1] in scene.gcps),
            "check_measurements": sum(1 for o in noisy if o[1] in scene.checks)}
