"""``thermogrammetry demo``: synthetic scenes with exact truth, every workflow run end to end, a report.

The demo is a list of **sections**. Each section makes (or reuses) a synthetic scene, runs a workflow
through the same library code paths as the real verb (the calibration workflow functions, the
close-range pipeline steps, the geometry kernels, the radiometry forward model ...) and returns
**rows**: what was achieved against the truth, each with a stated bound. :func:`demo_steps` turns the
sections into pipeline :class:`~thermogrammetry.pipeline.Step`\\ s; :func:`run_demo` runs them over a
project store, writes ``demo/<section>.json`` per section, ``reports/<section>.json`` (the step
report), ``demo/rows.json`` and ``report.html``; the CLI exits non-zero when any row misses its bound
or any section fails.

Adding a workflow to the demo
-----------------------------
Write a function ``run(project, options) -> list[DemoRow]`` (it may write files through ``project``
under its own prefix, e.g. ``"mysection/"``; keep it well under a minute) and register it::

    from thermogrammetry.pipeline.demo import DemoRow, DemoSection, register_section

    def _my_section(project, options):
        ...                                  # make a scene, run the workflow's library entry point
        return [DemoRow("my workflow", "point error (max)", achieved_mm, 5.0, "mm", note="...")]

    register_section(DemoSection("mine", "My workflow", _my_section))

Rows compare ``value`` with ``bound``: ``kind="max"`` passes when value ≤ bound (errors),
``kind="min"`` when value ≥ bound (counts, rates), ``kind="info"`` never fails (context numbers).
A section that raises is reported as a failed row. Sections are run in registration order;
``DemoOptions.sections`` selects a subset by name. Sections registered from other modules must be
imported before :func:`run_demo` (add the module to :data:`SECTION_MODULES`).

The built-in sections: ``render`` (geometric and radiometric exactness of the renderer),
``calibration-target`` (rendered circle-grid images → detection → self-calibration),
``calibration-testfield`` (seed 001 3D test field → self-calibration), ``closerange`` (seed 000
network → the close-range pipeline), ``survey`` (rendered UAV survey → resection / triangulation of
the ground-control markers, per-pixel temperature recovery), ``survey-bundle`` (the adjustment
engine on the survey's exact tie points + GNSS + GCPs, accuracy at check points), ``facade`` (facade mesh + rig → the
per-pixel correction over a mesh used by ``thermogrammetry correct --mesh``).
"""

from __future__ import annotations

import html
import importlib
import json
import math
import platform
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from ..errors import ConfigError
from .project import ProjectStore
from .steps import Step, StepReport, run_steps

__all__ = [
    "DemoRow",
    "DemoSection",
    "DemoOptions",
    "DemoResult",
    "DEMO_SECTIONS",
    "SECTION_MODULES",
    "all_sections",
    "register_section",
    "demo_steps",
    "run_demo",
    "report_html",
    "PrefixedProject",
    "match_to_truth",
]


@dataclass
class DemoRow:
    """One achieved-vs-truth figure with its bound."""

    section: str
    check: str
    value: float
    bound: float | None
    unit: str = ""
    kind: str = "max"  # "max": value <= bound passes; "min": value >= bound; "info": never fails
    note: str = ""

    @property
    def passed(self) -> bool:
        if self.kind == "info" or self.bound is None:
            return True
        v = float(self.value)
        if not math.isfinite(v):
            return False
        return v <= self.bound if self.kind == "max" else v >= self.bound

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d


@dataclass(frozen=True)
class DemoSection:
    name: str
    title: str
    run: Callable[[ProjectStore, "DemoOptions"], list[DemoRow]]


@dataclass(frozen=True)
class DemoOptions:
    """``seed``: every scene's seed offset; ``sections``: names to run (None = all); ``threads``."""

    seed: int = 0
    sections: tuple[str, ...] | None = None
    threads: int = 2


@dataclass
class DemoResult:
    rows: list[DemoRow]
    reports: list[StepReport]
    seconds: float

    @property
    def ok(self) -> bool:
        return all(r.passed for r in self.rows) and all(r.ok for r in self.reports)


#: the registry, in run order
DEMO_SECTIONS: list[DemoSection] = []

#: modules imported before a run so that their sections register themselves
SECTION_MODULES: tuple[str, ...] = ("thermogrammetry.pipeline.demo_survey",)


def register_section(section: DemoSection, *, replace: bool = True) -> None:
    """Add ``section`` to the registry (replacing one of the same name when ``replace``)."""
    for i, s in enumerate(DEMO_SECTIONS):
        if s.name == section.name:
            if not replace:
                raise ConfigError(f"demo section {section.name!r} is already registered")
            DEMO_SECTIONS[i] = section
            return
    DEMO_SECTIONS.append(section)


class PrefixedProject(ProjectStore):
    """A view of ``parent`` whose keys live under ``prefix`` (so a workflow writing ``inputs/...``
    can share a demo folder with the others)."""

    def __init__(self, parent: ProjectStore, prefix: str):
        self.parent = parent
        self.prefix = prefix.rstrip("/") + "/"

    def write_bytes(self, key, data):
        self.parent.write_bytes(self.prefix + key, data)

    def read_bytes(self, key):
        return self.parent.read_bytes(self.prefix + key)

    def exists(self, key):
        return self.parent.exists(self.prefix + key)

    def keys(self, prefix=""):
        n = len(self.prefix)
        return [k[n:] for k in self.parent.keys(self.prefix + prefix)]

    def describe(self, key):
        return self.parent.describe(self.prefix + key)

    def local_path(self, key):
        return self.parent.local_path(self.prefix + key)


# ------------------------------------------------------------------------------------------ helpers

