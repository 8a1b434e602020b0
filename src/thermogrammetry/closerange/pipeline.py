"""The close-range workflow as pipeline steps over a project store.

Inputs (keys written by the caller, e.g. the CLI, before :func:`closerange_steps` run):

- ``inputs/control.csv``, ``inputs/measurements.csv``, ``inputs/planes.csv`` (see :mod:`.tables`);
- ``inputs/settings.json``: ``{"thermal": IMAGE_NAME, "config": {...CloseRangeConfig...},
  "cameras": {IMAGE_NAME: "inputs/cameras/IMAGE_NAME.json"}, "thermal_unit": "K" | "C"}``;
- ``inputs/thermal_k.npy`` (optional): the thermal image's temperatures in kelvin.

Outputs: ``points.csv`` (``id,X,Y,Z,sX,sY,sZ``), ``cameras.json``, ``orientation.json``,
``planes.csv``, ``corrected.tif`` (float32 in ``thermal_unit``), ``angle_deg.tif``, ``distance_m.tif``,
``sigma_k.tif``, ``valid.tif`` and ``report.html``. Every step re-solves the (cheap, deterministic)
network from the inputs, so steps share nothing in memory.

``cameras.json`` is the project's one oriented-cameras schema
(:class:`thermogrammetry.io.oriented.OrientedCameras`, ``thermogrammetry/cameras`` version 1), read by
``correct --cameras``, ``dense``, ``ortho`` and ``texture``: one entry per image (``camera_id`` = image
name), ``crs`` null (the local frame of the control points), ``sensor`` ``thermal`` for the thermal
image and ``rgb`` (visible-light) for the optical ones, no decoded ``frame``. A camera with a known
interior orientation (``--camera``) keeps its calibrated model; a camera oriented by DLT becomes an
``opencv`` camera without distortion whose ``fx fy cx cy skew`` are the decomposition of its 3×4 matrix
(exact: the DLT is that camera). closerange does not know the pixel size of the images of DLT cameras:
the thermal camera gets the thermal image's size when one is given; otherwise ``image_size`` is a
nominal size covering the measured points and the principal point (said in the image's ``notes``).
``center_std`` is the propagated σ of the projection centre; ``rotation_std_deg`` is null (the σ of
ω φ κ are in ``orientation.json``).

``orientation.json`` (``"format": "thermogrammetry.closerange.orientation/1"``) keeps what the schema
has no place for: per camera the method, points used, σ0, interior/exterior orientation with σ
(ω φ κ in degrees, Kraus's convention), the 11 DLT coefficients ``dlt_L_world`` of ``P / P[2, 3]`` in
the world frame, the additional parameters of the joint adjustment, and the thermal centre's
covariance and the warnings. (Before this file existed closerange wrote that report as
``cameras.json`` with ``"format": "thermogrammetry.closerange.cameras/1"``; ``correct`` still reads
such files.)
"""

from __future__ import annotations

import base64
import html
import io
import json
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..reporting import ReportHeader, header_html
from ..store import ProjectStore, Step
from . import network as nw
from .solve import NetworkResult, Observations, solve_network
from .tables import parse_control, parse_measurements, parse_planes
from .workflow import CloseRangeConfig, correct_thermal_image, estimate_planes

__all__ = ["closerange_steps", "load_inputs", "camera_report", "oriented_cameras", "write_inputs",
           "ORIENTATION_FORMAT"]

ORIENTATION_FORMAT = "thermogrammetry.closerange.orientation/1"

_SETTINGS_KEYS = {"thermal", "config", "cameras", "thermal_unit"}


