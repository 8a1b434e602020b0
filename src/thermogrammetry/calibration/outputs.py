"""Calibration outputs: camera.json, calibration.json, report.html and exports, through a project store.

Keys written by :func:`write_outputs` (``store`` is a :class:`~thermogrammetry.pipeline.ProjectStore`)::

    camera.json                      first camera, thermogrammetry.camera format v1 (Camera.load), with std
    cameras/<k>_<name>.json          every camera, when more than one was calibrated
    calibration.json                 figures of the run (see calibration_dict)
    report.html                      self-contained report (figures embedded as base64 PNG)
    exports/opencv.yaml              cv::FileStorage YAML: camera_matrix, distortion_coefficients
    exports/opencv.json              the same as JSON, with the residuals and the covariance
    exports/colmap_cameras.txt       COLMAP cameras.txt (OPENCV / FULL_OPENCV; x_colmap = x + 0.5)
    exports/metashape.xml            Agisoft Metashape calibration XML
    exports/photogrammetric.json     opencv-model calibrations only: the photogrammetric camera (camera.json format)

camera.json is in the model that was estimated (``photogrammetric`` by default, or ``opencv``). Exports to
another model are least-squares conversions over the whole image; exports to the same model hold the
estimated parameters (:mod:`thermogrammetry.calibration.exports`). Their max and RMS residuals over the
whole frame and over the area the data covered are recorded in calibration.json ("exports") and the files.
Above :data:`WARN_RESIDUAL_PX` (0.1 px) a warning is given; above :data:`BAD_RESIDUAL_PX` (1 px) the files
are written as ``opencv_INACCURATE.yaml`` etc. (the names say so) with the warning inside.

To keep OUT consistent on failure, build everything into a :class:`~thermogrammetry.pipeline.MemoryProject`
first and copy it to the folder only when complete (:func:`flush`); every folder write is atomic.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
from typing import Any

import numpy as np

from ..camera.models import CameraModel
from ..store import ProjectStore
from .exports import BAD_RESIDUAL_PX, WARN_RESIDUAL_PX, camera_from_calibration  # noqa: F401 (public here as before)
from .exports import export_files as _exports
from .selfcal import CalibrationResult, CameraCalibration
from .workflow import CalibrationRun

__all__ = ["camera_from_calibration", "calibration_dict", "write_outputs", "flush", "report_html"]

FORMAT_NAME = "thermogrammetry.calibration"
FORMAT_VERSION = 1


def calibration_solver(r: CalibrationResult) -> str:
    if r.solution is not None and r.solution.layout.get("engine") == "adjustment":
        return "thermogrammetry.adjustment (sparse LM + Schur)"
    return "thermogrammetry.adjustment.dense.solve_dense (dense Gauss-Newton/LM)"


def _f(v):
    v = float(v)
    return v if np.isfinite(v) else None


def _camera_block(cc: CameraCalibration) -> dict[str, Any]:
    tests = {t.name: t for t in cc.tests}
    params = {}
    for i, (n, u) in enumerate(zip(cc.param_names, cc.param_units)):
        d = {"value": _f(cc.params[i]), "std": _f(cc.std[i]), "unit": u, "estimated": bool(cc.free[i])}
        if n in tests:
            d["t"] = _f(tests[n].t)
            d["significant"] = tests[n].significant
        params[n] = d
    params_px = {k: {"value": _f(v), "std": _f(s), "unit": u} for k, (v, s, u) in cc.parameters_px().items()}
    names, rho = cc.correlation()
    return {
        "name": cc.name,
        "model": cc.model.value,
        "image_size": list(cc.image_size),
        "pixel_pitch_um": list(cc.pixel_pitch_um),
        "parameters": params,
        "parameters_px": params_px,
        "sigma_x_px": _f(cc.sigma_xy_px[0]),
        "sigma_y_px": _f(cc.sigma_xy_px[1]),
        "sigma_x_um": _f(cc.sigma_xy_um[0]),
        "sigma_y_um": _f(cc.sigma_xy_um[1]),
        "rms_px": _f(cc.rms_px),
        "n_observations": cc.n_observations,
        "significance_test": {"test": "two-sided Student t, H0: parameter = 0",
                              "critical_t": _f(cc.tests[0].critical) if cc.tests else None},
        "correlation_warnings": [{"a": a, "b": b, "rho": _f(r)} for a, b, r in cc.correlation_warnings],
        "correlation": {"names": names, "matrix": [[_f(x) for x in row] for row in rho]},
    }


def _detector_of(run: CalibrationRun, image: str):
    """The detector variant that found the target in ``image`` (``run.meta["target"]["detections"]``,
    written by the target route), or None."""
    t = run.meta.get("target") if isinstance(run.meta, dict) else None
    d = (t or {}).get("detections", {}).get(image) if isinstance(t, dict) else None
    return (d.get("method") or None) if isinstance(d, dict) else None


def calibration_dict(run: CalibrationRun, exports: dict | None = None) -> dict[str, Any]:
    """Everything calibration.json holds. Top-level ``parameters`` / ``parameters_px`` are the first camera's."""
    r: CalibrationResult = run.result
    cams = [_camera_block(c) for c in r.cameras]
    d: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "termination": r.outcome.termination.value,
        "reason": r.outcome.reason,
        "rms_px": _f(r.rms_px),
        "rms_definition": "sqrt(mean(vx^2 + vy^2)) over image points (as cv2.calibrateCamera)",
        "sigma0": _f(r.sigma0),
        "dof": r.dof,
        "images_used": r.images_used,
        "images_rejected": r.images_rejected,
        "per_image": [
            {"image": v.name, "camera": v.camera, "used": v.used, "reason": v.reason, "n_points": v.n_points,
             "n_blunders": v.n_blunders, "rms_px": _f(v.rms_px), "detector": _detector_of(run, v.name)}
            for v in r.images
        ],
        "stage1": r.stage1,
        "warnings": list(r.warnings),
        "blunder_test": r.snooping_test,
        "blunders": r.blunders,
        "solver": calibration_solver(r),
        "run": run.meta,
    }
    if cams:
        for k in ("model", "parameters", "parameters_px", "sigma_x_px", "sigma_y_px", "sigma_x_um", "sigma_y_um",
                  "correlation_warnings"):
            d[k] = cams[0][k]
    d["cameras"] = cams
    if r.relative:
        d["relative_orientation"] = [
            {"camera": ro.camera, "reference_camera": ro.reference_camera, "R_cam_from_reference": ro.R.tolist(),
             "t_m": ro.t.tolist(), "std_rotation_rad": ro.std[:3].tolist(), "std_t_m": ro.std[3:].tolist(),
             "baseline_m": ro.baseline_m, "n_frames": ro.n_frames}
            for ro in r.relative
        ]
    if exports:
        d["exports"] = exports
    return d


