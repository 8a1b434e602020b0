"""Check: an ``ortho.tif`` of ``thermogrammetry ortho`` in QGIS, styled by its ``ortho.qml``, with the °C legend.

Two steps in one script:

1. with the project's Python: a synthetic survey (``tests/survey_truth.py``: TRUE poses, rendered frames in kelvin,
   2 lines × 5 frames) and its true DSM, then ``thermogrammetry ortho --unit C`` (or ``--ortho DIR``: an existing
   OUT folder of ``ortho``);
2. with the system's Python and QGIS's own bindings (Debian's ``python3-qgis``; ``QT_QPA_PLATFORM=offscreen``, no
   screen): the raster opened as QGIS opens it (its default style, i.e. the ``ortho.qml`` beside it) and the style
   also loaded explicitly; checked: the style loads without error, the renderer is ``singlebandpseudocolor`` on band 1
   between the limits ``ortho.json`` states, the legend's entries carry the raster's unit; then a print layout (map +
   legend + title) exported to PNG.

Usage::

    python benchmarks/qgis_ortho_check.py [--ortho DIR] [--save docs/images/ortho_qgis.png] [--keep DIR]

Exit status 0 when every check holds, 1 otherwise, 2 when QGIS's Python bindings are missing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SYSTEM_PYTHON = "/usr/bin/python3"
FRAMES = [k for line in (1, 2) for k in range(14 * line + 4, 14 * line + 9)]


# --------------------------------------------------------------------------------------- step 1: the ortho
def make_ortho(work: Path) -> Path:
    sys.path.insert(0, str(REPO / "src"))
    sys.path.insert(0, str(REPO / "tests"))
    from survey_truth import write_true_dsm, write_true_survey

    from thermogrammetry.cli.main import main as cli

    sc, survey = write_true_survey(work / "survey", frames=FRAMES)
    write_true_dsm(work / "dsm.tif", sc, 0.25)
    out = work / "ortho"
    rc = cli(["ortho", str(survey), "--dsm", str(work / "dsm.tif"), "-o", str(out), "--unit", "C", "--workers", "0"])
    if rc != 0:
        raise SystemExit(f"thermogrammetry ortho failed (exit {rc})")
    return out


# --------------------------------------------------------------------------------------- step 2: QGIS
def qgis_render(ortho_dir: Path, png: Path) -> dict:
    """Open ``ortho_dir/ortho.tif`` in QGIS (system Python), check its style and export a layout with its legend."""
    from qgis.core import (QgsApplication, QgsLayout, QgsLayoutExporter, QgsLayoutItemLabel, QgsLayoutItemLegend,
                           QgsLayoutItemMap, QgsLayoutPoint, QgsLayoutSize, QgsPrintLayout, QgsProject, QgsRasterLayer,
                           QgsUnitTypes, Qgis)
    from qgis.PyQt.QtCore import Qt
    from qgis.PyQt.QtGui import QFont

    app = QgsApplication([], False)
    app.setPrefixPath("/usr", True)
    app.initQgis()
    info = json.loads((ortho_dir / "ortho.json").read_text())
    style = info["style"]
    unit = {"C": "°C", "K": "K"}.get(info["unit"], info["unit"])
    tif = str(ortho_dir / "ortho.tif")
    rep: dict = {"qgis": Qgis.QGIS_VERSION, "ortho_json_style": style}

    def describe(layer):
        r = layer.renderer()
        d = {"valid": layer.isValid(), "renderer": r.type() if r else None}
        if r is not None and r.type() == "singlebandpseudocolor":
            sh = r.shader().rasterShaderFunction()
            d.update(band=r.band(), min=r.classificationMin(), max=r.classificationMax(),
                     ramp_items=[(i.value, i.label) for i in sh.colorRampItemList()],
                     legend_suffix=sh.legendSettings().suffix() if hasattr(sh, "legendSettings") else None)
        d["legend_symbology"] = [str(lbl) for lbl, _ in r.legendSymbologyItems()] if r else []
        return d

    # as QGIS opens it: the default style of ortho.tif is the ortho.qml beside it
    opened = QgsRasterLayer(tif, "ortho", "gdal", QgsRasterLayer.LayerOptions(loadDefaultStyle=True))
    rep["opened"] = describe(opened)
    # and the style loaded explicitly, with QGIS's own message
    layer = QgsRasterLayer(tif, "ortho", "gdal")
    msg, ok = layer.loadNamedStyle(str(ortho_dir / "ortho.qml"))
    rep["loadNamedStyle"] = {"ok": bool(ok), "message": msg}
    rep["styled"] = describe(layer)
    rep["crs"] = layer.crs().authid()

    rep["map"] = map_colours(layer, ortho_dir)
    project = QgsProject.instance()
    project.setCrs(layer.crs())
    project.addMapLayer(layer)
    layout = QgsPrintLayout(project)
    layout.initializeDefaults()
    page = layout.pageCollection().page(0)
    page.setPageSize(QgsLayoutSize(280, 130, QgsUnitTypes.LayoutMillimeters))
    m = QgsLayoutItemMap(layout)
    layout.addLayoutItem(m)  # first: a map item given its extent before it is in the layout draws nothing
    m.attemptMove(QgsLayoutPoint(5, 14, QgsUnitTypes.LayoutMillimeters))
    m.attemptResize(QgsLayoutSize(190, 110, QgsUnitTypes.LayoutMillimeters))
    m.setCrs(layer.crs())
    m.setLayers([layer])
    m.setKeepLayerSet(True)
    m.setExtent(layer.extent())
    title = QgsLayoutItemLabel(layout)
    title.setText(f"ortho.tif in QGIS {Qgis.QGIS_VERSION.split('-')[0]}, styled by ortho.qml ({rep['crs']})")
    title.setFont(QFont("DejaVu Sans", 12))
    title.attemptMove(QgsLayoutPoint(5, 3, QgsUnitTypes.LayoutMillimeters))
    title.attemptResize(QgsLayoutSize(270, 9, QgsUnitTypes.LayoutMillimeters))
    layout.addLayoutItem(title)
    legend = QgsLayoutItemLegend(layout)
    legend.setLinkedMap(m)
    legend.setTitle("Legend")
    legend.attemptMove(QgsLayoutPoint(200, 14, QgsUnitTypes.LayoutMillimeters))
    layout.addLayoutItem(legend)
    legend.adjustBoxSize()
    exporter = QgsLayoutExporter(layout)
    settings = QgsLayoutExporter.ImageExportSettings()
    settings.dpi = 110
    res = exporter.exportToImage(str(png), settings)
    rep["export"] = {"ok": res == QgsLayoutExporter.Success, "png": str(png)}
    # the legend's own text, as the layout draws it
    model = legend.model()
    texts = []
    for row in range(model.rowCount()):
        idx = model.index(row, 0)
        texts.append(model.data(idx, Qt.DisplayRole))
        for k in range(model.rowCount(idx)):
            texts.append(model.data(model.index(k, 0, idx), Qt.DisplayRole))
    rep["legend_model_text"] = [str(t) for t in texts]
    for node in model.layerLegendNodes(model.rootGroup().findLayer(layer)) if hasattr(model, "layerLegendNodes") else []:
        s = getattr(node, "settings", None)
        if callable(s):
            st = s()
            rep.setdefault("legend_nodes", []).append({"class": type(node).__name__, "suffix": st.suffix(),
                                                       "min_label": node.data(0) if hasattr(node, "data") else None})
        else:
            rep.setdefault("legend_nodes", []).append({"class": type(node).__name__, "text": str(node.data(0))})
    rep["checks"] = checks(rep, style, unit)
    return rep


def map_colours(layer, ortho_dir: Path) -> dict:
    """The layer rendered by QGIS (``QgsMapRendererParallelJob``) at one pixel per cell over its extent, against the
    colour the style's palette gives each cell's value (linear between the palette's stops, end colours outside):
    the share of the mosaic's cells drawn, and the median and 99th percentile of the largest RGB difference."""
    import numpy as np
    from qgis.core import QgsMapRendererParallelJob, QgsMapSettings
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor

    w, h = layer.width(), layer.height()
    block = layer.dataProvider().block(1, layer.extent(), w, h)
    vals = np.array([[block.value(r, c) if not block.isNoData(r, c) else np.nan for c in range(w)] for r in range(h)])
    s = QgsMapSettings()
    s.setLayers([layer])
    s.setDestinationCrs(layer.crs())
    s.setExtent(layer.extent())
    s.setOutputSize(QSize(w, h))
    s.setBackgroundColor(QColor(0, 255, 0))
    job = QgsMapRendererParallelJob(s)
    job.start()
    job.waitForFinished()
    img = job.renderedImage()
    rgb = np.array([[[(img.pixel(c, r) >> sh) & 255 for sh in (16, 8, 0)] for c in range(w)] for r in range(h)], float)
    items = layer.renderer().shader().rasterShaderFunction().colorRampItemList()
    xs = np.array([i.value for i in items])
    cols = np.array([[i.color.red(), i.color.green(), i.color.blue()] for i in items], float)
    fin = np.isfinite(vals)
    want = np.stack([np.interp(vals[fin], xs, cols[:, k]) for k in range(3)], axis=1)
    drawn = ~np.all(rgb == [0, 255, 0], axis=-1)
    err = np.abs(rgb[fin] - want).max(axis=1)
    return {"cells": int(w * h), "cells_with_value": int(fin.sum()), "drawn_of_those": float(drawn[fin].mean()),
            "drawn_without_value": int((drawn & ~fin).sum()), "rgb_error_median": float(np.median(err)),
            "rgb_error_p99": float(np.percentile(err, 99)), "errors": [e.message for e in job.errors()]}


def checks(rep: dict, style: dict, unit: str) -> dict:
    out = {}
    for name in ("opened", "styled"):
        d = rep[name]
        rel = max(1e-6, 1e-5 * abs(style["max"] - style["min"]))
        out[f"{name}: pseudocolour on band 1"] = d["renderer"] == "singlebandpseudocolor" and d.get("band") == 1
        out[f"{name}: limits as ortho.json"] = (d.get("min") is not None and abs(d["min"] - style["min"]) <= rel
                                                and abs(d["max"] - style["max"]) <= rel)
        out[f"{name}: every ramp entry in {unit}"] = bool(d.get("ramp_items")) and all(
            lbl.endswith(f" {unit}") for _, lbl in d["ramp_items"])
    out["loadNamedStyle ok"] = rep["loadNamedStyle"]["ok"]
    ramp_nodes = [n for n in rep.get("legend_nodes", []) if n["class"] == "QgsColorRampLegendNode"]
    out["legend's ramp in the unit"] = bool(ramp_nodes) and all(n["suffix"] == f" {unit}" for n in ramp_nodes)
    out["every cell with a value drawn, none without"] = (rep["map"]["drawn_of_those"] == 1.0
                                                          and rep["map"]["drawn_without_value"] == 0)
    out["colours as the palette (median <= 2, p99 <= 4 RGB units)"] = (rep["map"]["rgb_error_median"] <= 2
                                                                        and rep["map"]["rgb_error_p99"] <= 4)
    out["exported"] = rep["export"]["ok"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ortho", default=None, help="an OUT folder of `thermogrammetry ortho` (default: a synthetic one)")
    ap.add_argument("--save", default=None, help="copy the PNG here (e.g. docs/images/ortho_qgis.png)")
    ap.add_argument("--keep", default=None, help="keep the survey, the ortho and the PNG in this folder")
    ap.add_argument("--qgis-render", nargs=2, metavar=("ORTHO_DIR", "PNG"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.qgis_render:  # step 2, in the system's Python
        rep = qgis_render(Path(args.qgis_render[0]), Path(args.qgis_render[1]))
        print(json.dumps(rep, indent=1, ensure_ascii=False, default=str), flush=True)
        # no teardown: QGIS 3.22 from Python can crash when its objects are freed after exitQgis (the work is done)
        os._exit(0 if all(rep["checks"].values()) else 1)
    if not Path(SYSTEM_PYTHON).is_file() or subprocess.run([SYSTEM_PYTHON, "-c", "import qgis.core"],
                                                           capture_output=True).returncode != 0:
        print(f"needs QGIS's Python bindings for {SYSTEM_PYTHON} (apt-get install python3-qgis)", file=sys.stderr)
        return 2
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="qgis_ortho_"))
    work.mkdir(parents=True, exist_ok=True)
    ortho = Path(args.ortho) if args.ortho else make_ortho(work)
    png = work / "ortho_qgis.png"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_RUNTIME_DIR=str(work / "xdg"))
    (work / "xdg").mkdir(mode=0o700, exist_ok=True)
    env.pop("PYTHONPATH", None)
    r = subprocess.run([SYSTEM_PYTHON, str(Path(__file__).resolve()), "--qgis-render", str(ortho), str(png)],
                       env=env, capture_output=True, text=True, timeout=600)
    print(r.stdout)
    if r.returncode not in (0, 1):
        print(r.stderr[-3000:], file=sys.stderr)
        return 1
    if args.save and png.is_file():
        shutil.copy(png, args.save)
    print("OK" if r.returncode == 0 else "FAILED", file=sys.stderr)
    return r.returncode


if __name__ == "__main__":
    raise SystemExit(main())
