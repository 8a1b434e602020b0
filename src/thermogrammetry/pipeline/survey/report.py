"""``report.html`` of ``survey``: the header (:mod:`thermogrammetry.reporting`), the blocks, cameras and
accuracy tables, the per-point table of the GCPs and check points, and the maps of
:mod:`.report_figures` (sparse cloud, overlap, camera-centre error ellipses, residuals at the points)."""

from __future__ import annotations

import html
import io

import numpy as np

from ...reporting import ReportHeader, figure_png, html_page, log_counts_axis, map_origin

_png = figure_png  # (the name older callers import)


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
    """``report.html`` from the store's ``survey.json``, ``cameras.json`` and ``sparse.ply``."""
    import matplotlib

    matplotlib.use("Agg")
    s = project.read_json("survey.json")
    geo = s.get("footprints") or survey_geometry(project)
    parts = []
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
    parts += _point_table(s)
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
    parts += _figures(project, s, geo)
    if s.get("steps"):
        parts.append("<h2>Time per step</h2><table><tr><th>step</th><th>s</th><th>status</th></tr>" + "".join(
            f"<tr><td class=l>{st['name']}</td><td>{st['seconds']:.1f}</td><td class=l>{st['status']}</td></tr>" for st in s["steps"]) + "</table>")
    if s.get("notes"):
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in s["notes"]) + "</ul>")
    project.write_text("report.html", html_page("thermogrammetry survey", "Survey report", survey_header(s, geo), parts))


def _mapper_auto_text(a: dict) -> str:
    """survey.json's ``mapper_auto``, as a clause of the report's summary line."""
    return html.escape(f" (mapper auto: the incremental orientation's largest block {a.get('incremental_largest_block')}"
                       f"/{a.get('images')} images, {a.get('incremental_oriented')} in all; the global one's "
                       f"{a.get('global_largest_block')}/{a.get('images')}, {a.get('global_oriented')} in all: "
                       f"{a.get('kept')} kept)")


def _sparse_points(project) -> np.ndarray:
    """(n, 3) points of ``sparse.ply`` ((0, 3) when there is none)."""
    if not project.exists("sparse.ply"):
        return np.zeros((0, 3))
    from plyfile import PlyData

    v = PlyData.read(io.BytesIO(project.read_bytes("sparse.ply")))["vertex"]
    return np.column_stack([v["x"], v["y"], v["z"]]).astype(float)


def survey_geometry(project) -> dict:
    """``survey.json``'s ``footprints`` (:func:`.report_figures.block_geometry`) from ``cameras.json`` and the sparse
    cloud's median height; {} without them."""
    from .report_figures import block_geometry

    if not project.exists("cameras.json"):
        return {}
    try:
        P = _sparse_points(project)
        return block_geometry(project.read_json("cameras.json"), float(np.median(P[:, 2])) if len(P) else None)
    except Exception as exc:  # noqa: BLE001 - the report's figures must not fail the survey
        return {"not_computed": f"{type(exc).__name__}: {exc}"}


def survey_header(s: dict, geo: dict) -> ReportHeader:
    """The header of the survey report from ``survey.json`` (``s``) and its ``footprints`` (``geo``)."""
    ins = s.get("inputs", {})
    n_rgb = sum(1 for im in s.get("images", []) if im.get("sensor") == "rgb")
    inputs = [(s["images_total"] - n_rgb, "thermal images", ins.get("image_folders", []))]
    if n_rgb or ins.get("rgb_folders"):
        inputs.append((n_rgb, "RGB images", ins.get("rgb_folders", [])))
    for key, what in (("gcps", "GCPs"), ("gcp_measurements", "GCP image measurements"), ("checkpoints", "check points"),
                      ("check_measurements", "check-point image measurements"), ("rig", "rig file")):
        if ins.get(key):
            inputs.append((None, what, [ins[key]]))
    return ReportHeader(
        "survey", inputs=inputs, crs=s.get("crs"), georeferenced=bool(s.get("crs")), gsd_m=geo.get("gsd_m"),
        gsd_note="of the images at nadir: flying height / focal length", flying_height_m=geo.get("flying_height_m"),
        flying_height_note="median camera height above the sparse cloud's median height",
        area_m2=geo.get("area_m2"), area_note="union of the image footprints on that height, as in the overlap map",
        seconds=s.get("seconds"))