def write_inputs(project: ProjectStore, *, control_csv: str, measurements_csv: str, planes_csv: str, thermal: str,
                 config: CloseRangeConfig | None = None, cameras: dict[str, dict] | None = None,
                 thermal_k: np.ndarray | None = None, thermal_unit: str = "K") -> None:
    """Store the workflow's inputs in ``project`` (camera dicts are ``Camera.to_dict()`` payloads)."""
    project.write_text("inputs/control.csv", control_csv)
    project.write_text("inputs/measurements.csv", measurements_csv)
    project.write_text("inputs/planes.csv", planes_csv)
    cams = {}
    for name, d in (cameras or {}).items():
        key = f"inputs/cameras/{name}.json"
        project.write_json(key, d)
        cams[name] = key
    if thermal_k is not None:
        project.write_array("inputs/thermal_k.npy", np.asarray(thermal_k, np.float32))
    project.write_json("inputs/settings.json", {
        "thermal": thermal, "config": (config or CloseRangeConfig()).to_dict(), "cameras": cams,
        "thermal_unit": thermal_unit,
    })


def load_inputs(project: ProjectStore) -> dict[str, Any]:
    """Parse the inputs; returns control, rows, planes, thermal, config, known cameras, unit."""
    st = project.read_json("inputs/settings.json")
    unknown = sorted(set(st) - _SETTINGS_KEYS)
    if unknown:
        raise ConfigError(f"{project.describe('inputs/settings.json')}: unknown key(s) {unknown}; "
                          f"expected some of {sorted(_SETTINGS_KEYS)}")
    cfg = CloseRangeConfig.from_dict(st.get("config", {}))
    known = {}
    if st.get("cameras"):
        from ..camera import Camera

        for name, key in st["cameras"].items():
            known[name] = Camera.from_dict(project.read_json(key), source=project.describe(key))
    return {
        "control": parse_control(project.read_text("inputs/control.csv"), project.describe("inputs/control.csv")),
        "rows": parse_measurements(project.read_text("inputs/measurements.csv"),
                                   project.describe("inputs/measurements.csv")),
        "planes": parse_planes(project.read_text("inputs/planes.csv"), project.describe("inputs/planes.csv")),
        "thermal": str(st["thermal"]),
        "config": cfg,
        "known": known,
        "unit": str(st.get("thermal_unit", "K")).upper(),
    }


def _solve(project: ProjectStore) -> tuple[dict, NetworkResult]:
    inp = load_inputs(project)
    obs = Observations.from_rows(inp["rows"], inp["config"].sigma_px)
    net = solve_network(inp["control"], obs, inp["thermal"], known=inp["known"],
                        control_sigma_m=inp["config"].control_sigma_m)
    if inp["config"].bundle:
        from .adjust import adjust_network

        net = adjust_network(net, additional=inp["config"].additional_parameters)
    return inp, net


# -- cameras.json --------------------------------------------------------------------------------------

def _describe_L(L, frame: nw.Frame) -> np.ndarray:
    """(11,) DLT → [fx, fy, cx, cy, skew, X0, Y0, Z0, ω, φ, κ] (px, m, rad)."""
    from ..geometry.rotations import opk_from_matrix

    P = nw.dlt_matrix(L) @ frame.world_matrix()
    K, R, C = nw.decompose_projection(P)
    M = np.diag([1.0, -1.0, -1.0]) @ R  # photo_from_world (docs/conventions.md)
    o, p, k = opk_from_matrix(M)
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1], *C, float(o), float(p), float(k)])