# ---------------------------------------------------------------------------------------------- figures
def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _figures(run: CalibrationRun, ci: int) -> dict[str, str]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    r = run.result
    cc = r.cameras[ci]
    w, h = cc.image_size
    cam_of = np.array([r.images[k].camera for k in r.obs_image], dtype=int) if r.obs_image.size else np.zeros(0, int)
    m = cam_of == ci
    xy = r.obs_xy[m]
    v = r.residuals_px[m]
    figs = {}
    # residual vectors
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * h / w + 0.6))
    scale = 0.02 * w / max(np.sqrt(np.mean(np.sum(v**2, axis=1))) if v.size else 1.0, 1e-9)
    ax.quiver(xy[:, 0], xy[:, 1], v[:, 0], v[:, 1], angles="xy", scale_units="xy", scale=1.0 / scale, width=0.002, color="C3")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"residual vectors (x{scale:.0f}); RMS {cc.rms_px:.3f} px")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    figs["residuals"] = _png(fig)
    # coverage
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * h / w + 0.6))
    nb = (16, max(2, int(round(16 * h / w))))
    H, xe, ye = np.histogram2d(xy[:, 0], xy[:, 1], bins=nb, range=[[-0.5, w - 0.5], [-0.5, h - 0.5]])
    im = ax.imshow(H.T, extent=[-0.5, w - 0.5, h - 0.5, -0.5], cmap="viridis", interpolation="nearest")
    ax.plot(xy[:, 0], xy[:, 1], ".", ms=1.5, color="w", alpha=0.6)
    covered = float(np.mean(H > 0))
    ax.set_title(f"coverage: {xy.shape[0]} points, {100 * covered:.0f} % of {nb[0]}x{nb[1]} cells")
    fig.colorbar(im, ax=ax, shrink=0.8, label="observations per cell")
    figs["coverage"] = _png(fig)
    # distortion curve (radial and tangential along the image diagonal directions)
    if cc.model is CameraModel.OPENCV:
        fig = _distortion_opencv(cc, plt)
    else:
        p = cc.params
        px_mm = cc.pixel_pitch_um[0] * 1e-3
        rmax = float(np.hypot(w * cc.pixel_pitch_um[0], h * cc.pixel_pitch_um[1]) * 0.5e-3)
        rr = np.linspace(0, rmax, 200)
        K = p[3:8]
        dr = sum(K[i] * rr ** (2 * i + 3) for i in range(5))
        fig, ax = plt.subplots(figsize=(6.4, 3.8))
        ax.plot(rr, dr * 1e3, label="radial Δr (µm)")
        # 1-σ band by propagation through the K covariance
        J = np.stack([rr ** (2 * i + 3) for i in range(5)], axis=1)
        C = cc.covariance[3:8, 3:8]
        sd = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", J, C, J), 0))
        ax.fill_between(rr, (dr - sd) * 1e3, (dr + sd) * 1e3, alpha=0.3, label="±1σ")
        tang = np.sqrt(p[8] ** 2 + p[9] ** 2) * rr**2
        ax.plot(rr, tang * 1e3, "--", label="decentering |P| r² (µm)")
        ax.axhline(0, color="k", lw=0.5)
        sec = ax.secondary_yaxis("right", functions=(lambda y: y / (px_mm * 1e3), lambda y: y * px_mm * 1e3))
        sec.set_ylabel("px")
        ax.set_xlabel("radial distance r from the principal point [mm]")
        ax.set_ylabel("µm")
        ax.legend(fontsize=8)
        ax.set_title("distortion (correction form: Δr = K1 r³ + K2 r⁵ + …)")
    figs["distortion"] = _png(fig)
    # correlation heat map
    names, rho = cc.correlation()
    if names:
        fig, ax = plt.subplots(figsize=(5.2, 4.4))
        im = ax.imshow(rho, vmin=-1, vmax=1, cmap="RdBu_r")
        ax.set_xticks(range(len(names)), names, rotation=90)
        ax.set_yticks(range(len(names)), names)
        for a in range(len(names)):
            for b in range(len(names)):
                ax.text(b, a, f"{rho[a, b]:.2f}", ha="center", va="center", fontsize=6,
                        color="w" if abs(rho[a, b]) > 0.6 else "k")
        fig.colorbar(im, ax=ax, label="ρ")
        ax.set_title("correlation of the interior orientation")
        figs["correlation"] = _png(fig)
    # per-image RMS
    used = [im for im in r.images if im.used and im.camera == ci]
    if used:
        fig, ax = plt.subplots(figsize=(max(6.4, 0.18 * len(used)), 3.2))
        ax.bar(range(len(used)), [im.rms_px for im in used], color="C0")
        ax.set_xticks(range(len(used)), [im.name for im in used], rotation=90, fontsize=6)
        ax.set_ylabel("RMS [px]")
        ax.set_title("per-image RMS")
        figs["per_image"] = _png(fig)
    return figs