def _point_table(s: dict) -> list[str]:
    """One row per GCP and check point: residual dX, dY, dZ and σ (GCPs: the σ given; check points: the σ of their
    intersection)."""
    rows = []
    for g in s.get("gcp_residuals", []):
        sg = g.get("sigma_given") or [None] * 3
        rows.append(f"<tr><td class=l>{html.escape(str(g['id']))}</td><td class=l>GCP</td><td></td>"
                    + "".join(f"<td>{_f(g[k])}</td>" for k in ("dx", "dy", "dz"))
                    + "".join(f"<td>{_f(v)}</td>" for v in sg) + "<td class=l>σ given</td></tr>")
    for c in s.get("checkpoint_errors", []):
        if "dx" in c:
            cells = "".join(f"<td>{_f(c[k])}</td>" for k in ("dx", "dy", "dz", "sx", "sy", "sz"))
            note = "σ of the intersection" if c.get("sx") is not None else html.escape(c.get("sigma_refused", "") or "no σ")
        else:
            cells, note = "<td colspan=6></td>", html.escape(c.get("reason", ""))
        rows.append(f"<tr><td class=l>{html.escape(str(c['id']))}</td><td class=l>check point</td><td>{c['n_images']}</td>"
                    f"{cells}<td class=l>{note}</td></tr>")
    if not rows:
        return []
    return ["<h3>Per point (residual = adjusted or intersected − given, m)</h3><table><tr><th>point</th><th>kind</th>"
            "<th>images</th><th>dX</th><th>dY</th><th>dZ</th><th>σX</th><th>σY</th><th>σZ</th><th>σ</th></tr>"
            + "".join(rows) + "</table>"]


def _figure(draw, *args):
    """``draw(*args)``, or a line saying why the figure was not drawn (a figure must not lose the report)."""
    try:
        return draw(*args)
    except Exception as exc:  # noqa: BLE001
        import matplotlib.pyplot as plt

        plt.close("all")
        return f"<p class=bad>figure not drawn: {html.escape(type(exc).__name__)}: {html.escape(str(exc))}</p>"


def _figures(project, s: dict, geo: dict) -> list[str]:
    from . import report_figures as rf

    out = ["<h2>Figures</h2>"]
    cams = project.read_json("cameras.json") if project.exists("cameras.json") else None
    if cams and cams.get("images"):
        C = np.array([im["center"] for im in cams["images"]], float)
        P = _sparse_points(project)
        if len(P) > 20000:
            P = P[np.random.default_rng(0).choice(len(P), 20000, replace=False)]
        origin = map_origin(C[:, 0], C[:, 1])  # one origin for every map of the report
        out.append(_figure(rf.sparse_figure, P, C, [im["name"] for im in cams["images"]], origin))
        if geo.get("ground_z_m") is not None:
            def overlap():
                counts, ext, cell = rf.overlap_counts([q for _, q in rf.footprints(cams, geo["ground_z_m"])])
                return (rf.overlap_figure(counts, ext, C, geo["ground_z_m"], origin)
                        + f"<p class=caption>Images covering each {cell:.2g} m ground cell: the footprints of "
                          f"cameras.gpkg ({geo.get('images_with_footprint')} images), i.e. the image corners on the plane "
                          f"at the sparse cloud's median height; median {_f(geo.get('images_per_cell_median'), '{:g}')}, "
                          f"at most {geo.get('images_per_cell_max')} images per covered cell.</p>")
            out.append(_figure(overlap))
        cov = _centre_cov(s, cams)
        if np.isfinite(cov).all(axis=(1, 2)).any():
            def ellipses():
                img, mag = rf.ellipse_figure(C, cov, origin)
                sd = 100 * np.sqrt(np.nanmedian(np.diagonal(cov, axis1=1, axis2=2), axis=0))
                return img + (f"<p class=caption>1 σ error ellipses of the camera centres (from the covariance of the "
                              f"final adjustment), drawn magnified ×{mag:g}; the dots' colour is σZ. Median σX, σY, σZ "
                              f"{sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f} cm.</p>")
            out.append(_figure(ellipses))
        pts = rf.control_points(s)
        if pts:
            def control():
                img, mag = rf.control_figure(pts, C, origin)
                return img + (f"<p class=caption>Planimetric residuals dX, dY drawn at each point's given position, "
                              f"magnified ×{mag:g} (key arrow above the map); dZ written beside each point.</p>")
            out.append(_figure(control))
    ims = [im for im in s["images"] if im["oriented"]]
    if ims:
        out.append(_figure(rf.residual_bars, ims))
    hist = s.get("tie_point_multiplicity", {}).get("histogram", [])
    if hist:
        def multiplicity():
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(5, 2.6))
            ax.bar(range(len(hist)), hist, color="#777")
            ax.set_xlabel("images per tie point")
            ax.set_ylabel("points")
            ax.set_yscale("log")
            log_counts_axis(ax.yaxis)
            ax.set_title("Tie points by the number of images observing them", fontsize=10)
            return figure_png(fig)
        out.append(_figure(multiplicity))
    return out


def _centre_cov(s: dict, cams: dict) -> np.ndarray:
    """(n, 3, 3) covariance of each camera centre of ``cameras.json`` (m²): survey.json's ``center_cov_m2``, else
    the diagonal of its ``center_std`` (correlations unknown), NaN when neither is known."""
    by_name = {im["name"]: im for im in s.get("images", [])}
    out = np.full((len(cams["images"]), 3, 3), np.nan)
    for k, im in enumerate(cams["images"]):
        c = by_name.get(im["name"], {}).get("center_cov_m2")
        if c is not None:
            out[k] = np.asarray(c, float)
        elif im.get("center_std") is not None and all(v is not None for v in im["center_std"]):
            out[k] = np.diag(np.asarray(im["center_std"], float) ** 2)
    return out