def camera_report(net: NetworkResult, name: str) -> dict[str, Any]:
    """Interior and exterior orientation of one camera with standard deviations."""
    cam = net.cameras[name]
    v = _describe_L(cam.L, net.frame)
    G = np.zeros((11, 11))
    for j in range(11):
        h = 1e-7 * max(1.0, abs(cam.L[j]))
        e = np.zeros(11)
        e[j] = h
        d = _describe_L(cam.L + e, net.frame) - _describe_L(cam.L - e, net.frame)
        d[8:] = (d[8:] + np.pi) % (2 * np.pi) - np.pi
        G[:, j] = d / (2 * h)
    cov = net.cov(G @ cam.J)
    s = np.sqrt(np.maximum(np.diag(cov), 0))
    K, R, C = nw.decompose_projection(nw.dlt_matrix(cam.L) @ net.frame.world_matrix())
    P = nw.dlt_matrix(cam.L) @ net.frame.world_matrix()
    P = P / P[2, 3]
    names = ["fx_px", "fy_px", "cx_px", "cy_px", "skew_px"]
    known = name in net.known
    return {
        "name": name,
        "kind": cam.kind,
        "method": ("resection (known interior orientation)" if known else "DLT + least-squares refinement")
                  + (" + joint adjustment" if net.adjusted else ""),
        "points_used": list(cam.ids),
        "sigma0_px": cam.sigma0_px,
        "rms_residual_px": float(np.sqrt(np.mean(cam.residuals**2))),
        "termination": str(cam.outcome.termination),
        "interior": {n: float(v[i]) for i, n in enumerate(names)},
        "interior_std": ({n: 0.0 for n in names} if known else {n: float(s[i]) for i, n in enumerate(names)}),
        "exterior": {"X0": float(v[5]), "Y0": float(v[6]), "Z0": float(v[7]),
                     "omega_deg": float(np.degrees(v[8])), "phi_deg": float(np.degrees(v[9])),
                     "kappa_deg": float(np.degrees(v[10]))},
        "exterior_std": {"X0": float(s[5]), "Y0": float(s[6]), "Z0": float(s[7]),
                         "omega_deg": float(np.degrees(s[8])), "phi_deg": float(np.degrees(s[9])),
                         "kappa_deg": float(np.degrees(s[10]))},
        "R_cam_from_world": R.tolist(),
        "center_m": C.tolist(),
        "dlt_L_world": P.ravel()[:11].tolist(),
        **({"camera": net.known[name].to_dict()} if known and hasattr(net.known[name], "to_dict") else {}),
        **cam.extra,
        "conventions": "pixels: OpenCV origin; R is cam_from_world (x right, y down, z forward); "
                       "omega/phi/kappa: M = R_kappa R_phi R_omega = photo_from_world (docs/conventions.md)",
    }


def _nominal_size(xy: np.ndarray, cx: float, cy: float) -> tuple[int, int]:
    """Smallest (w, h) holding the measured points and centring the principal point (pixels)."""
    hi = np.max(np.asarray(xy, float), axis=0) if len(xy) else np.zeros(2)
    w = int(np.ceil(max(hi[0] + 0.5, 2.0 * cx + 1.0, 1.0)))
    h = int(np.ceil(max(hi[1] + 0.5, 2.0 * cy + 1.0, 1.0)))
    return w, h


def oriented_cameras(net: NetworkResult, reports: dict[str, dict], inp: dict, *, thermal_size=None):
    """The network's cameras in the oriented-cameras schema (see the module docstring).

    Parameters
    ----------
    net : the solved network
    reports : ``{name: camera_report(net, name)}``
    inp : :func:`load_inputs` of the project (rows give the measured pixels, for nominal sizes)
    thermal_size : (w, h) of the thermal image, or None

    Returns
    -------
    thermogrammetry.io.oriented.OrientedCameras

    References
    ----------
    Sawicki, Stein & Więcek (1998) for the DLT cameras; docs/conventions.md for the pose convention.
    """
    from ..camera import Camera
    from ..io.oriented import OrientedCameras, OrientedImage

    xy_of: dict[str, list] = {}
    for r in inp["rows"]:
        xy_of.setdefault(r[0], []).append((float(r[2]), float(r[3])))
    cameras, images = {}, []
    for name, rep in reports.items():
        R = np.asarray(rep["R_cam_from_world"], float)
        C = np.asarray(rep["center_m"], float)
        notes = [f"closerange: {rep['method']}"]
        known = net.known.get(name)
        if isinstance(known, Camera):
            cam = known
        else:
            i = rep["interior"]
            size = thermal_size if (name == net.thermal and thermal_size is not None) else None
            if size is None:
                size = _nominal_size(np.array(xy_of.get(name, []), float).reshape(-1, 2), i["cx_px"], i["cy_px"])
                notes.append("image_size is nominal (closerange does not know the image's pixel size)")
            cam = Camera("opencv", size, dict(fx=i["fx_px"], fy=i["fy_px"], cx=i["cx_px"], cy=i["cy_px"],
                                              skew=i["skew_px"]), name=name)
            notes.append("camera from the DLT decomposition (no distortion); DLT coefficients in orientation.json")
        if rep.get("additional_parameters"):
            notes.append("additional parameters of the joint adjustment (orientation.json) are not part of this camera")
        s = rep["exterior_std"]
        images.append(OrientedImage(
            name, name, R, -R @ C, center_std=np.array([s["X0"], s["Y0"], s["Z0"]], float),
            unit="K" if name == net.thermal else "dn", sensor="thermal" if name == net.thermal else "rgb",
            notes="; ".join(notes)))
        cameras[name] = cam
    return OrientedCameras(cameras, images, crs=None,
                           notes="written by thermogrammetry closerange (Sawicki, Stein & Więcek 1998); local frame "
                                 "of the control points; full orientation report with σ and DLT coefficients in "
                                 "orientation.json")


