"""``PROJECT/report.html`` of the ``run`` verb: one short index page, a row per step (status of this run, time, key
figures) with links to the step's own report and outputs."""

from __future__ import annotations

import html
from pathlib import Path

import json

from .._atomic import write_atomic_text
from ..reporting import ReportHeader, folders_of, header_html

__all__ = ["write_run_report", "run_header"]

#: per step: (label, relative path) of the outputs linked when present
LINKS = {
    "survey": (("report", "survey/report.html"), ("cameras.json", "survey/cameras.json"), ("survey.json", "survey/survey.json"),
               ("sparse cloud", "survey/sparse.las"), ("COLMAP model", "survey/colmap/cameras.txt")),
    "dense": (("report", "dense/report.html"), ("DSM", "dense/dsm.tif"), ("cloud (LAS)", "dense/cloud.las"),
              ("cloud (PLY)", "dense/cloud.ply"), ("dense.json", "dense/dense.json")),
    "ortho": (("report", "ortho/report.html"), ("orthophoto", "ortho/ortho.tif"), ("QGIS style", "ortho/ortho.qml"),
              ("16-bit", "ortho/ortho_u16.tif"), ("ortho.json", "ortho/ortho.json")),
}


def _figures(name: str, s: dict) -> list[str]:
    if not s:
        return []
    if name == "survey":
        out = [f"images oriented: {s.get('images_oriented')}/{s.get('images_total')}"
               + (f" in {len(s['blocks'])} block(s)" if s.get("blocks") else "")]
        if s.get("reprojection_rms_px") is not None:
            out.append(f"reprojection RMS: {s['reprojection_rms_px']:.3f} px")
        cp = s.get("checkpoints")
        out.append(f"check points: n = {cp['n']}, RMSE X {cp['rmse_x']:.3f} m, Y {cp['rmse_y']:.3f} m, Z {cp['rmse_z']:.3f} m"
                   if cp else "check points: none given")
        out.append(f"CRS: {s.get('crs') or 'local frame'}")
        return out
    if name == "dense":
        return [f"points: {s['points']}", f"DSM: {s['dsm_cells'][0]} × {s['dsm_cells'][1]} cells at {s['gsd_m']} m",
                f"DSM completeness: {100 * s['completeness']:.1f} %", f"values: {s['unit']}"]
    return [f"ortho: {s['size'][0]} × {s['size'][1]} cells at {s['gsd_m']} m in {s['unit']}",
            *([f"the frames' footprint covered: {100 * s['footprint_coverage']:.1f} %"]
              if s.get("footprint_coverage") is not None else []),
            f"ortho coverage of its box: {100 * s['coverage']:.1f} %", f"images used: {s['images_used']}"]


def run_header(project: Path, results: list, recs: dict, images=()) -> ReportHeader:
    """The header of the project's index page: the images given (``images``: the files or folders), the CRS and the
    flying height of the survey, the ortho's cell and area, the time of this run's steps."""
    summ = {k: (r.get("summary") or {}) for k, r in recs.items()}
    for r in results:
        if r.summary:
            summ[r.name] = r.summary
    sv, ortho = summ.get("survey", {}), summ.get("ortho", {})
    try:
        geo = json.loads((project / "survey" / "survey.json").read_text(encoding="utf-8")).get("footprints") or {}
    except (OSError, ValueError):
        geo = {}
    cells = ortho.get("cells")
    return ReportHeader(
        "run", inputs=[(sv.get("images_total"), "images", folders_of(images))] if images else [],
        crs=sv.get("crs"), georeferenced=bool(sv.get("crs")) if "crs" in sv else None, gsd_m=ortho.get("gsd_m"),
        gsd_note="orthophoto cell", flying_height_m=geo.get("flying_height_m"),
        flying_height_note="median camera height above the sparse cloud's median height",
        area_m2=cells * ortho["gsd_m"] ** 2 if cells and ortho.get("gsd_m") else None,
        area_note="orthophoto cells with a value", seconds=sum(r.seconds for r in results if r.status != "skipped"))


def write_run_report(project: Path, results: list, recs: dict, products, header: ReportHeader | None = None) -> Path:
    """Write ``project/report.html`` from the step results of this run and the records of run.json (``header``:
    :func:`run_header`'s, None: one without the inputs)."""
    rows = []
    for r in results:
        rec = recs.get(r.name, {})
        status = {"ran": "ran", "skipped": "skipped (unchanged)", "failed": "FAILED"}[r.status]
        when = rec.get("finished_utc", "") if r.status != "failed" else ""
        figs = "".join(f"<li>{html.escape(f)}</li>" for f in _figures(r.name, r.summary or rec.get("summary", {})))
        if r.message:
            figs += f"<li class='err'>{html.escape(r.message)}</li>"
        links = " · ".join(f"<a href='{html.escape(p)}'>{html.escape(lab)}</a>" for lab, p in LINKS.get(r.name, ())
                           if (project / p).is_file())
        secs = rec.get("seconds", r.seconds) if r.status == "skipped" else r.seconds
        rows.append(f"<tr><td><b>{r.name}</b></td><td class='{r.status}'>{status}</td><td>{secs:.1f} s"
                    f"{'<br><small>finished ' + html.escape(when) + '</small>' if when else ''}</td>"
                    f"<td><ul>{figs}</ul></td><td>{links}</td></tr>")
    text = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>thermogrammetry run: {html.escape(project.name)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 70em; }}
table {{ border-collapse: collapse; width: 100%; }}
td, th {{ border: 1px solid #ccc; padding: 0.4em 0.6em; vertical-align: top; text-align: left; }}
td ul {{ margin: 0; padding-left: 1.2em; }}
.ran {{ color: #060; }} .skipped {{ color: #555; }} .failed, .err {{ color: #b00; font-weight: bold; }}
</style></head><body>
<h1>Project {html.escape(project.name)}</h1>
{header_html(header or run_header(project, results, recs))}
<p>Products {html.escape(', '.join(products))}. A step is skipped when its inputs, options and upstream step are unchanged (hashes in <a href="run.json">run.json</a>);
progress and the libraries' messages are in <a href="run.log">run.log</a>.</p>
<table><tr><th>step</th><th>status (this run)</th><th>time</th><th>key figures</th><th>outputs</th></tr>
{chr(10).join(rows)}
</table></body></html>
"""
    return write_atomic_text(project / "report.html", text)
