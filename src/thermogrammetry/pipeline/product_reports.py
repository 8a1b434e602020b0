"""``report.html`` of ``dense`` and ``ortho``: the header (:mod:`thermogrammetry.reporting`), the product as a
picture with its legend, how complete it is and what was filled.

dense: the DSM as a hillshade coloured by height (colour limits from the 1st and 99th percentiles, stated on the
figure), a map of measured, filled and empty cells, the point count and completeness. ortho: the mosaic in the
palette and limits of ``ortho.qml`` (legend in the mosaic's unit: °C, K or counts), a map of the cells with a
value, those on filled DSM heights and the empty ones, and the σ map of ``ortho_sigma.tif`` when it was written.
Rasters are read decimated to at most :data:`PREVIEW_PX` cells a side (the figures are previews, the files hold
the values).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..reporting import (ColourLimits, ReportHeader, colour_limits, colourbar, figure_png, height_colormap, html_page,
                         map_axes, map_origin)

__all__ = ["PREVIEW_PX", "dense_report_html", "ortho_report_html", "raster_preview"]

#: largest side (cells) of a raster as read for a report figure
PREVIEW_PX = 900
_EMPTY = "#ececec"  # cells without a value (the figures' background)


def raster_preview(path, band: int = 1, max_px: int = PREVIEW_PX) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Band ``band`` of a GeoTIFF read decimated to at most ``max_px`` cells a side (nodata → NaN) and its extent
    ``(xmin, xmax, ymin, ymax)`` (m). Every preview cell is one cell of the raster (nearest, from the full resolution:
    not from the averaged overviews, whose cells have a value where any of the cells they average has one)."""
    import rasterio

    with rasterio.open(path, OVERVIEW_LEVEL="NONE") as src:
        k = max(1, int(np.ceil(max(src.width, src.height) / max_px)))
        shape = (max(1, int(np.ceil(src.height / k))), max(1, int(np.ceil(src.width / k))))
        a = src.read(band, out_shape=shape, masked=True)
        tr = src.transform
        ext = (tr.c, tr.c + src.width * tr.a, tr.f + src.height * tr.e, tr.f)
    return np.asarray(a.astype(np.float64).filled(np.nan)), ext


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _map(ext, size=(7.6, 6.2)):
    """A figure and map axes for a raster of extent ``ext``; returns ``(fig, ax, shifted extent, origin)``."""
    plt = _plt()
    ox, oy = map_origin(ext[:2], ext[2:])
    fig, ax = plt.subplots(figsize=size)
    e = (ext[0] - ox, ext[1] - ox, ext[2] - oy, ext[3] - oy)
    ax.set_facecolor("white")
    return fig, ax, e, (ox, oy)


def _hillshade_figure(z: np.ndarray, ext) -> str:
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LightSource, Normalize, to_rgba

    lim = colour_limits(z, 1.0, 99.0)
    fig, ax, e, origin = _map(ext)
    ok = np.isfinite(z)
    cmap = height_colormap()
    norm = Normalize(lim.lo, lim.hi, clip=True)
    dx = (ext[1] - ext[0]) / max(1, z.shape[1])
    zf = np.where(ok, z, float(np.nanmedian(z)) if ok.any() else 0.0)
    rgb = LightSource(azdeg=315, altdeg=45).shade(zf, cmap=cmap, norm=norm, blend_mode="soft", vert_exag=1.0,
                                                  dx=dx, dy=dx)
    rgb[~ok] = to_rgba(_EMPTY)
    ax.imshow(rgb, extent=e, origin="upper", interpolation="nearest")
    colourbar(fig, ax, ScalarMappable(norm=norm, cmap=cmap), "height (m)", lim, "m")
    map_axes(ax, origin, adjustable="box")
    ax.set_title("DSM: hillshade (sun from the north-west, 45°), colours by height", fontsize=10)
    return figure_png(fig)