def _distortion_opencv(cc: CameraCalibration, plt):
    """Radial and decentering distortion of an opencv-model camera in px against the ideal radius in px (along x),
    with the 1σ band of the radial part from the covariance of k1..k6."""
    p = cc.param_dict
    w, h = cc.image_size
    f = p["fx"]
    from ..camera.models import opencv_unproject

    # the ideal radius of the frame's corners (their rays), else the distorted one
    rays = opencv_unproject(cc.params, np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]]))
    rn = np.hypot(rays[:, 0], rays[:, 1])
    rn_max = float(np.nanmax(rn)) if np.isfinite(rn).any() else \
        float(np.hypot(max(p["cx"], w - 1 - p["cx"]) / p["fx"], max(p["cy"], h - 1 - p["cy"]) / p["fy"]))
    rn = np.linspace(0, rn_max, 200)
    r2 = rn * rn
    num = 1 + r2 * (p["k1"] + r2 * (p["k2"] + r2 * p["k3"]))
    den = 1 + r2 * (p["k4"] + r2 * (p["k5"] + r2 * p["k6"]))
    dr = f * rn * (num / den - 1)
    # d dr / d (k1 k2 k3 k4 k5 k6)
    J = f * rn[:, None] * np.stack([r2 / den, r2**2 / den, r2**3 / den, -num * r2 / den**2, -num * r2**2 / den**2,
                                    -num * r2**3 / den**2], axis=1)
    ks = [cc.param_names.index(k) for k in ("k1", "k2", "k3", "k4", "k5", "k6")]
    C = np.where(cc.free[:, None] & cc.free[None, :], cc.covariance, 0.0)[np.ix_(ks, ks)]
    sd = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", J, C, J), 0))
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    ax.plot(f * rn, dr, label="radial Δr (px)")
    ax.fill_between(f * rn, dr - sd, dr + sd, alpha=0.3, label="±1σ")
    ax.plot(f * rn, f * np.hypot(p["p1"], p["p2"]) * r2, "--", label="decentering f |p| r² (px)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("ideal radial distance f·r from the principal point [px]")
    ax.set_ylabel("px")
    ax.legend(fontsize=8)
    ax.set_title("distortion (forward form: Δr = f r (k1 r² + k2 r⁴ + k3 r⁶), r = ideal normalised radius)")
    return fig


# ---------------------------------------------------------------------------------------------- HTML
def _sci(value: float, std: float) -> tuple[str, str, str]:
    """Seed 001 Table 2 style: value and std scaled by a common 10^e (e from the std)."""
    if not np.isfinite(std) or std <= 0:
        return f"{value:.6g}", "—", ""
    e = int(np.floor(np.log10(std)))
    if -2 <= e <= 1:
        return f"{value:.4f}", f"{std:.4f}", ""
    s = 10.0**e
    return f"{value / s:.4f}", f"{std / s:.4f}", f"× 10<sup>{e}</sup>"


_LABEL = {"c_mm": "Focal length, c (mm)", "x0_mm": "Principal point x<sub>0</sub> (mm)", "y0_mm": "Principal point y<sub>0</sub> (mm)",
          "K1": "Radial distortion K<sub>1</sub>", "K2": "Radial distortion K<sub>2</sub>", "K3": "Radial distortion K<sub>3</sub>",
          "K4": "Radial distortion K<sub>4</sub>", "K5": "Radial distortion K<sub>5</sub>",
          "P1": "Tangential distortion P<sub>1</sub>", "P2": "Tangential distortion P<sub>2</sub>",
          "B1": "Affinity B<sub>1</sub>", "B2": "Shear B<sub>2</sub>",
          "fx": "Focal length f<sub>x</sub> (px)", "fy": "Focal length f<sub>y</sub> (px)",
          "cx": "Principal point c<sub>x</sub> (px)", "cy": "Principal point c<sub>y</sub> (px)", "skew": "Skew (px)",
          **{f"k{i}": f"Radial distortion k<sub>{i}</sub>" for i in range(1, 7)},
          "p1": "Tangential distortion p<sub>1</sub>", "p2": "Tangential distortion p<sub>2</sub>"}

_MODEL_TEXT = {CameraModel.PHOTOGRAMMETRIC: "the correction-form (photogrammetric) model, Brown (1971) / Fraser (1997)",
               CameraModel.OPENCV: "OpenCV's forward-form model (as cv2.calibrateCamera), Brown (1971) / Bradski (2000)"}

_CSS = """body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}td.l{text-align:left}
.warn{color:#a40}.bad{color:#b00}img{max-width:100%}h2{border-bottom:1px solid #ccc}"""


def report_html(run: CalibrationRun, exports: dict | None = None) -> str:
    """The self-contained HTML report (tables like seed 001 Tables 2 and 4, figures)."""
    r = run.result
    e = html.escape
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>thermogrammetry calibration</title><style>{_CSS}</style></head><body>",
           "<h1>Camera calibration report</h1>"]
    meta = run.meta
    out.append(f"<p>Route: <b>{e(str(meta.get('route', '')))}</b>. Termination: <b>{e(r.outcome.termination.value)}</b> "
               f"({e(r.outcome.reason)}). σ0 = {r.sigma0:.4f} (a-priori σ of a coordinate = 1 unless given), "
               f"redundancy {r.dof}, RMS {r.rms_px:.4f} px. Blunder test: {e(r.snooping_test)}. "
               f"Solver: {e(calibration_solver(r))} with {_MODEL_TEXT[r.cameras[0].model if r.cameras else CameraModel.PHOTOGRAMMETRIC]}.</p>")
    for wtext in r.warnings:
        out.append(f"<p class='warn'>Warning: {e(wtext)}</p>")
    if meta.get("pixel_pitch_assumed"):
        out.append(f"<p class='warn'>Pixel pitch not given: {meta['pixel_pitch_um'][0]} µm assumed. Values in mm scale with "
                   "the pitch; the values in pixels do not.</p>")
    if r.stage1:
        s1 = r.stage1
        out.append(f"<p>Stage 1 (nominal c = {', '.join(f'{c:.4f}' for c in s1.get('c_mm', []))} mm, principal point at the centre, "
                   f"no distortion): RMS {s1.get('rms_px', float('nan')):.3f} px, {s1.get('n_blunders', 0)} gross errors removed "
                   "(re-admitted for stage 2 when below 10 σ under the full model and re-tested there).</p>")
    figs_all = {}
    for ci, cc in enumerate(r.cameras):
        out.append(f"<h2>Camera {ci + 1}: {e(cc.name)} ({cc.image_size[0]}×{cc.image_size[1]} px, pitch {cc.pixel_pitch_um[0]:g} µm)</h2>")
        out.append("<h3>Interior orientation and additional parameters (layout of Yastikli &amp; Guler 2013, Table 2)</h3>")
        out.append("<table><tr><th>Additional parameters</th><th>Parameter</th><th>Standard deviation</th><th>scale</th>"
                   "<th>t</th><th>significant</th><th>in pixels</th></tr>")
        tests = {t.name: t for t in cc.tests}
        ppx = cc.parameters_px()
        pxmap = {"c_mm": "fx", "x0_mm": "cx", "y0_mm": "cy"}
        for i, n in enumerate(cc.param_names):
            if not cc.free[i]:
                continue
            v, s, sc = _sci(cc.params[i], cc.std[i])
            t = tests.get(n)
            pk = pxmap.get(n, n)
            pv, ps, pu = ppx[pk]
            sig = "" if t is None else ("yes" if t.significant else "<span class='warn'>no</span>")
            out.append(f"<tr><td class='l'>{_LABEL[n]}</td><td>{v}</td><td>{s}</td><td>{sc}</td>"
                       f"<td>{'' if t is None else f'{t.t:.2f}'}</td><td>{sig}</td><td>{pk} = {pv:.6g} ± {ps:.3g} {e(pu)}</td></tr>")
        out.append("</table>")
        if cc.tests:
            out.append(f"<p>Significance: two-sided Student t test of H0 “parameter = 0”, critical t = {cc.tests[0].critical:.3f}.</p>")
        if cc.correlation_warnings:
            out.append("<p class='warn'>High correlations (|ρ| &gt; 0.9): " + ", ".join(
                f"{a}–{b} ρ = {rho:+.3f}" for a, b, rho in cc.correlation_warnings) + "</p>")
        sx, sy = cc.sigma_xy_px
        ux, uy = cc.sigma_xy_um
        out.append("<h3>Standard deviation of the measured image coordinates (layout of Yastikli &amp; Guler 2013, Table 4)</h3>")
        out.append("<table><tr><th>Camera</th><th>σ<sub>x</sub> (mm)</th><th>σ<sub>y</sub> (mm)</th><th>σ<sub>x</sub> (µm)</th>"
                   f"<th>σ<sub>y</sub> (µm)</th><th>σ<sub>x</sub> (px)</th><th>σ<sub>y</sub> (px)</th></tr><tr><td class='l'>{e(cc.name)}</td>"
                   f"<td>{ux * 1e-3:.5f}</td><td>{uy * 1e-3:.5f}</td><td>{ux:.2f}</td><td>{uy:.2f}</td><td>{sx:.3f}</td><td>{sy:.3f}</td></tr></table>")
        out.append("<p>σ<sub>x</sub> = sqrt(Σ v<sub>x</sub>² / Σ r<sub>x</sub>) with the redundancy numbers r of the x coordinates "
                   f"({cc.n_observations} image points).</p>")
        figs = _figures(run, ci)
        figs_all[ci] = figs
        for key, title in (("residuals", "Residual vectors"), ("distortion", "Distortion curve"),
                           ("correlation", "Correlation heat map"), ("coverage", "Coverage of the image by observations"),
                           ("per_image", "Per-image RMS")):
            if key in figs:
                out.append(f"<h3>{title}</h3><img alt='{key}' src='data:image/png;base64,{figs[key]}'>")
    if r.relative:
        out.append("<h2>Relative orientation (rig)</h2><table><tr><th>camera</th><th>reference</th><th>t (m)</th><th>σt (mm)</th>"
                   "<th>rotation σ (mrad)</th><th>baseline (m)</th><th>frames</th></tr>")
        for ro in r.relative:
            out.append(f"<tr><td>{ro.camera}</td><td>{ro.reference_camera}</td><td>{np.array2string(ro.t, precision=4)}</td>"
                       f"<td>{np.array2string(ro.std[3:] * 1e3, precision=2)}</td><td>{np.array2string(ro.std[:3] * 1e3, precision=3)}</td>"
                       f"<td>{ro.baseline_m:.4f}</td><td>{ro.n_frames}</td></tr>")
        out.append("</table>")
    tgt = run.meta.get("target") if isinstance(run.meta, dict) else None
    cb = tgt.get("centre_bias") if isinstance(tgt, dict) else None
    if cb:
        out.append(f"<h2>Circle-centre bias</h2><p>{e(cb.get('method', ''))}</p>")
        if cb.get("rounds"):
            out.append(f"<p>largest bias {cb['max_bias_px']:.3f} px; per round: "
                       + "; ".join(f"round {h['round']}: RMS {h['rms_px']:.4f} px"
                                   + (f", bias change {h['bias_change_px']:.4f} px" if h.get("bias_change_px") is not None else "")
                                   for h in cb["rounds"]) + "</p>")
    show_det = any(_detector_of(run, v.name) for v in r.images)
    out.append("<h2>Images</h2><table><tr><th>image</th><th>camera</th><th>used</th><th>points</th><th>blunders</th><th>RMS (px)</th>"
               + ("<th>detector</th>" if show_det else "") + "<th>reason</th></tr>")
    for v in r.images:
        out.append(f"<tr><td class='l'>{e(v.name)}</td><td>{v.camera + 1}</td><td>{'yes' if v.used else '<span class=bad>no</span>'}</td>"
                   f"<td>{v.n_points}</td><td>{v.n_blunders}</td><td>{'' if not np.isfinite(v.rms_px) else f'{v.rms_px:.3f}'}</td>"
                   + (f"<td class='l'>{e(_detector_of(run, v.name) or '')}</td>" if show_det else "")
                   + f"<td class='l'>{e(v.reason)}</td></tr>")
    out.append("</table>")
    if r.blunders:
        out.append(f"<h2>Rejected observations ({len(r.blunders)})</h2><table><tr><th>stage</th><th>image</th><th>point</th><th>|w|</th><th>v (px)</th></tr>")
        ids = run.meta.get("point_ids")
        for b in r.blunders:
            pid = ids[b["point"]] if ids else b["point"]
            out.append(f"<tr><td>{b['stage']}</td><td class='l'>{e(b['image'])}</td><td>{e(str(pid))}</td><td>{b['w']:.2f}</td>"
                       f"<td>{b['residual_px'][0]:+.2f}, {b['residual_px'][1]:+.2f}</td></tr>")
        out.append("</table>")
    if exports:
        out.append("<h2>Exports</h2><ul>")
        for k, v in exports.items():
            out.append(f"<li>{e(k)}: {e(str(v))}</li>")
        out.append("</ul>")
    out.append("<p style='font-size:small'>References: Yastikli &amp; Guler 2013; Khodaei et al. 2015; "
               "Brown 1971; Fraser 1997; Bradski 2000; Baarda 1968; Pope 1976.</p></body></html>")
    return "\n".join(out)


