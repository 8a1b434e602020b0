"""thermogrammetry.pipeline.survey.report"""

from __future__ import annotations

import base64
import html
import io

import numpy as np


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _f(v, fmt="{:.4f}"):
    return "—" if v is None else fmt.format(v)


def _axis_table(title, d):
    rows = "".join(
        f"<tr><th>{ax.upper()}</th><td>{_f(d.get('min_' + ax))}</td><td>{_f(d.get('max_' + ax))}</td>"
        f"<td>{_f(d.get('mae_' + ax))}</td><td>{_f(d.get('rmse_' + ax))}</td></tr>" for ax in "xyz")
    return (f"<h3>{html.escape(title)} (n = {d.get('n', 0)})</h3><table><tr><th>axis</th><th>min (m)</th><th>max (m)</th>"
            f"<th>MAE (m)</th><th>RMSE (m)</th></tr>{rows}</table>")


def _gcp_measurement_tables(s) -> list:
    """The GCP image measurements per GCP and per image (used, RMS and largest residual of the used ones) and every
    measurement left out with its reason."""
    if not s.get("gcp_measurements"):
        return []

    def table(rows, key, title):
        body = "".join(f"<tr><td class=l>{html.escape(str(r[key]))}</td><td>{r['measurements']}</td><td>{r['used']}</td>"
                       f"<td>{_f(r['rms_px'], '{:.2f}')}</td><td>{_f(r['max_px'], '{:.2f}')}</td></tr>" for r in rows)
        return (f"<table><tr><th>{title}</th><th>measurements</th><th>used</th><th>RMS px</th><th>max px</th></tr>"
                f"{body}</table>")

    out = ["<h3>GCP image measurements (residual = projected − measured, at the adjusted GCP and camera)</h3>",
           table(s.get("gcp_measurements_by_gcp", []), "id", "GCP"),
           table(s.get("gcp_measurements_by_image", []), "image", "image")]
    left = [r for r in s["gcp_measurements"] if not r["used"]]
    if left:  # (the blunders of gcp_rejected_measurements among them, with the reason each was found)
        out.append(f"<p class='bad'>{len(left)} GCP measurement(s) left out:</p>"
                   "<table><tr><th>GCP</th><th>image</th><th>residual px</th><th>left out because</th></tr>" + "".join(
            f"<tr><td class=l>{html.escape(r['id'])}</td><td class=l>{html.escape(r['image'])}</td>"
            f"<td>{_f(r['residual_px'], '{:.1f}')}</td><td class=l>{html.escape(r['reason'])}</td></tr>" for r in left)
                   + "</table>")
    return out