def _cells_figure(classes: np.ndarray, ext, labels: list[tuple[int, str, str]], title: str, shares=None,
                  total: int | None = None) -> str:
    """A categorical map: ``classes`` (h, w) ints, ``labels`` (value, colour, legend text) in legend order;
    ``shares``: {value: share of the raster's ``total`` cells} counted on the full raster (else on the preview)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    fig, ax, e, origin = _map(ext)
    vals = [v for v, _, _ in labels]
    lut = np.zeros(max(vals) + 1, int)
    for k, v in enumerate(vals):
        lut[v] = k
    ax.imshow(lut[classes], extent=e, origin="upper", interpolation="nearest",
              cmap=ListedColormap([c for _, c, _ in labels]), vmin=-0.5, vmax=len(labels) - 0.5)
    if shares is None:
        shares, total = {v: float(np.mean(classes == v)) for v, _, _ in labels}, None
    ax.legend(handles=[Patch(facecolor=c, edgecolor="#888", label=f"{t}: {100 * shares[v]:.1f} %")
                       for v, c, t in labels],
              loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
              title=f"share of the box's {total:,} cells" if total else f"share of the {classes.size:,} preview cells",
              title_fontsize=8)
    map_axes(ax, origin, adjustable="box")
    ax.set_title(title, fontsize=10)
    return figure_png(fig)


def _safe(draw, *args) -> str:
    """A figure, or one line saying why it was not drawn (a figure must not lose the products: the report is written
    last, after every raster)."""
    try:
        return draw(*args)
    except Exception as exc:  # noqa: BLE001
        _plt().close("all")
        return f"<p class=bad>figure not drawn: {html.escape(type(exc).__name__)}: {html.escape(str(exc))}</p>"


def _row(label: str, value) -> str:
    return f"<tr><th class=l>{html.escape(label)}</th><td class=l>{html.escape(str(value))}</td></tr>"


def _notes(notes) -> list[str]:
    return ["<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>"] if notes else []


def median_height(path) -> float | None:
    """Median of the finite heights of a DSM preview (m), None when it holds none."""
    z, _ = raster_preview(path, 1, 400)
    return float(np.nanmedian(z)) if np.isfinite(z).any() else None


def survey_header(verb: str, sv, survey_dir, *, crs, gsd_m, gsd_note, ground_z, area_m2, area_note, seconds,
                  more_inputs=()) -> ReportHeader:
    """The header of a product of a survey folder: its oriented images, the CRS, the cell size, the flying height
    (median camera height above ``ground_z``, the product's median height) and the area."""
    C = np.array([im.center for im in sv.images], float)
    fh = float(np.median(C[:, 2]) - ground_z) if ground_z is not None and len(C) else None
    inputs = [(len(sv), "oriented images of the survey", [str(Path(survey_dir).resolve())])]
    if sv.skipped:
        inputs.append((len(sv.skipped), "frames skipped (damaged or unreadable)", []))
    inputs += list(more_inputs)
    return ReportHeader(verb, inputs=inputs, crs=crs, georeferenced=crs is not None, gsd_m=gsd_m, gsd_note=gsd_note,
                        flying_height_m=fh if fh is not None and fh > 0 else None,
                        flying_height_note="median camera height above the median height of the DSM",
                        area_m2=area_m2, area_note=area_note, seconds=seconds)


def dense_report_html(out: Path, rep: dict, sv, survey_dir) -> str:
    """The page of ``dense`` from its staged outputs in ``out`` and ``dense.json`` (``rep``)."""
    out = Path(out)
    z, ext = raster_preview(out / "dsm.tif")
    d = rep["dsm"]
    header = survey_header("dense", sv, survey_dir, crs=rep.get("crs"), gsd_m=rep["gsd_m"], gsd_note="DSM cell",
                           ground_z=float(np.nanmedian(z)) if np.isfinite(z).any() else None,
                           area_m2=d["valid_cells"] * rep["gsd_m"] ** 2, area_note="DSM cells with a measured height",
                           seconds=rep.get("seconds"))
    parts = []
    filled_rec = rep.get("dsm_filled")
    cells = d["width"] * d["height"]
    rows = [_row("dense points (cloud.las, cloud.ply)", f"{rep['points']:,}"),
            _row("DSM", f"{d['width']} × {d['height']} cells of {rep['gsd_m']:g} m"),
            _row("cells with a measured height", f"{d['valid_cells']:,} ({100 * d['valid_cells'] / max(cells, 1):.1f} % of the box)"),
            _row("completeness", f"{100 * rep['completeness']:.1f} % ({rep.get('completeness_definition', '')})"),
            _row("values of the cloud", f"{rep.get('value_dimension') or 'none'} ({rep.get('unit')})")]
    if d.get("filled_cells") is not None:
        rows.append(_row("dsm.tif band 2 (--fill)", f"{d['filled_cells']:,} cells filled from their nearest neighbour"))
    if filled_rec:
        rows.append(_row("dsm_filled.tif", f"{filled_rec['filled_cells']:,} cells interpolated (holes up to "
                         f"{filled_rec['max_hole_m']:g} m across; {filled_rec['empty_cells']:,} cells left empty): "
                         f"{filled_rec['method']}"))
    else:
        rows.append(_row("filled", "nothing: dsm.tif holds the measured heights only (no dsm_filled.tif)"))
    parts.append("<h2>Summary</h2><table>" + "".join(rows) + "</table>")
    fig = _safe(_hillshade_figure, z, ext)
    parts.append("<h2>DSM</h2>" + fig + "<p class=caption>dsm.tif as measured (no filled cell); grey: no height.</p>")
    classes = np.where(np.isfinite(z), 1, 0)
    labels = [(1, "#6a8caf", "measured height"), (0, _EMPTY, "no height")]
    fill_src, n_filled = None, 0
    if filled_rec and (out / filled_rec["file"]).is_file():
        fill_src, fill_band, n_filled = out / filled_rec["file"], 2, filled_rec["filled_cells"]
    elif d.get("filled_cells") is not None:
        fill_src, fill_band, n_filled = out / "dsm.tif", 2, d["filled_cells"]
    if fill_src is not None:
        m, _ = raster_preview(fill_src, fill_band)
        classes = np.where((classes == 0) & (np.nan_to_num(m) > 0), 2, classes)
        labels.insert(1, (2, "#f28e2b", f"filled ({fill_src.name})"))
    shares = {1: d["valid_cells"] / max(cells, 1), 2: n_filled / max(cells, 1),
              0: (cells - d["valid_cells"] - n_filled) / max(cells, 1)}
    parts.append("<h2>Completeness and what was filled</h2>"
                 + _safe(_cells_figure, classes, ext, labels, "DSM cells: measured, filled, empty", shares, cells)
                 + "<p class=caption>Shares of the DSM's box (the completeness above counts only the cells inside the "
                   "images' footprints).</p>")
    parts += _notes(rep.get("notes"))
    return html_page("thermogrammetry dense", "Dense cloud and DSM report", header, parts)


def _thermal_cmap():
    from matplotlib.colors import LinearSegmentedColormap

    from ..products.qml import THERMAL_PALETTE

    return LinearSegmentedColormap.from_list("thermal", list(THERMAL_PALETTE))


def _value_label(unit: str) -> str:
    return {"°C": "temperature (°C)", "K": "temperature (K)", "counts": "raw sensor counts (not a temperature)",
            "dn": "display numbers (not a temperature)"}.get(unit, unit)


def _ortho_figure(v: np.ndarray, ext, style: dict, unit: str) -> str:
    from matplotlib.colors import Normalize

    finite = v[np.isfinite(v)]
    lo, hi = float(style["min"]), float(style["max"])
    lim = ColourLimits(lo, hi, 2.0, 98.0, int((finite < lo).sum()), int((finite > hi).sum()), int(finite.size))
    fig, ax, e, origin = _map(ext)
    cmap = _thermal_cmap().with_extremes(bad=_EMPTY)
    im = ax.imshow(np.ma.masked_invalid(v), extent=e, origin="upper", interpolation="nearest", cmap=cmap,
                   norm=Normalize(lo, hi))
    colourbar(fig, ax, im, _value_label(unit), lim, unit)
    map_axes(ax, origin, adjustable="box")
    ax.set_title("Orthophoto (palette and limits of ortho.qml)", fontsize=10)
    return figure_png(fig)


def _sigma_figure(s: np.ndarray, ext, unit: str) -> str:
    plt = _plt()
    lim = colour_limits(s, 1.0, 99.0)
    fig, ax, e, origin = _map(ext)
    cmap = plt.get_cmap("viridis").with_extremes(bad=_EMPTY)
    im = ax.imshow(np.ma.masked_invalid(s), extent=e, origin="upper", interpolation="nearest", cmap=cmap,
                   vmin=lim.lo, vmax=lim.hi)
    colourbar(fig, ax, im, f"σ, total random ({unit})", lim, unit)
    map_axes(ax, origin, adjustable="box")
    ax.set_title("Standard deviation of each cell (ortho_sigma.tif band 1)", fontsize=10)
    return figure_png(fig)


def ortho_report_html(out: Path, rep: dict, sv, survey_dir, dsm_path) -> str:
    """The page of ``ortho`` from its staged outputs in ``out`` and ``ortho.json`` (``rep``)."""
    out = Path(out)
    unit = rep["unit"]
    v, ext = raster_preview(out / "ortho.tif")
    box = max(1, rep["width"] * rep["height"])
    header = survey_header("ortho", sv, survey_dir, crs=rep.get("crs"), gsd_m=rep["gsd_m"], gsd_note="mosaic cell",
                           ground_z=median_height(dsm_path), area_m2=rep["cells"] * rep["gsd_m"] ** 2,
                           area_note="mosaic cells with a value", seconds=rep.get("seconds"),
                           more_inputs=[(None, "DSM", [str(Path(dsm_path).resolve())])])
    fill = rep.get("fill")
    rows = [_row("mosaic", f"{rep['width']} × {rep['height']} cells of {rep['gsd_m']:g} m, values in {unit} "
                 f"({_value_label(unit)})"),
            _row("cells with a value", f"{rep['cells']:,} ({100 * rep['cells'] / box:.1f} % of the box)"),
            _row("images used", f"{rep['images_used']} of {len(rep.get('images', {}))}"),
            _row("sampling", f"{rep['sampling']}, viewing angle ≤ {rep['max_angle_deg']:g}°, one source image per "
                 "cell (no blending)")]
    if fill:
        rows.append(_row("surface filled", f"{fill['filled_cells']:,} DSM cells interpolated (holes up to "
                         f"{fill['max_hole_m']:g} m across): {fill['method']}; {fill['ortho_cells_on_filled']:,} mosaic "
                         f"cells ({100 * fill['ortho_cells_on_filled'] / max(rep['cells'], 1):.1f} %) lie on them "
                         f"({fill['mask']})"))
    else:
        rows.append(_row("surface filled", "nothing (--no-fill): the DSM as given; cells over its holes are empty"))
    if rep.get("corrected"):
        rows.append(_row("correction", "per-cell viewing angle, emissivity and transmission correction applied"))
    sig = rep.get("sigma")
    if sig:
        t = sig.get("total", {})
        if t.get("median") is not None:
            rows.append(_row("σ of a cell (total random)", f"median {t['median']:.3g} {unit}, 95th percentile "
                             f"{t['p95']:.3g} {unit}"))
    parts = ["<h2>Summary</h2><table>" + "".join(rows) + "</table>"]
    img = _safe(_ortho_figure, v, ext, rep["style"], unit)
    parts.append("<h2>Orthophoto</h2>" + img + "<p class=caption>ortho.tif (preview); grey: no value.</p>")
    classes = np.where(np.isfinite(v), 1, 0)
    labels = [(1, "#6a8caf", "value on measured heights"), (0, _EMPTY, "no value")]
    on_filled = 0
    if fill and (out / fill["mask"]).is_file():
        m, _ = raster_preview(out / fill["mask"])
        classes = np.where((classes == 1) & (m == 1), 2, classes)
        labels.insert(1, (2, "#f28e2b", "value on filled heights"))
        on_filled = fill["ortho_cells_on_filled"]
    shares = {1: (rep["cells"] - on_filled) / box, 2: on_filled / box, 0: 1.0 - rep["cells"] / box}
    parts.append("<h2>Coverage and what was filled</h2>"
                 + _safe(_cells_figure, classes, ext, labels, "Mosaic cells: on measured heights, on filled heights, empty",
                         shares, box)
                 + "<p class=caption>Shares of the mosaic's box. A cell on filled heights holds a copy of a source "
                   "pixel too; where the interpolated height is wrong, that pixel shows a neighbouring ground "
                   "point.</p>")
    if sig and (out / "ortho_sigma.tif").is_file():
        s, sext = raster_preview(out / "ortho_sigma.tif", 1)
        img = _safe(_sigma_figure, s, sext, unit)
        parts.append("<h2>Precision of each cell</h2>" + img + "<p class=caption>Sensor noise, pose and surface σ "
                     "(and the correction's inputs) propagated to each cell; systematic errors (the camera's "
                     "radiometric calibration) not included.</p>")
    parts += _notes(rep.get("notes"))
    return html_page("thermogrammetry ortho", "Orthophoto report", header, parts)