def write_outputs(store: ProjectStore, run: CalibrationRun) -> dict[str, Any]:
    """Write camera(s), calibration.json, report.html and exports into ``store``; returns a summary."""
    r = run.result
    if not r.outcome.success or not r.cameras:
        raise ValueError(f"write_outputs: the calibration failed ({r.outcome.termination.value}: {r.outcome.reason})")
    exports_info: dict[str, Any] = {}
    for ci, cc in enumerate(r.cameras):
        cam = camera_from_calibration(cc)
        if ci == 0:
            store.write_json("camera.json", cam.to_dict())
        if len(r.cameras) > 1:
            store.write_json(f"cameras/{ci + 1}_{_safe(cc.name)}.json", cam.to_dict())
        cam_of = np.array([r.images[k].camera for k in r.obs_image], dtype=int) if r.obs_image.size else np.zeros(0, int)
        files, info = _exports(cc, r.obs_xy[cam_of == ci] if r.obs_xy.size else None)
        prefix = "exports/" if ci == 0 else f"exports/{ci + 1}_{_safe(cc.name)}/"
        for k, b in files.items():
            store.write_bytes(prefix + k, b)
        exports_info[cc.name or f"camera {ci + 1}"] = info
    store.write_json("calibration.json", calibration_dict(run, exports_info))
    store.write_text("report.html", report_html(run, exports_info))
    return {"keys": store.keys(), "exports": exports_info}


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in (name or "camera"))


def flush(memory: ProjectStore, folder: ProjectStore) -> list[str]:
    """Copy every key of ``memory`` into ``folder`` (each write atomic); returns the keys."""
    keys = memory.keys()
    for k in keys:
        folder.write_bytes(k, memory.read_bytes(k))
    return keys
