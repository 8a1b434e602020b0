"""Demo section ``render``: the renderer's geometric and radiometric exactness."""

from __future__ import annotations

import numpy as np

from .demo_registry import DemoOptions, DemoRow
from .project import ProjectStore

__all__ = [
    "section_render",
]


def section_render(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Renderer exactness: point-target moments vs projection, flat surface vs radiometry forward model."""
    from .. import radiometry as rad
    from ..camera import Camera
    from ..geometry import Pose
    from ..synthetic.radiance import FlirCurve
    from ..synthetic.surfaces import FlatSurface, render_flat_surface
    from ..synthetic.targets import CircleGridTarget, render_target_image

    sec = "render"
    cam = Camera("opencv", (160, 120), dict(fx=220, fy=220, cx=81.3, cy=58.7, k1=-0.12, k2=0.03, p1=0.001, p2=-0.0005))
    tgt = CircleGridTarget(5, 4, 0.06, 0.014)
    ctr = tgt.object_points().mean(axis=0)
    pose = Pose(np.eye(3), -(ctr + np.array([0.01, -0.008, -0.5])))
    r = render_target_image(cam, pose, tgt, supersample=16, temperatures=(310.0, 295.0, 295.0))
    s = r.signal - r.signal.min()
    h, w = s.shape
    yy, xx = np.mgrid[0:h, 0:w]
    err = []
    for p in r.points_px:
        m = (np.abs(xx - p[0]) < 8) & (np.abs(yy - p[1]) < 8)
        wgt = s * m
        err.append(np.hypot((wgt * xx).sum() / wgt.sum() - p[0], (wgt * yy).sum() / wgt.sum() - p[1]))
    rows = [DemoRow(sec, "point targets: moment centre vs camera-model projection (max of 20)", float(np.max(err)), 0.02, "px",
                    note="noise-free, blur-free, 16x16 samples/px, OpenCV lens with up to 0.8 px distortion")]
    cam2 = Camera("opencv", (160, 120), dict(fx=180, fy=180, cx=80.2, cy=59.1, k1=-0.15, k2=0.02))
    pose2 = Pose.look_at(np.array([0.0, -3.0, 2.0]), np.zeros(3), up=(0, 0, 1))
    pc = rad.PlanckConstants(17096.453, 0.046642166, 1428.0, 1.0, -7340.0)
    eps = rad.FresnelEmissivity(1.6, normal_emissivity=0.93)
    params = rad.MeasurementParams(reflected_temperature_k=280.0, atmospheric_temperature_k=290.0, relative_humidity=0.6)

    def tau(d):
        t = rad.atmospheric_transmission(np.asarray(d) / 2.0, 290.0, 0.6, params.coefficients)
        return t * t

    rs = render_flat_surface(cam2, pose2, FlatSurface([0, 0, 0], [0, 0, 1], 318.15, eps), reflected_k=280.0, atmosphere_k=290.0,
                             transmission=tau, background_k=250.0, supersample=1, curve=FlirCurve.from_planck_constants(pc))
    on = np.isfinite(rs.angle_rad) & (rs.angle_rad < np.deg2rad(85))
    raw = rad.raw_for_directional(318.15, pc, params, rs.angle_rad[on], eps, distance_m=rs.distance_m[on], max_angle_deg=89.0)
    t_model = rad.temperature_from_raw(raw, pc)
    rows.append(DemoRow(sec, "flat surface (Fresnel emissivity, 35-75 deg, atmosphere): render vs radiometry forward model (max)",
                        float(np.max(np.abs(rs.image_k[on] - t_model))), 0.01, "K",
                        note=f"apparent temperatures span {t_model.min():.2f}-{t_model.max():.2f} K for a 318.15 K surface"))
    return rows