# -- steps ---------------------------------------------------------------------------------------------

def _step_orient(project: ProjectStore) -> dict:
    inp, net = _solve(project)
    sig = net.point_sigmas
    lines = ["id,X,Y,Z,sX,sY,sZ,kind"]
    for pid, X in net.control.items():
        sc = np.sqrt(np.maximum(np.diag(net.cov(net.point_jacobian(pid))), 0))
        lines.append(f"{pid},{X[0]:.6f},{X[1]:.6f},{X[2]:.6f},{sc[0]:.6f},{sc[1]:.6f},{sc[2]:.6f},control")
    for k, pid in enumerate(net.pass_ids):
        X, s = net.points_world[k], sig[k]
        lines.append(f"{pid},{X[0]:.6f},{X[1]:.6f},{X[2]:.6f},{s[0]:.6f},{s[1]:.6f},{s[2]:.6f},pass")
    project.write_text("points.csv", "\n".join(lines) + "\n")
    cams = {name: camera_report(net, name) for name in net.cameras}
    C, Cc = net.thermal_center()
    size = None
    if project.exists("inputs/thermal_k.npy"):
        h, w = project.read_array("inputs/thermal_k.npy").shape[:2]
        size = (int(w), int(h))
    oc = oriented_cameras(net, cams, inp, thermal_size=size)
    project.write_text("cameras.json", json.dumps(oc.to_dict(), indent=1) + "\n")
    project.write_json("orientation.json", {
        "format": ORIENTATION_FORMAT,
        "thermal": net.thermal,
        "sigma_px_a_priori": inp["config"].sigma_px,
        "cameras": cams,
        "thermal_center_cov_m2": Cc.tolist(),
        "warnings": net.warnings,
    })
    return {"cameras": len(cams), "pass_points": len(net.pass_ids), "thermal_center_m": C.tolist(),
            "thermal_center_std_m": np.sqrt(np.diag(Cc)).tolist(), "warnings": net.warnings}


def _step_planes(project: ProjectStore) -> dict:
    inp, net = _solve(project)
    planes = estimate_planes(net, inp["planes"])
    lines = ["name,normal_x,normal_y,normal_z,angle_deg,distance_m,sigma_angle_deg,sigma_distance_m,"
             "los_angle_deg,perpendicular_m,sigma_normal_deg,rms_m,d_m,ids"]
    for p in planes:
        sn = float(np.degrees(np.sqrt(max(np.trace(p.cov_normal), 0.0))))
        lines.append(
            f"{p.name},{p.normal[0]:.8f},{p.normal[1]:.8f},{p.normal[2]:.8f},{np.degrees(p.angle_rad):.4f},"
            f"{p.distance_m:.5f},{np.degrees(p.sigma_angle_rad):.4f},{p.sigma_distance_m:.5f},"
            f"{np.degrees(p.los_angle_rad):.4f},{p.perpendicular_m:.5f},{sn:.4f},{p.rms_m:.6f},{p.d:.6f},{' '.join(p.ids)}")
    project.write_text("planes.csv", "\n".join(lines) + "\n")
    return {p.name: {"angle_deg": float(np.degrees(p.angle_rad)), "distance_m": p.distance_m} for p in planes}