def match_to_truth(points_px, truth_px) -> tuple[np.ndarray, np.ndarray]:
    """Pair detected points with true projections by position, not by index.

    A detector numbers a grid in its own canonical order; for grids that look the same turned by 180°
    (symmetric circle grids, chessboards with both inner counts odd or both even) that order can run
    from the other end than the target's own, so comparing ``detected[k]`` with ``truth[k]`` would
    report a grid-sized "error" for a perfect detection. Here each detected point is assigned to a
    distinct true point minimising the summed squared distance (Hungarian assignment, exact and
    one-to-one; for errors well below half the grid spacing it is the nearest-neighbour pairing).

    Parameters
    ----------
    points_px : (N, 2) detected points, pixels.
    truth_px : (M, 2) true projections, pixels, M >= N (NaN rows, e.g. points behind the camera,
        are never matched).

    Returns
    -------
    errors_px : (N,) distance of each detected point to its true point, pixels.
    truth_index : (N,) index into ``truth_px`` of the matched true point.
    """
    from scipy.optimize import linear_sum_assignment

    from .._validate import as_points

    det = as_points(points_px, "points_px", 2)
    tru = np.asarray(truth_px, dtype=np.float64)
    if tru.ndim != 2 or tru.shape[1] != 2:
        raise ConfigError(f"truth_px: expected an (M, 2) array of pixel positions, got shape {tru.shape}")
    ok = np.flatnonzero(np.all(np.isfinite(tru), axis=1))
    if len(ok) < len(det):
        raise ConfigError(f"truth_px: {len(ok)} finite true points for {len(det)} detections; expected at least as many")
    if len(det) == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    d2 = np.sum((det[:, None, :] - tru[ok][None, :, :]) ** 2, axis=2)
    r, c = linear_sum_assignment(d2)
    idx = np.empty(len(det), dtype=np.int64)
    idx[r] = ok[c]
    return np.linalg.norm(det - tru[idx], axis=1), idx


# ---------------------------------------------------------------------------------------- sections