def write_survey_report(project) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = project.read_json("survey.json")
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>thermogrammetry survey</title><style>"
             "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}table{border-collapse:collapse;margin:.5em 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}td.l{text-align:left}"
             ".bad{color:#a00}</style></head><body>"]
    parts.append("<h1>Survey report</h1>")
    parts.append(f"<p><b>{s['images_oriented']} of {s['images_total']} images oriented</b> in {len(s['components'])} block(s) "
                 f"{s['components']}; reprojection RMS {_f(s['reprojection_rms_px'], '{:.3f}')} px; "
                 f"{s.get('points', 0)} tie points; CRS {html.escape(str(s['crs'] or 'local frame (not georeferenced)'))}; "
                 f"{_f(s.get('seconds'), '{:.1f}')} s"
                 + (f"; orientation: {html.escape(str(s['mapper']))}" if s.get("mapper") else "")
                 + (_mapper_auto_text(s["mapper_auto"]) if s.get("mapper_auto") else "") + ".</p>")
    if not s.get("temperatures"):
        parts.append(f"<p class='bad'>Frame values are {html.escape(', '.join(s.get('frame_units', [])))}: "
                     "not temperatures (K) — the cloud carries counts or nothing.</p>")
    if s.get("blocks"):
        def _selfcal(b):
            if "self_calibration" not in b:
                return ""
            txt = ", ".join(b["self_calibration"]) or "none (camera held fixed)"
            return txt + (f" (stepped down {len(b['self_calibration_steps'])}×, see notes)" if b.get("self_calibration_steps") else "")

        def _offset(b):
            o = b.get("gnss_offset")
            if not o:
                return ""
            f3 = lambda v: ", ".join(f"{x:+.3f}" for x in v)  # noqa: E731
            return (f"{f3(o['offset_m'])} ± {', '.join(f'{x:.3f}' for x in o['std_m'])}" + (f"; applied {f3(o['applied_m'])}" if any(o["applied_m"]) else "; not applied"))

        def _moved(b):
            m = b.get("moved_to_blocks") or {}
            return "".join(f"; {len(v)} of its images later added to block {k} at their GNSS positions" for k, v in m.items())

        parts.append("<table><tr><th>block</th><th>images</th><th>datum</th><th>σ0</th><th>termination</th>"
                     "<th>self-calibrated</th><th>GCP − GNSS offset (m)</th></tr>" + "".join(
            f"<tr><td>{b['block']}</td><td>{b['images']}</td><td class=l>{html.escape(str(b['datum']))}</td>"
            f"<td>{_f(b.get('sigma0'), '{:.3f}')}</td>"
            f"<td class=l>{html.escape(b.get('termination') or b.get('rejected', ''))}{html.escape(_moved(b))}</td>"
            f"<td class=l>{html.escape(_selfcal(b))}</td><td class=l>{html.escape(_offset(b))}</td></tr>"
            for b in s["blocks"]) + "</table>")
    bad = [im for im in s["images"] if not im["oriented"]]
    if bad:
        parts.append("<h2>Images not oriented</h2><table><tr><th>image</th><th>reason</th></tr>" + "".join(
            f"<tr><td class=l>{html.escape(im['name'])}</td><td class=l>{html.escape(im['reason'])}</td></tr>" for im in bad) + "</table>")
    # cameras
    parts.append("<h2>Cameras</h2>")
    for cid, c in s.get("cameras", {}).items():
        rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{v:.6g}</td><td>{_f(c['std'].get(k), '{:.3g}')}</td></tr>"
                       for k, v in c["params"].items() if v != 0 or c["std"].get(k) is not None)
        parts.append(f"<h3>{html.escape(cid)}</h3><table><tr><th>parameter</th><th>value</th><th>σ</th></tr>{rows}</table>")
    if s.get("rig"):  # RGB + thermal rig (Barazzetti et al. 2013, eq. 4-5)
        rg = s["rig"]
        parts.append(f"<h2>Rig (RGB + thermal)</h2><p>{html.escape(rg['file'])}: {rg['pairs']} pair(s), R*, t "
                     f"{'held fixed' if rg['fixed'] else 'estimated in the block'}; thermal images without a partner: "
                     f"{len(rg['thermal_unpaired'])}</p>")
        if rg.get("rig_only"):
            parts.append(f"<h3>Thermal images posed by the rig only ({len(rg['rig_only'])})</h3><p>No (or fewer than 6) "
                         "observations of their own: their pose is their RGB partner's moved by R*, t, unchecked by the "
                         f"image itself. {html.escape(rg.get('rig_only_counted', ''))}.</p><p>"
                         + ", ".join(html.escape(n) for n in rg["rig_only"]) + "</p>")
        for b in rg["blocks"]:
            if b.get("refused"):
                parts.append(f"<h3>block {b['block']}: R*, t not estimated</h3><p>{html.escape(b['refused'])} (start: "
                             f"{html.escape(b['start'])}). Thermal frames without an orientation of their own are not "
                             "oriented.</p>")
                continue
            sd = b.get("std") or {}
            rows = "".join(f"<tr><th>{k}</th><td>{v:.4f}</td><td>{_f(sd.get('rotation_deg', [None] * 3)[a], '{:.4f}')}</td></tr>"
                           for a, (k, v) in enumerate(zip(("ω (deg)", "φ (deg)", "κ (deg)"), b["rotation_vector_deg"])))
            rows += "".join(f"<tr><th>{k}</th><td>{v:.4f}</td><td>{_f(sd.get('t_base_rgb_frame', [None] * 3)[a], '{:.4f}')}</td></tr>"
                            for a, (k, v) in enumerate(zip(("bx", "by", "bz"), b["seed002"]["t_base_rgb_frame"])))
            parts.append(f"<h3>block {b['block']}: cam_thermal_from_cam_rgb ({html.escape(b['start'])})</h3>"
                         f"<p>rotation vector of R_rel (= R*ᵀ) and base vector b = t of Barazzetti et al. 2013, eq. 5 (thermal centre in the "
                         f"RGB camera frame, {html.escape(b['unit'])})</p><table><tr><th></th><th>value</th><th>σ</th></tr>{rows}</table>")
    if s.get("manual_ties"):
        mt = s["manual_ties"]
        parts.append(f"<h2>Manual tie points</h2><p>{len(mt['used'])} of {mt['ids']} used</p><table><tr><th>id</th><th>images</th>"
                     "<th>sensors</th><th>RMS px</th></tr>" + "".join(
                         f"<tr><td class=l>{html.escape(t['id'])}</td><td>{len(t['images'])}</td><td>{'+'.join(t['sensors'])}</td>"
                         f"<td>{t['rms_px']:.2f}</td></tr>" for t in mt["used"]) + "</table>")
    parts.append("<h2>Accuracy</h2>")
    parts.append(_axis_table("GCP residuals (adjusted − given)", s["gcps"]))
    parts.append(_axis_table("Check points (intersected − given; never in the adjustment)", s["checkpoints"]))
    if s.get("checkpoint_errors"):
        parts.append("<table><tr><th>check point</th><th>images</th><th>dX</th><th>dY</th><th>dZ</th><th>σX</th><th>σY</th><th>σZ</th></tr>" + "".join(
            f"<tr><td class=l>{html.escape(c['id'])}</td><td>{c['n_images']}</td>" + (
                "".join(f"<td>{_f(c[k])}</td>" for k in ("dx", "dy", "dz", "sx", "sy", "sz")) if "dx" in c
                else f"<td class=l colspan=6>{html.escape(c.get('reason', ''))}</td>") + "</tr>" for c in s["checkpoint_errors"]) + "</table>")
    if s.get("gnss", {}).get("n"):
        parts.append(_axis_table("Camera centres against GNSS (adjusted antenna − given)", s["gnss"]))
        if s.get("gnss_flagged"):
            parts.append("<p class='bad'>Camera centres far from their GNSS positions (orientation or GNSS tag wrong): "
                         + ", ".join(f"{html.escape(g['image'])} ({np.hypot(np.hypot(g['dx'], g['dy']), g['dz']):.3f} m, "
                                     f"{g['sigma']:.1f} σ)" for g in s["gnss_flagged"]) + "</p>")
    if s.get("attitude", {}).get("n"):
        a = s["attitude"]
        parts.append(f"<p>Camera rotations against the camera attitude in the files (gimbal): {a['n']} images, median "
                     f"{a['median_deg']:.2f}°, RMS {a['rms_deg']:.2f}°, max {a['max_deg']:.2f}°; their common tilt (mean "
                     f"world-frame rotation vector about x, y, z of the CRS) {', '.join(f'{x:+.2f}' for x in a['mean_deg'])}°"
                     "</p>")
        if a.get("flagged"):
            parts.append("<p class='bad'>Images far from their camera attitude (orientation or attitude tag wrong): "
                         + ", ".join(f"{html.escape(f['image'])} ({f['from_common_deg']:.1f}° beyond the block's common difference)"
                                   for f in a["flagged"]) + "</p>")
    parts += _gcp_measurement_tables(s)
    # figures
    try:
        cams = project.read_json("cameras.json")
        C = np.array([im["center"] for im in cams["images"]])
        fig, ax = plt.subplots(figsize=(7, 6))
        if project.exists("sparse.ply"):
            from plyfile import PlyData

            v = PlyData.read(io.BytesIO(project.read_bytes("sparse.ply")))["vertex"]
            P = np.column_stack([v["x"], v["y"], v["z"]])
            if len(P) > 20000:
                P = P[np.random.default_rng(0).choice(len(P), 20000, replace=False)]
            sc = ax.scatter(P[:, 0], P[:, 1], c=P[:, 2], s=1, cmap="terrain")
            fig.colorbar(sc, ax=ax, label="height of tie points (m)")
        ax.plot(C[:, 0], C[:, 1], "r^", ms=5, label="camera centres")
        for k, im in enumerate(cams["images"]):
            if len(C) <= 60:
                ax.annotate(im["name"][-6:], C[k, :2], fontsize=6)
        ax.set_aspect("equal")
        ax.set_xlabel("X (m)")
        ax.set_ylabel("Y (m)")
        ax.legend(loc="upper right")
        ax.set_title("Camera positions over the sparse cloud")
        parts.append("<h2>Figures</h2>" + _png(fig))
    except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not lose the report
        parts.append(f"<p>camera figure not drawn: {html.escape(str(exc))}</p>")
    ims = [im for im in s["images"] if im["oriented"]]
    if ims:
        fig, ax = plt.subplots(figsize=(max(6, 0.18 * len(ims)), 3))
        ax.bar(range(len(ims)), [im["rms_px"] or 0 for im in ims], color="#47a")
        ax.set_xticks(range(len(ims)))
        ax.set_xticklabels([im["name"][-8:] for im in ims], rotation=90, fontsize=6)
        ax.set_ylabel("reprojection RMS (px)")
        ax.set_title("Tie-point residuals per image")
        parts.append(_png(fig))
    hist = s.get("tie_point_multiplicity", {}).get("histogram", [])
    if hist:
        fig, ax = plt.subplots(figsize=(5, 2.6))
        ax.bar(range(len(hist)), hist, color="#777")
        ax.set_xlabel("images per tie point")
        ax.set_ylabel("points")
        ax.set_yscale("log")
        parts.append(_png(fig))
    ce = [c for c in s.get("checkpoint_errors", []) if "dx" in c]
    if ce:
        try:
            fig, ax = plt.subplots(figsize=(5, 5))
            import csv as _csv  # noqa: F401

            xs = np.arange(len(ce))
            ax.quiver(xs, np.zeros(len(ce)), [c["dx"] for c in ce], [c["dy"] for c in ce], angles="xy", scale_units="xy",
                      scale=max(1e-9, max(np.hypot(c["dx"], c["dy"]) for c in ce)) / 0.8, color="#c33")
            for k, c in enumerate(ce):
                ax.annotate(f"{c['id']}\ndZ {c['dz'] * 100:.1f} cm", (k, -0.3), fontsize=7, ha="center")
            ax.set_xlim(-1, len(ce))
            ax.set_ylim(-1, 1)
            ax.set_yticks([])
            ax.set_title("Check-point planimetric error vectors (arrow length ∝ |dXY|)")
            parts.append(_png(fig))
        except Exception:  # noqa: BLE001
            pass
    if s.get("steps"):
        parts.append("<h2>Time per step</h2><table><tr><th>step</th><th>s</th><th>status</th></tr>" + "".join(
            f"<tr><td class=l>{st['name']}</td><td>{st['seconds']:.1f}</td><td class=l>{st['status']}</td></tr>" for st in s["steps"]) + "</table>")
    if s.get("notes"):
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in s["notes"]) + "</ul>")
    parts.append("</body></html>")
    project.write_text("report.html", "".join(parts))


def _mapper_auto_text(a: dict) -> str:
    """survey.json's ``mapper_auto``, as a clause of the report's summary line."""
    return html.escape(f" (mapper auto: the incremental orientation's largest block {a.get('incremental_largest_block')}"
                       f"/{a.get('images')} images, {a.get('incremental_oriented')} in all; the global one's "
                       f"{a.get('global_largest_block')}/{a.get('images')}, {a.get('global_oriented')} in all: "
                       f"{a.get('kept')} kept)")