def _tif_bytes(arr: np.ndarray) -> bytes:
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.asarray(arr))
    return buf.getvalue()


def _step_correct(project: ProjectStore) -> dict:
    if not project.exists("inputs/thermal_k.npy"):
        return {"skipped": "no thermal image given (--thermal-image)"}
    inp, net = _solve(project)
    planes = estimate_planes(net, inp["planes"])
    T0 = project.read_array("inputs/thermal_k.npy").astype(np.float64)
    cr = correct_thermal_image(net, planes, T0, inp["config"])
    unit = inp["unit"]
    out = cr.corrected_k - (273.15 if unit == "C" else 0.0)
    try:
        from ..io.tiff import encode_temperature_tiff

        data, _ = encode_temperature_tiff(cr.corrected_k.astype(np.float32), unit=unit, encoding="float32")
    except ImportError:  # pragma: no cover - io.tiff is part of the package
        data = _tif_bytes(out.astype(np.float32))
    project.write_bytes("corrected.tif", data)
    project.write_bytes("angle_deg.tif", _tif_bytes(np.degrees(cr.angle_rad).astype(np.float32)))
    project.write_bytes("distance_m.tif", _tif_bytes(cr.distance_m.astype(np.float32)))
    project.write_bytes("sigma_k.tif", _tif_bytes(cr.sigma_k.astype(np.float32)))
    project.write_bytes("valid.tif", _tif_bytes(cr.valid.astype(np.uint8)))
    project.write_array("work/measured_k.npy", T0.astype(np.float32))
    project.write_array("work/corrected_k.npy", cr.corrected_k.astype(np.float32))
    project.write_array("work/valid.npy", cr.valid)
    v = cr.valid
    return {
        "valid_pixels": int(v.sum()),
        "max_correction_k": float(np.max(np.abs(cr.corrected_k - T0)[v])) if v.any() else 0.0,
        "max_sigma_k": float(np.nanmax(cr.sigma_k)) if v.any() else float("nan"),
        "unit": unit,
        "notes": cr.notes,
    }


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _step_report(project: ProjectStore) -> dict:
    inp = load_inputs(project)
    cams = project.read_json("orientation.json")
    pts = project.read_text("points.csv").strip().splitlines()[1:]
    pls = project.read_text("planes.csv").strip().splitlines()
    e = html.escape
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>thermogrammetry closerange</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #999;padding:2px 6px;text-align:right}th{background:#eee}</style></head><body>",
             "<h1>Close-range orientation and directional correction</h1>",
             header_html(ReportHeader("closerange", inputs=[
                 (len({r[0] for r in inp["rows"]}), "images measured", []), (len(inp["control"]), "control points", []),
                 (len(inp["rows"]), "image measurements", []), (max(0, len(pls) - 1), "planes", [])])),
             "<p>Method: Sawicki, Stein, Więcek — optical cameras by DLT with least-squares refinement, pass points "
             "intersected, thermal camera from pass points only, planes from marked points (eq. 5–6), temperature "
             "correction eq. 7–8 per pixel. Standard deviations propagated from an a-priori image σ of "
             f"{inp['config'].sigma_px} px.</p>",
             "<h2>Results of 3D points positioning (cf. Sawicki, Stein &amp; Więcek, Table 1)</h2><table><tr><th>Point ID</th><th>X [m]</th>"
             "<th>Y [m]</th><th>Z [m]</th><th>σX [mm]</th><th>σY [mm]</th><th>σZ [mm]</th></tr>"]
    for title, kind in (("3D Control Points Coordinates", "control"), ("Final Computed 3D Pass Points Coordinates",
                                                                          "pass")):
        parts.append(f"<tr><th colspan=7 style='text-align:left'>{title}</th></tr>")
        for ln in pts:
            c = ln.split(",")
            if c[7] != kind:
                continue
            fixed = kind == "control" and all(float(x) == 0 for x in c[4:7])
            sig = "<td colspan=3>fixed</td>" if fixed else "".join(f"<td>{1000 * float(x):.2f}</td>" for x in c[4:7])
            parts.append(f"<tr><td>{e(c[0])}</td><td>{float(c[1]):.4f}</td><td>{float(c[2]):.4f}</td>"
                         f"<td>{float(c[3]):.4f}</td>{sig}</tr>")
    parts.append("</table><h2>Cameras</h2><table><tr><th>camera</th><th>method</th><th>X0 [m]</th><th>Y0 [m]</th>"
                 "<th>Z0 [m]</th><th>σX0/σY0/σZ0 [mm]</th><th>ω φ κ [°]</th><th>fx fy [px]</th><th>σ0 [px]</th></tr>")
    for name, c in cams["cameras"].items():
        x, s, i = c["exterior"], c["exterior_std"], c["interior"]
        parts.append(
            f"<tr><td>{e(name)} ({e(c['kind'])})</td><td>{e(c['method'])}</td><td>{x['X0']:.4f}</td><td>{x['Y0']:.4f}</td>"
            f"<td>{x['Z0']:.4f}</td><td>{1000 * s['X0']:.1f} / {1000 * s['Y0']:.1f} / {1000 * s['Z0']:.1f}</td>"
            f"<td>{x['omega_deg']:.3f} {x['phi_deg']:.3f} {x['kappa_deg']:.3f}</td>"
            f"<td>{i['fx_px']:.1f} {i['fy_px']:.1f}</td><td>{c['sigma0_px']:.3f}</td></tr>")
    parts.append("</table><h2>Planes</h2><table><tr>" + "".join(f"<th>{e(h)}</th>" for h in pls[0].split(",")) + "</tr>")
    for ln in pls[1:]:
        parts.append("<tr>" + "".join(f"<td>{e(c)}</td>" for c in ln.split(",")) + "</tr>")
    parts.append("</table>")
    if cams.get("warnings"):
        parts.append("<h3>Warnings</h3><ul>" + "".join(f"<li>{e(w)}</li>" for w in cams["warnings"]) + "</ul>")
    if project.exists("work/corrected_k.npy"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        T0 = project.read_array("work/measured_k.npy") - 273.15
        Tc = project.read_array("work/corrected_k.npy") - 273.15
        valid = project.read_array("work/valid.npy")
        lo, hi = np.nanpercentile(np.concatenate([T0.ravel(), Tc.ravel()]), [1, 99.9])
        fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
        for a, img, t in ((ax[0], T0, "measured [°C]"), (ax[1], Tc, "corrected [°C]")):
            im = a.imshow(img, vmin=lo, vmax=hi, cmap="inferno")
            a.set_title(t)
            fig.colorbar(im, ax=a, fraction=0.046)
        d = np.where(valid, Tc - T0, np.nan)
        im = ax[2].imshow(d, cmap="viridis")
        ax[2].set_title("correction [K] (valid mask)")
        fig.colorbar(im, ax=ax[2], fraction=0.046)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
        parts.append("<h2>Thermal image: measured and corrected temperatures</h2>"
                     f"<img src='data:image/png;base64,{_png(fig)}' style='width:100%'>")
        plt.close(fig)
    parts.append("</body></html>")
    project.write_text("report.html", "\n".join(parts))
    return {"report": project.describe("report.html")}


def closerange_steps() -> list[Step]:
    """The workflow's steps: orient → planes → correct → report."""
    return [
        Step("orient", _step_orient, "optical cameras by DLT, pass points, thermal camera from pass points"),
        Step("planes", _step_planes, "planes from marked points: normal, angle to the thermal axis, distance"),
        Step("correct", _step_correct, "per-pixel directional correction of the thermal image"),
        Step("report", _step_report, "report.html"),
    ]