def _section_render(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
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


def _section_calibration_target(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Rendered thermal images of a mask circle grid -> detection -> self-calibration (seed 003 route)."""
    from ..calibration.detect import detect
    from ..calibration.workflow import calibrate_detections
    from ..camera import Camera
    from ..geometry import Pose
    from ..io.tiff import encode_temperature_tiff
    from ..synthetic.targets import render_target_image
    from ..synthetic.testfield import (
        FLIR_A320_IMAGE_SIZE,
        FLIR_A320_PIXEL_PITCH_UM,
        flir_a320_table2_params,
    )
    from ..targets import CircleGridTarget

    sec = "calibration-target"
    truth = flir_a320_table2_params()
    cam = Camera("photogrammetric", FLIR_A320_IMAGE_SIZE, truth, pixel_pitch_um=FLIR_A320_PIXEL_PITCH_UM)
    # one description (mm) for rendering and detection
    tgt = CircleGridTarget(4, 11, 50.0, asymmetric=True, diameter_mm=30.0)
    ctr = tgt.object_points_m().mean(axis=0)
    n = 12
    dets, det_err = [], []
    for k in range(n):
        ang = 2 * np.pi * k / n
        tilt = np.deg2rad(22)
        dist = 2.3 + 0.2 * (k % 3)
        C = ctr + dist * np.array([np.sin(tilt) * np.cos(ang), np.sin(tilt) * np.sin(ang), -np.cos(tilt)])
        look = ctr + np.r_[0.1 * np.cos(3 * ang), 0.12 * np.sin(2 * ang), 0]
        roll = np.deg2rad(20 * np.sin(1.7 * k))
        pose = Pose.look_at(C, look, up=np.array([np.sin(roll), -np.cos(roll), 0.0]))
        r = render_target_image(cam, pose, tgt, supersample=4, psf_sigma_px=0.6, netd_k=0.05, fpn_k=0.03, vignetting=0.03,
                                seed=opt.seed * 100 + k, temperatures=(303.15, 296.15, 295.15))
        project.write_bytes(f"calibration-target/images/V{k:02d}.tif", encode_temperature_tiff(r.image_k)[0])
        d = detect(r.image_k, tgt, f"V{k:02d}")
        dets.append(d)
        if d.found:  # by position: the detector's canonical order need not be the target's own
            det_err.append(match_to_truth(d.points_px, r.points_px)[0])
    n_found = sum(1 for d in dets if d.found)
    from ..calibration.selfcal import SelfCalibrationOptions

    # the options `thermogrammetry calibrate --target circles` passes (k45/affinity off by default)
    run = calibrate_detections(dets, tgt.object_points_m(), target={"kind": "circles", "description": "asymmetric 4x11, 50 mm"},
                               pixel_pitch_um=FLIR_A320_PIXEL_PITCH_UM, focal_mm=18.0,
                               options=SelfCalibrationOptions(k45=False, affinity=False))
    res = run.result
    e = np.concatenate(det_err) if det_err else np.array([np.nan])
    rows = [
        DemoRow(sec, "views with the grid detected", n_found, 10, "of 12", kind="min", note="320x240, NETD 0.05 K, 7 K contrast, PSF 0.6 px"),
        DemoRow(sec, "detected circle centres vs true projections (RMS)", float(np.sqrt(np.mean(e**2))), 0.15, "px",
                note="bound: blob centroid noise ~0.05 px + residual perspective/PSF bias"),
    ]
    # a symmetric grid seen upside down: the detector numbers it from the other end (180° symmetry);
    # the comparison pairs points by position, so the figure is the detection error, not the order
    sym = CircleGridTarget(7, 4, 50.0, diameter_mm=20.0)
    c_sym = sym.object_points_m().mean(axis=0)
    pose = Pose.look_at(c_sym + np.array([0.25, 0.2, -2.0]), c_sym, up=(0, 1, 0))
    r = render_target_image(cam, pose, sym, supersample=4, psf_sigma_px=0.6, netd_k=0.05, seed=opt.seed * 100 + 99,
                            temperatures=(303.15, 296.15, 295.15))
    d = detect(r.image_k, sym, "symmetric-upside-down")
    if d.found:
        e_sym, idx = match_to_truth(d.points_px, r.points_px)
        flipped = int(np.sum(idx != np.asarray(d.object_ids)))
        rows.append(DemoRow(sec, "symmetric 7x4 grid upside down: detected vs true centres, matched by position (max)",
                            float(e_sym.max()), 0.3, "px",
                            note=f"{flipped} of {len(idx)} points numbered differently from the target's own order "
                                 "(180° symmetry); bound: ~0.05 px centroid noise + perspective bias of 20 mm holes"))
    else:
        rows.append(DemoRow(sec, f"symmetric 7x4 grid upside down: not detected ({d.reason})", float("nan"), 0.3, "px"))
    if not res.outcome.success:
        rows.append(DemoRow(sec, f"self-calibration ({res.outcome.termination.value}: {res.outcome.reason})", float("nan"), 0.0, ""))
        return rows
    cc = res.cameras[0]
    z = [(name, (cc.params[i] - truth[name]) / cc.std[i]) for i, name in enumerate(cc.param_dict) if cc.free[i] and cc.std[i] > 0]
    worst = max(z, key=lambda t: abs(t[1]))
    rows.append(DemoRow(sec, f"camera parameters: max |estimate - truth| / sigma over {len(z)} free ({worst[0]})", float(abs(worst[1])), 4.0,
                        "sigma", note=", ".join(f"{k} {v:+.1f}" for k, v in z)))
    rows.append(DemoRow(sec, "principal distance error (relative)", float(abs(cc.params[0] / truth["c_mm"] - 1.0)) * 100,
                        CALIB_C_BOUND_PCT, "%", note=f"{abs(cc.params[0] - truth['c_mm']) * 1000:.1f} um, sigma "
                                                     f"{cc.std[0] * 1000:.1f} um; absolute bound {CALIB_C_BOUND_PCT} % of c"))
    project.write_json("calibration-target/camera.json", {"params": cc.param_dict, "std": cc.std_dict, "truth": truth})
    return rows


def _section_calibration_testfield(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Seed 001: 77-point 3D test field, 4 positions x 4 rolls, 0.4 px noise -> self-calibration."""
    from ..io.testfield_csv import parse_control_csv, parse_measurements_csv
    from ..calibration.workflow import calibrate_testfield
    from ..synthetic.testfield import (
        FLIR_A320_IMAGE_SIZE,
        FLIR_A320_NOMINAL_FOCAL_MM,
        FLIR_A320_PIXEL_PITCH_UM,
        make_testfield,
    )

    sec = "calibration-testfield"
    tf = make_testfield(np.random.default_rng(1000 + opt.seed))
    project.write_text("calibration-testfield/control.csv", tf.control_csv())
    project.write_text("calibration-testfield/measurements.csv", tf.measurements_csv())
    ctl = parse_control_csv(project.read_text("calibration-testfield/control.csv"), "control.csv")
    meas = parse_measurements_csv(project.read_text("calibration-testfield/measurements.csv"), "measurements.csv")
    run = calibrate_testfield(ctl, meas, image_size=FLIR_A320_IMAGE_SIZE, pixel_pitch_um=FLIR_A320_PIXEL_PITCH_UM,
                              focal_mm=FLIR_A320_NOMINAL_FOCAL_MM)
    res = run.result
    if not res.outcome.success:
        return [DemoRow(sec, f"self-calibration ({res.outcome.termination.value}: {res.outcome.reason})", float("nan"), 0.0, "")]
    cc = res.cameras[0]
    truth = tf.truth.param_dict
    z = [(name, (cc.params[i] - truth[name]) / cc.std[i]) for i, name in enumerate(cc.param_dict) if cc.free[i] and cc.std[i] > 0]
    worst = max(z, key=lambda t: abs(t[1]))
    sx, sy = cc.sigma_xy_px
    return [
        DemoRow(sec, f"camera parameters: max |estimate - truth| / sigma over {len(z)} free ({worst[0]})", float(abs(worst[1])), 4.0,
                "sigma", note=", ".join(f"{k} {v:+.1f}" for k, v in z)),
        DemoRow(sec, "image residual sigma vs injected 0.4 px (relative error)", float(abs(0.5 * (sx + sy) / 0.4 - 1.0)), 0.1, "",
                note=f"sigma_x {sx:.3f} px, sigma_y {sy:.3f} px; {cc.n_observations} observations (the estimate's own "
                     f"relative sigma is ~{1 / np.sqrt(2 * max(cc.n_observations, 1)):.3f}, the bound allows ~5 of it)"),
    ]


def _section_closerange(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Seed 000: 6 control + 11 pass points, two optical cameras, one thermal -> the close-range pipeline."""
    import csv
    import io

    import tifffile

    from ..closerange.pipeline import closerange_steps, write_inputs
    from ..synthetic.closerange import (
        make_closerange_scene,
        measure,
        measurements_csv,
        render_thermal,
    )

    sec = "closerange"
    s = make_closerange_scene()
    rows_m = measure(s, 0.5, np.random.default_rng(2000 + opt.seed))
    img = render_thermal(s)
    sub = PrefixedProject(project, "closerange")
    write_inputs(sub, control_csv=s.control_csv(), measurements_csv=measurements_csv(rows_m), planes_csv=s.planes_csv(),
                 thermal=s.thermal, thermal_k=img["temperature_k"], thermal_unit="K")
    reps = run_steps(sub, closerange_steps())
    bad = [r for r in reps if not r.ok]
    if bad:
        return [DemoRow(sec, f"close-range pipeline step {bad[0].name} failed: {bad[0].error}", float("nan"), 0.0, "")]
    pts = {r["id"]: r for r in csv.DictReader(io.StringIO(sub.read_text("points.csv")))}
    d3, s3, zmax = [], [], 0.0
    for pid, X in s.passpoints.items():
        r = pts[pid]
        est = np.array([float(r[a]) for a in "XYZ"])
        sd = np.array([float(r["s" + a]) for a in "XYZ"])
        d3.append(np.linalg.norm(est - X))
        s3.append(np.linalg.norm(sd))
        zmax = max(zmax, float(np.max(np.abs(est - X) / sd)))
    d3 = np.array(d3) * 1000
    s3 = np.array(s3) * 1000
    cams = sub.read_json("orientation.json")["cameras"]  # closerange's orientation report
    th = cams[s.thermal]
    C = s.camera(s.thermal).pose.center
    dc = np.array([th["exterior"][k] for k in ("X0", "Y0", "Z0")]) - C
    sc = np.array([th["exterior_std"][k] for k in ("X0", "Y0", "Z0")])
    corr = tifffile.imread(io.BytesIO(sub.read_bytes("corrected.tif"))).astype(float)
    inside = img["inside"] & np.isfinite(corr)
    # away from face borders (the pixel footprint straddles two faces there)
    from scipy.ndimage import binary_erosion

    core = binary_erosion(inside, iterations=2) & np.isfinite(corr)
    dt = np.abs(corr[core] - img["true_temperature_k"][core])
    sig_k = tifffile.imread(io.BytesIO(sub.read_bytes("sigma_k.tif"))).astype(float)[core]
    z_t = dt / sig_k
    return [
        DemoRow(sec, "pass points: 3D error (max of 11)", float(d3.max()), float(round(4.5 * s3.max(), 2)), "mm",
                note=f"bound 4.5 x the largest propagated 3D sigma ({s3.max():.2f} mm); RMS {np.sqrt(np.mean(d3**2)):.2f} mm "
                     "at ~2 m with 0.5 px image noise (Sawicki et al. quote 1:4000 of the distance)"),
        DemoRow(sec, "pass points: max |error| / propagated sigma (33 coordinates)", zmax, 4.5, "sigma"),
        DemoRow(sec, "thermal camera centre (no control on the thermal image): max |error| / sigma", float(np.max(np.abs(dc) / sc)), 4.0,
                "sigma", note=f"error {np.linalg.norm(dc) * 1000:.1f} mm"),
        DemoRow(sec, "thermal camera centre: 3D error", float(np.linalg.norm(dc)) * 1000, CLOSERANGE_THERMAL_CENTRE_BOUND_MM, "mm",
                note=f"absolute bound {CLOSERANGE_THERMAL_CENTRE_BOUND_MM} mm at ~2 m (resection of a 320-px-wide thermal frame "
                     "from intersected pass points)"),
        DemoRow(sec, "angle-corrected temperature on the hot faces vs truth (median |error|)", float(np.median(dt)),
                float(round(3 * np.nanmedian(sig_k), 3)), "K",
                note=f"bound 3 x the median propagated sigma (sigma_k.tif, {np.nanmedian(sig_k):.3f} K); 95th percentile "
                     f"{np.percentile(dt, 95):.3f} K over {dt.size} px; cosine-law emissivity, Sawicki et al. eq. 8"),
        DemoRow(sec, "angle-corrected temperature: 95th percentile of |error| / propagated sigma", float(np.nanpercentile(z_t, 95)),
                3.0, "sigma", note="errors are correlated per face (one plane normal per face)"),
    ]


def _image_gsd_m(cfg) -> float:
    """Nadir ground sampling distance of the rendered frames at the planned height (m)."""
    return cfg.flight_height_m * cfg.pixel_pitch_um * 1e-6 / (cfg.focal_mm * 1e-3)


def _demo_survey_config(seed: int):
    from ..synthetic.sensor import SensorEffects
    from ..synthetic.survey import SurveyConfig
    from ..synthetic.terrain import TerrainConfig

    return SurveyConfig(
        terrain=TerrainConfig(width_m=120.0, height_m=90.0, n_buildings=5, n_trees=10, n_roads=1),
        image_size=(320, 256), focal_mm=12.5, flight_height_m=100.0, overlap=0.7, sidelap=0.6,
        n_gcp=12, n_check=8, marker_size_m=1.0, supersample=1, seed=seed,
        sensor=SensorEffects(psf_sigma_px=0.0, netd_k=0.05, fpn_k=0.03, vignetting=0.0, fpn_seed=11),
    )


def _section_survey(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Rendered UAV survey -> ground truth files; resection and triangulation of the GCP/check markers;
    per-pixel temperature recovery through the radiometry measurement equation."""
    import csv
    import io

    import tifffile

    from .. import radiometry as rad
    from ..geometry import resection, triangulate
    from ..synthetic.survey import make_survey, render_frame, write_survey

    sec = "survey"
    t0 = time.perf_counter()
    scene = make_survey(_demo_survey_config(opt.seed))
    summary = write_survey(project, scene, prefix="survey", threads=opt.threads, write_jpeg=True, n_tie_points=400)
    t_make = time.perf_counter() - t0
    rows = [DemoRow(sec, f"scene + {summary['frames']} frames 320x256 rendered and written", t_make, None, "s", kind="info",
                    note=f"{summary['gcp']} GCP, {summary['check']} check points, {summary['marker_observations']} marker observations")]
    # --- geometry: read back the files the way a user would
    obs = list(csv.DictReader(io.StringIO(project.read_text("survey/gcp_observations.csv"))))
    pts = {}
    for f in ("survey/gcp.csv", "survey/check.csv"):
        for r in csv.DictReader(io.StringIO(project.read_text(f))):
            pts[r["name"]] = np.array([float(r["easting"]), float(r["northing"]), float(r["height"])])
    cams = project.read_json("survey/cameras.json")
    from ..camera import Camera
    from ..geometry import Pose

    cam = Camera.from_dict(cams["camera"])
    poses = {c["name"]: Pose(np.array(c["R"]), np.array(c["t"])) for c in cams["images"]}
    rng = np.random.default_rng(3000 + opt.seed)
    sigma_px = 0.3
    noisy = {(r["image"], r["name"]): np.array([float(r["x_px"]), float(r["y_px"])]) + rng.normal(0, sigma_px, 2) for r in obs}
    zc, dcs = [], []
    by_img: dict[str, list[str]] = {}
    for (im, nm) in noisy:
        by_img.setdefault(im, []).append(nm)
    gnss = {r["name"]: np.array([float(r["easting"]), float(r["northing"]), float(r["height"])])
            for r in csv.DictReader(io.StringIO(project.read_text("survey/gnss.csv")))}
    from ..geometry.rotations import matrix_from_axis_angle

    import cv2

    eligible = sorted(im for im, names in by_img.items() if len(names) >= 4)
    failed_resections: list[str] = []
    covers: list[float] = []
    for im, names in by_img.items():
        if len(names) < 4:
            continue
        # start from the GNSS centre and an IMU-grade attitude (2 deg): with 4-5 nearly coplanar markers
        # an uninformed start can land on the mirror solution of planar resection (seen with seed 6)
        R0 = matrix_from_axis_angle(rng.normal(0.0, np.deg2rad(2.0), 3)) @ poses[im].R
        obs_xy = np.array([noisy[(im, n)] for n in names])
        res = resection(cam, np.array([pts[n] for n in names]), obs_xy, sigma_px=sigma_px,
                        initial_pose=Pose.from_center(R0, gnss[im]))
        if not res.success:
            failed_resections.append(f"{im} ({res.reason})")
            continue
        dc = res.center - poses[im].center
        zc.append(np.max(np.abs(dc) / res.center_std_prior))
        dcs.append(np.linalg.norm(dc))
        covers.append(float(cv2.contourArea(cv2.convexHull(obs_xy.astype(np.float32)))) / (cam.width * cam.height))
    if zc:
        rows.append(DemoRow(sec, f"resection of {len(zc)} frames from >= 4 markers (GNSS/IMU start): max |centre error| / sigma",
                            float(np.max(zc)), 4.5,
                            "sigma", note=f"centre error RMS {np.sqrt(np.mean(np.square(dcs))) * 1000:.0f} mm, {sigma_px} px marker noise"))
        strong = [d for d, c in zip(dcs, covers) if c >= RESECTION_MIN_COVER]
        if strong:
            rows.append(DemoRow(sec, f"resection: largest camera-centre error, {len(strong)} frames whose markers cover "
                                     f">= {RESECTION_MIN_COVER * 100:.0f} % of the frame", float(np.max(strong)),
                                round(RESECTION_CENTRE_BOUND_REL * scene.config.flight_height_m, 2), "m",
                                note=f"absolute bound {RESECTION_CENTRE_BOUND_REL * 100:.0f} % of the {scene.config.flight_height_m:.0f} m "
                                     "flight height: over flat ground and a 25 deg field of view, tilt and horizontal position "
                                     "trade against each other, so a single-image resection is weak (the bundle fixes it); "
                                     f"{len(dcs) - len(strong)} frames with less marker cover (weaker still) are in the sigma row"))
    rows.append(DemoRow(sec, f"frames resected, of the {len(eligible)} that see >= 4 markers", float(len(zc)),
                        float(max(len(eligible), 1)), "frames", kind="min",
                        note=("failed: " + "; ".join(failed_resections)) if failed_resections else
                        ("none failed" if eligible else "no frame sees >= 4 markers")))
    # triangulation of the check points from the true poses
    checks = [n for n in pts if n.startswith("CHK")]
    cfg_gsd_cm = _image_gsd_m(scene.config) * 100
    tri_err, tri_z = [], []
    for n in checks:
        ims = [im for (im, nm) in noisy if nm == n]
        if len(ims) < 2:
            continue
        tr = triangulate(cam, [poses[i] for i in ims], np.array([noisy[(i, n)] for i in ims])[:, None, :], sigma_px=sigma_px)
        e = tr.points[0] - pts[n]
        tri_err.append(np.linalg.norm(e))
        tri_z.append(np.max(np.abs(e) / tr.std[0]))
    if tri_err:
        rows.append(DemoRow(sec, f"check points triangulated from the true poses: max |error| / sigma ({len(tri_err)} points)",
                            float(np.max(tri_z)), 4.5, "sigma",
                            note=f"3D error max {np.max(tri_err) * 1000:.0f} mm, RMS {np.sqrt(np.mean(np.square(tri_err))) * 1000:.0f} mm; "
                                 f"GSD {cfg_gsd_cm:.1f} cm, {sigma_px} px marker noise"))
        rows.append(DemoRow(sec, "check points triangulated from the true poses: largest 3D error", float(np.max(tri_err)) * 100,
                            round(TRIANGULATION_BOUND_GSD * cfg_gsd_cm, 1), "cm",
                            note=f"absolute bound {TRIANGULATION_BOUND_GSD} GSD ({cfg_gsd_cm:.1f} cm): {sigma_px} px marker noise "
                                 "over a base/height of ~0.3 gives ~1 GSD in height"))
    # --- radiometry: recover the surface temperature of one frame per pixel from the written TIFF
    k = len(scene.frames) // 2
    fr = scene.frames[k]
    img = tifffile.imread(io.BytesIO(project.read_bytes(f"survey/images/{fr.name}.tif"))).astype(float)
    truth = render_frame(scene, k, with_truth=True, sensor=False)
    cfg = scene.config
    w, h = cam.image_size
    gy, gx = np.mgrid[0:h, 0:w]
    rays = cam.unproject(np.c_[gx.ravel(), gy.ravel()].astype(float))
    dist = truth["depth_m"].ravel() * np.linalg.norm(rays, axis=1)
    eps = truth["emissivity"].ravel()
    c = scene.curve
    pc = rad.PlanckConstants(c.r1, c.r2, c.b, c.f, c.o)
    good = np.isfinite(dist) & (eps >= 0.9)
    params = rad.MeasurementParams(emissivity=eps[good], reflected_temperature_k=cfg.sky_k, atmospheric_temperature_k=cfg.air_k,
                                   relative_humidity=cfg.relative_humidity, distance_m=dist[good])
    raw = rad.raw_from_temperature(img.ravel()[good], pc)
    t_rec = rad.object_temperature_from_raw(raw, pc, params)
    dt = t_rec - truth["surface_temperature_k"].ravel()[good]
    app = img.ravel()[good] - truth["surface_temperature_k"].ravel()[good]
    rows += [
        DemoRow(sec, f"surface temperature recovered per pixel (frame {fr.name}, eps >= 0.9): mean error", float(abs(dt.mean())), 0.02, "K",
                note=f"{good.sum()} px; uncorrected apparent temperature is off by {app.mean():+.2f} K on average"),
        DemoRow(sec, "surface temperature recovered per pixel: RMS error", float(np.sqrt(np.mean(dt**2))), 0.1, "K",
                note="bound: NETD 0.05 K + FPN 0.03 K, amplified by 1/(eps tau) <= 1.15"),
    ]
    return rows


def _section_survey_bundle(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Bundle adjustment of the survey (the adjustment engine): exact tie-point correspondences + 0.3 px
    noise, GNSS camera centres (3/5 cm), weighted GCPs (1 cm); the check points are free points.

    Poses start from the noisy GNSS centres and 0.5 deg rotation errors, points 0.3 m off. The
    adjustment runs in a local frame (CRS coordinates minus the scene origin): with the raw UTM values
    (~5.6e6 m) the engine reported the normal matrix as rank deficient (condition 7.7e12).
    """
    from ..adjustment import BundleProblem, SolverOptions, solve
    from ..geometry import Pose
    from ..geometry.rotations import matrix_from_axis_angle
    from ..synthetic.survey import make_survey, marker_observations, tie_points

    sec = "survey-bundle"
    scene = make_survey(_demo_survey_config(opt.seed))
    cfg = scene.config
    tp, tobs = tie_points(scene, 400)
    mobs = marker_observations(scene)
    rng = np.random.default_rng(4000 + opt.seed)
    sig_px = 0.3
    cnt: dict[str, int] = {}
    for _, nm, _, _ in tobs + mobs:
        cnt[nm] = cnt.get(nm, 0) + 1
    checks = {n: v for n, v in scene.checks.items() if cnt.get(n, 0) >= 2}
    mobs = [o for o in mobs if o[1] in scene.gcps or o[1] in checks]
    O = np.array([*scene.terrain.origin_en, 0.0])
    pb = BundleProblem()
    ic = pb.add_camera(scene.camera, fixed=True)
    vidx = {}
    for fr in scene.frames:
        R0 = matrix_from_axis_angle(rng.normal(0.0, np.deg2rad(0.5), 3)) @ fr.pose.R
        vidx[fr.name] = pb.add_pose(Pose.from_center(R0, fr.gnss_enh - O))
    views = np.array([vidx[f.name] for f in scene.frames])
    pb.add_gnss(views, np.array([f.gnss_enh for f in scene.frames]) - O,
                np.array([cfg.gnss_sigma_h_m, cfg.gnss_sigma_h_m, cfg.gnss_sigma_v_m]))
    names = list(tp) + list(scene.gcps) + list(checks)
    truth = np.array([tp.get(n, scene.gcps.get(n, checks.get(n))) for n in names]) - O
    pidx = pb.add_points(truth + rng.normal(0.0, 0.3, truth.shape))
    pi = {n: int(pidx[i]) for i, n in enumerate(names)}
    pb.add_control(np.array([pi[n] for n in scene.gcps]), np.array(list(scene.gcps.values())) - O, 0.01)
    by_view: dict[str, list] = {}
    for im, nm, x, y in tobs + mobs:
        by_view.setdefault(im, []).append((pi[nm], x, y))
    for im, lst in by_view.items():
        idx = np.array([a for a, _, _ in lst])
        xy = np.array([[x, y] for _, x, y in lst]) + rng.normal(0.0, sig_px, (len(lst), 2))
        pb.add_image_points(ic, vidx[im], idx, xy, sigma_px=sig_px)
    res = solve(pb, SolverOptions(compute_point_covariance=True))
    if not res.success or res.point_covariance is None:
        return [DemoRow(sec, f"bundle adjustment ({res.termination.value}: {res.reason})", float("nan"), 0.0, "")]
    ck = np.array([pi[n] for n in checks])
    gsd_cm = _image_gsd_m(cfg) * 100
    e = res.points[ck] - (np.array(list(checks.values())) - O)
    sd = np.sqrt(np.diagonal(res.point_covariance[ck], axis1=1, axis2=2))
    C = np.array([p.center for p in res.poses])
    dC = C - (np.array([f.pose.center for f in scene.frames]) - O)
    zc = np.abs(dC) / res.pose_std[:, 3:]
    rmse = np.sqrt(np.mean(e**2, axis=0)) * 1000
    dof = float(res.chi2.get("dof", res.redundancy) or 1)
    s_hi = float(np.sqrt(res.chi2["upper"] / dof)) if "upper" in res.chi2 else 1.15
    s_lo = float(np.sqrt(res.chi2["lower"] / dof)) if "lower" in res.chi2 else 0.85
    project.write_json("survey-bundle/summary.json", {
        "check_points": {n: {"error_m": e[k].tolist(), "sigma_m": sd[k].tolist()} for k, n in enumerate(checks)},
        "sigma0": res.sigma0, "chi2": res.chi2, "iterations": res.iterations,
        "n_tie_points": len(tp), "n_observations": len(tobs) + len(mobs)})
    return [
        DemoRow(sec, f"sigma0 (a priori 1; {res.redundancy} redundancy): upper chi2 bound", float(res.sigma0), round(s_hi, 4), "",
                note=f"{res.termination.value} in {res.iterations} iterations; chi2 test {'passed' if res.chi2.get('passed') else 'FAILED'}; "
                     f"{len(tp)} tie points, {len(tobs) + len(mobs)} image points"),
        DemoRow(sec, "sigma0: lower chi2 bound", float(res.sigma0), round(s_lo, 4), "", kind="min",
                note="the engine's two-sided chi2 test interval on sigma0"),
        DemoRow(sec, f"check points ({len(checks)}): max |error| / sigma", float(np.max(np.abs(e) / sd)), 4.5, "sigma",
                note=f"RMSE E/N/h {rmse[0]:.0f}/{rmse[1]:.0f}/{rmse[2]:.0f} mm (B/H 0.3: 70 % overlap)"),
        DemoRow(sec, f"camera centres ({len(C)}): max |error| / sigma", float(np.max(zc)), 4.5, "sigma",
                note="RMSE E/N/h " + "/".join(f"{v:.0f}" for v in np.sqrt(np.mean(dC**2, axis=0)) * 1000) + " mm"),
        DemoRow(sec, "check points: horizontal RMSE (E and N, the larger)", float(np.max(rmse[:2])) / 10 / gsd_cm,
                BUNDLE_CHECK_BOUND_GSD[0], "GSD", note=f"GSD {gsd_cm:.1f} cm; absolute bound {BUNDLE_CHECK_BOUND_GSD[0]} GSD "
                                                   "(issue 10's survey target)"),
        DemoRow(sec, "check points: height RMSE", float(rmse[2]) / 10 / gsd_cm, BUNDLE_CHECK_BOUND_GSD[1], "GSD",
                note=f"absolute bound {BUNDLE_CHECK_BOUND_GSD[1]} GSD (base/height 0.3)"),
        DemoRow(sec, "camera centres: largest 3D error", float(np.max(np.linalg.norm(dC, axis=1))), BUNDLE_CENTRE_BOUND_M, "m",
                note=f"absolute bound {BUNDLE_CENTRE_BOUND_M} m (GNSS sigma {cfg.gnss_sigma_h_m}/{cfg.gnss_sigma_v_m} m H/V, "
                     "tightened by the tie points)"),
    ]


def _section_facade(project: ProjectStore, opt: DemoOptions) -> list[DemoRow]:
    """Facade mesh + oriented thermal image -> per-pixel angle/emissivity/transmission correction over the
    mesh (the ``thermogrammetry correct --mesh`` code path) -> corrected vs true wall temperature."""
    import io

    import tifffile
    import trimesh

    from ..camera import Camera
    from ..products.correction import CorrectionConfig, correct_oriented_image
    from ..synthetic.facade import (
        FacadeConfig,
        make_facade,
        render_facade_thermal,
        write_facade,
    )
    from ..synthetic.radiance import fresnel_emissivity

    sec = "facade"
    eps0 = float(fresnel_emissivity(0.0, 1.5))  # plaster = a smooth n = 1.5 dielectric: the tool's Fresnel model
    scene = make_facade(FacadeConfig(plaster_emissivity=eps0, n_stations=2, rgb_size=(640, 426), rgb_focal_px=600.0, seed=opt.seed))
    write_facade(project, scene)
    cams = project.read_json("facade/cameras.json")
    cam = Camera.from_dict(cams["cameras"]["thermal"])
    st = cams["stations"][0]
    R, t = np.array(st["thermal"]["R"]), np.array(st["thermal"]["t"])
    mesh = trimesh.load(io.BytesIO(project.read_bytes("facade/mesh.obj")), file_type="obj", force="mesh", process=False)
    img = tifffile.imread(io.BytesIO(project.read_bytes(f"facade/thermal/{st['name']}.tif"))).astype(float)
    c = scene.config
    cfg = CorrectionConfig(ambient_c=c.sky_k - 273.15, emissivity="fresnel", refractive_index=1.5, transmission=True,
                           relative_humidity=c.relative_humidity, air_c=c.air_k - 273.15)
    cr = correct_oriented_image(img, cam, R, t, None, cfg, mesh=(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, int)))
    truth = render_facade_thermal(scene, 0, sensor=False, with_truth=True)
    m = cr.valid & (truth["material"] == "plaster")
    err = np.abs(cr.corrected_k[m] - truth["surface_temperature_k"][m])
    app = img[m] - truth["surface_temperature_k"][m]
    return [
        DemoRow(sec, "wall temperature after angle/emissivity/transmission correction over the mesh (median |error|)",
                float(np.median(err)), 0.1, "K", note=f"{m.sum()} wall px; uncorrected apparent temperature is off by "
                                                      f"{app.mean():+.2f} K on average; NETD 0.04 K, FPN 0.02 K"),
        DemoRow(sec, "same, 95th percentile", float(np.percentile(err, 95)), 0.3, "K",
                note="includes mixed pixels at window reveals (PSF 0.5 px)"),
        DemoRow(sec, "rig: thermal-from-RGB relative pose identical at every station", float(max(
            np.abs(np.array(s_["thermal"]["R"]) @ np.array(s_["rgb"]["R"]).T - np.array(cams["rig"]["cam_thermal_from_cam_rgb"]["R"])).max()
            for s_ in cams["stations"])), 1e-12, "", note="written cameras.json, Barazzetti et al. 2013 eq. 4-5"),
    ]


for _s in (
    DemoSection("render", "Renderer exactness", _section_render),
    DemoSection("calibration-target", "Calibration from rendered circle-grid images", _section_calibration_target),
    DemoSection("calibration-testfield", "Calibration on a 3D test field (Yastikli & Guler 2013)", _section_calibration_testfield),
    DemoSection("closerange", "Close-range network and angle correction (Sawicki, Stein & Więcek)", _section_closerange),
    DemoSection("survey", "UAV thermal survey, set-up of Khodaei et al. (starts from true correspondences)", _section_survey),
    DemoSection("survey-bundle", "UAV survey bundle adjustment with GNSS, GCPs and check points (starts from true tie points)", _section_survey_bundle),
    DemoSection("facade", "Facade mesh, thermal + RGB rig, correction over the mesh (Barazzetti et al. 2013)", _section_facade),
):
    register_section(_s)


# Absolute bounds of the demo rows (beside the sigma ones; issue 14): fixed numbers from the scene's design
# (noise, base/height, distance), each 1.5-3x the worst figure measured over seeds 0-3.
RESECTION_MIN_COVER = 0.25  # convex hull of the markers / frame area
RESECTION_CENTRE_BOUND_REL = 0.08  # of the flight height; measured 2.4-5.0 % (seeds 0-3)
TRIANGULATION_BOUND_GSD = 5.0  # a-priori sigma_Z of a 2-ray point at B/H 0.3 and 0.3 px: ~1.4 GSD; measured <= 2.8
BUNDLE_CHECK_BOUND_GSD = (0.5, 4.0)  # E/N: issue 10's target (measured <= 0.34); h: ~3x the 2-ray sigma_Z (measured <= 2.6)
BUNDLE_CENTRE_BOUND_M = 0.15  # GNSS 3/5 cm H/V priors tightened by the ties; measured <= 0.10
CLOSERANGE_THERMAL_CENTRE_BOUND_MM = 200.0  # ~2 m away, no control on the thermal frame; measured 34-113 mm
CALIB_C_BOUND_PCT = 0.5  # measured <= 0.15 %

# ------------------------------------------------------------------------------------------ running

def all_sections() -> list[DemoSection]:
    """Every registered section, in run order (the built-in ones and those of :data:`SECTION_MODULES`)."""
    for mod in SECTION_MODULES:
        importlib.import_module(mod)
    return list(DEMO_SECTIONS)


def _selected(options: DemoOptions) -> list[DemoSection]:
    all_sections()
    if options.sections is None:
        return list(DEMO_SECTIONS)
    names = {s.name: s for s in DEMO_SECTIONS}
    unknown = [n for n in options.sections if n not in names]
    if unknown:
        raise ConfigError(f"unknown demo section(s) {unknown}; valid: {list(names)}")
    return [names[n] for n in options.sections]


def demo_steps(options: DemoOptions | None = None) -> list[Step]:
    """One pipeline step per selected section; each writes ``demo/<name>.json`` with its rows."""
    opt = options or DemoOptions()
    steps = []
    for sec in _selected(opt):
        def run(project, sec=sec):
            rows = sec.run(project, opt)
            data = [r.to_dict() for r in rows]
            project.write_json(f"demo/{sec.name}.json", {"section": sec.name, "title": sec.title, "rows": data})
            return {"rows": data, "passed": all(r["passed"] for r in data)}

        steps.append(Step(sec.name, run, sec.title))
    return steps


def run_demo(project: ProjectStore, options: DemoOptions | None = None, *, on_section: Callable | None = None) -> DemoResult:
    """Run every selected section (a failing section does not stop the others) and write the report."""
    opt = options or DemoOptions()
    t0 = time.perf_counter()
    rows: list[DemoRow] = []
    reports: list[StepReport] = []
    for step in demo_steps(opt):
        rep = run_steps(project, [step])[0]
        reports.append(rep)
        if rep.ok:
            got = [DemoRow(**{k: v for k, v in d.items() if k != "passed"}) for d in rep.summary["rows"]]
        else:
            got = [DemoRow(step.name, f"section failed: {rep.error}", float("nan"), 0.0, "")]
        rows.extend(got)
        if on_section is not None:
            on_section(rep, got)
    res = DemoResult(rows, reports, time.perf_counter() - t0)
    project.write_json("demo/rows.json", {"ok": res.ok, "seconds": res.seconds, "rows": [r.to_dict() for r in rows]})
    project.write_text("report.html", report_html(res))
    return res


def _fmt(v) -> str:
    if v is None:
        return ""
    v = float(v)
    if not math.isfinite(v):
        return str(v)
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.4g}"
    return f"{v:.3e}"


def report_html(res: DemoResult) -> str:
    """Self-contained HTML page: environment, per-section timing, every row with its bound and verdict."""
    import os
    import sys

    from .. import __version__

    titles = {s.name: s.title for s in DEMO_SECTIONS}
    secs = {r.name: r for r in res.reports}
    out = [
        "<!doctype html><html><head><meta charset='utf-8'><title>thermogrammetry demo</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}td,th{border:1px solid #bbb;"
        "padding:4px 8px;text-align:left}td.n{text-align:right;font-family:monospace}.ok{color:#070}.bad{color:#b00;"
        "font-weight:bold}</style></head><body>",
        f"<h1>thermogrammetry {html.escape(__version__)} demo: achieved vs truth</h1>",
        f"<p>Verdict: <span class='{'ok' if res.ok else 'bad'}'>{'all checks within their bounds' if res.ok else 'SOME CHECKS FAILED'}"
        f"</span>. Total run time {res.seconds:.1f} s on {html.escape(platform.platform())}, Python "
        f"{html.escape(sys.version.split()[0])}, {os.cpu_count()} CPUs. Every scene is synthetic with exact ground truth "
        "(<code>thermogrammetry.synthetic</code>); bounds are stated per row.</p>",
    ]
    for name in dict.fromkeys(r.section for r in res.rows):
        rep = secs.get(name)
        out.append(f"<h2>{html.escape(titles.get(name, name))} <small>({html.escape(name)}, "
                   f"{rep.seconds:.1f} s)</small></h2>" if rep else f"<h2>{html.escape(name)}</h2>")
        out.append("<table><tr><th>check</th><th>achieved</th><th>bound</th><th>unit</th><th>verdict</th><th>note</th></tr>")
        for r in (r for r in res.rows if r.section == name):
            verdict = "info" if r.kind == "info" else ("pass" if r.passed else "FAIL")
            cls = "ok" if r.passed else "bad"
            rel = {"max": "&le; ", "min": "&ge; "}.get(r.kind, "")
            out.append(f"<tr><td>{html.escape(r.check)}</td><td class='n'>{_fmt(r.value)}</td><td class='n'>"
                       f"{rel + _fmt(r.bound) if r.bound is not None else ''}</td><td>{html.escape(r.unit)}</td>"
                       f"<td class='{cls}'>{verdict}</td><td>{html.escape(r.note)}</td></tr>")
        out.append("</table>")
        if rep is not None and not rep.ok:
            out.append(f"<pre>{html.escape(rep.summary.get('traceback', rep.error))}</pre>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def rows_json(res: DemoResult) -> str:
    return json.dumps([r.to_dict() for r in res.rows], indent=2)
