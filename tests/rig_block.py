"""Test helper: a synthetic RGB + thermal rig block (seed 002 §2.3) rendered over the UAV terrain scene.

The RGB camera flies the planned poses; the thermal camera follows through a known ``cam_thermal_from_cam_rgb``
(R_rel, t_rel). Thermal frames: float32 kelvin TIFFs with the scene's sensor noise (NETD 0.05 K, FPN, PSF);
RGB frames: 8-bit PNGs (``render_rgb_frame``, 2 DN noise). GNSS (σ 3 cm H, 5 cm V) only for the RGB images.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

RIG_ROT_DEG = (0.5, -0.4, 0.3)
RIG_BASE_M = (0.10, 0.02, -0.01)  # thermal projection centre in the RGB camera frame (seed 002's t)
MARKER_SIGMA_PX = 0.3


def truth_rig():
    from thermogrammetry.geometry import Pose
    from thermogrammetry.geometry.rotations import matrix_from_axis_angle

    R = matrix_from_axis_angle(np.deg2rad(RIG_ROT_DEG))
    b = np.array(RIG_BASE_M)
    return Pose(R, -R @ b)


def rgb_camera():
    from thermogrammetry.camera import Camera

    return Camera("opencv", (480, 384), dict(fx=570.0, fy=570.0, cx=241.5, cy=190.0, k1=-0.03), name="synthetic-rgb")


def write_rig_block(root, *, seed: int = 0, n_frames: int | None = None):
    """Render the block into ``root`` (thermal/, rgb/, gnss.csv); returns a dict with the truth."""
    import cv2

    from thermogrammetry.io.tiff import encode_temperature_tiff
    from thermogrammetry.synthetic.survey import make_survey, render_frame, render_rgb_frame
    from thermogrammetry.synthetic.survey_files import uav_thermal_config
    from thermogrammetry.synthetic.terrain import TerrainConfig

    root = Path(root)
    cfg = uav_thermal_config(seed=seed, terrain=TerrainConfig(width_m=80.0, height_m=64.0, n_buildings=3, n_trees=6, n_roads=1),
                             n_gcp=4, n_check=0, max_frames=n_frames)
    scene = make_survey(cfg)
    rig = truth_rig()
    th_frames = [replace(fr, name=f"{k:04d}_ir", pose=rig.compose(fr.pose)) for k, fr in enumerate(scene.frames)]
    th_scene = replace(scene, frames=th_frames)
    cam_rgb = rgb_camera()
    (root / "thermal").mkdir(parents=True, exist_ok=True)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    rows = ["image,X,Y,Z,sX,sY,sZ"]
    for k, fr in enumerate(scene.frames):
        data, _ = encode_temperature_tiff(render_frame(th_scene, k)["image_k"])
        (root / "thermal" / f"{k:04d}_ir.tif").write_bytes(data)
        img = render_rgb_frame(scene, fr.pose, cam_rgb, seed=k)
        cv2.imwrite(str(root / "rgb" / f"{k:04d}_rgb.png"), img[..., ::-1])
        g = fr.gnss_enh
        rows.append(f"{k:04d}_rgb,{g[0]:.4f},{g[1]:.4f},{g[2]:.4f},{cfg.gnss_sigma_h_m},{cfg.gnss_sigma_h_m},{cfg.gnss_sigma_v_m}")
    (root / "gnss.csv").write_text("\n".join(rows) + "\n")
    # GCPs (σ 1 cm) measured in the RGB images, and manual tie points measured in RGB and thermal images
    # (truth projected + N(0, MARKER_SIGMA_PX)); ids MT.. are in no coordinate file
    rng = np.random.default_rng([seed, 0x7A6])
    (root / "gcps.csv").write_text("id,X,Y,Z,sX,sY,sZ\n" + "".join(
        f"{k},{X[0]:.4f},{X[1]:.4f},{X[2]:.4f},0.01,0.01,0.01\n" for k, X in scene.gcps.items()))
    ter = scene.terrain
    # on locally flat ground or roofs (a point on a steep DSM edge has no well-defined height)
    cand = np.array([[0.3, 0.35], [0.55, 0.5], [0.7, 0.6], [0.45, 0.65], [0.35, 0.5], [0.6, 0.4], [0.4, 0.4], [0.65, 0.5],
                     [0.5, 0.35], [0.3, 0.6], [0.7, 0.45], [0.5, 0.6]]) * [ter.width_m, ter.height_m]
    flat = []
    for x, y in cand:
        off = np.array([[1.0, 0], [-1.0, 0], [0, 1.0], [0, -1.0], [0.7, 0.7], [-0.7, -0.7]])
        hz = ter.height_at(x + off[:, 0], y + off[:, 1])
        if np.ptp(np.append(hz, ter.height_at(np.array([x]), np.array([y])))) < 0.1:
            flat.append((x, y))
    xy_t = np.array(flat[:6])
    ties = {f"MT{k + 1:02d}": ter.to_world(np.array([x, y, ter.height_at(np.array([x]), np.array([y]))[0]]))
            for k, (x, y) in enumerate(xy_t)}
    meas = ["image,id,x,y"]
    n_meas = {}
    for pts, kinds in ((scene.gcps, ("rgb",)), (ties, ("rgb", "ir"))):
        for pid, X in pts.items():
            for kind in kinds:
                poses = {"rgb": [(f"{k:04d}_rgb", fr.pose) for k, fr in enumerate(scene.frames)],
                         "ir": [(f.name, f.pose) for f in th_frames]}[kind]
                cam = cam_rgb if kind == "rgb" else scene.camera
                w, h = cam.image_size
                for name, pose in poses:
                    Xc = pose.R @ X + pose.t
                    u = cam.project(Xc[None, :])[0] + rng.normal(0, MARKER_SIGMA_PX, 2)
                    if 10 <= u[0] <= w - 11 and 10 <= u[1] <= h - 11 and n_meas.get((pid, kind), 0) < 4:
                        meas.append(f"{name},{pid},{u[0]:.3f},{u[1]:.3f}")
                        n_meas[(pid, kind)] = n_meas.get((pid, kind), 0) + 1
    (root / "measurements.csv").write_text("\n".join(meas) + "\n")
    return {"scene": scene, "rig": rig, "ties": ties, "gcps": scene.gcps, "rgb_poses": {f"{k:04d}_rgb": fr.pose for k, fr in enumerate(scene.frames)},
            "thermal_poses": {f.name: f.pose for f in th_frames}, "thermal_camera": scene.camera, "rgb_camera": cam_rgb,
            # realised mean GNSS error of the block (its datum inherits it; σ only carries its expectation)
            "gnss_mean_error": np.mean([fr.gnss_enh - fr.pose.center for fr in scene.frames], axis=0),
            "epsg": scene.terrain.epsg, "root": root}


def blank_thermal_copy(root, name, blank):
    """A copy of ``root/thermal`` in ``root/name`` where the frames with index in ``blank`` are featureless (a uniform
    295 K): thermal images without any observation of their own (they can only be posed through the rig)."""
    import shutil

    from thermogrammetry.io.tiff import encode_temperature_tiff

    root = Path(root)
    dst = root / name
    dst.mkdir(exist_ok=True)
    for f in sorted((root / "thermal").glob("*.tif")):
        if int(f.stem[:4]) in set(blank):
            data, _ = encode_temperature_tiff(np.full((256, 320), 295.0, np.float32))
            (dst / f.name).write_bytes(data)
        else:
            shutil.copy(f, dst / f.name)
    return dst


def write_rig_json(path, *, rig=None, estimate=False, pairing=True, extra=None):
    d = {"format": "thermogrammetry/rig", "estimate": estimate}
    if rig is not None:
        d["cam_thermal_from_cam_rgb"] = {"R": rig.R.tolist(), "t": rig.t.tolist()}
    if pairing:
        d["pairing"] = {"rgb_suffix": "_rgb", "thermal_suffix": "_ir"}
    d.update(extra or {})
    Path(path).write_text(json.dumps(d, indent=1))
    return path
