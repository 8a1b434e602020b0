"""What every ``report.html`` shares: its header and its figure helpers.

The header (:class:`ReportHeader`, :func:`header_html`) states the software version, the date (UTC), the command
line, the inputs (counts and folders), the CRS, the ground sampling distance, the flying height, the area covered
and the processing time, each where the verb knows it: a value the verb does not know is left out, never guessed.
The command line is what the user typed when the verb ran from the ``thermogrammetry`` command (recorded by the CLI
with :func:`cli_command`), else the Python call of the outermost driver (recorded with :func:`driver_call`).

The figure helpers keep figures readable on real data: colour limits from percentiles, stated on the figure
(:func:`colour_limits`; one stray tie point 400 m below the ground does not stretch the colour bar), error vectors
and ellipses drawn at their map positions (:func:`vectors_at`, :func:`ellipses_at`), map axes labelled relative to
a round origin so that tick labels of UTM coordinates do not run together (:func:`map_origin`, :func:`map_axes`),
and a figure embedded as a base64 PNG (:func:`figure_png`) so that a report is one self-contained file.
"""

from __future__ import annotations

import base64
import contextlib
import html
import inspect
import io
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any, Iterator, Sequence

import numpy as np

from . import __version__

__all__ = ["ReportHeader", "header_html", "insert_header", "command_line", "cli_command", "driver_call",
           "python_call", "folders_of", "html_page", "REPORT_CSS", "ColourLimits", "colour_limits", "colourbar",
           "caption_below", "figure_png", "nice_number", "height_colormap", "log_counts_axis", "map_origin",
           "map_axes", "pad_to_ratio", "vectors_at", "ellipses_at", "thin_labels", "short_names", "format_seconds",
           "crs_text"]

# ---------------------------------------------------------------------------------------------------- command line

_CLI: str | None = None  # the command the user typed (set by the CLI for the time a verb runs)
_CALL: str | None = None  # the outermost driver's Python call


@contextlib.contextmanager
def cli_command(argv: Sequence[str]) -> Iterator[str]:
    """Record ``thermogrammetry ARGV...`` as the command line of the reports written meanwhile."""
    global _CLI
    old, _CLI = _CLI, shlex.join(["thermogrammetry", *[str(a) for a in argv]])
    try:
        yield _CLI
    finally:
        _CLI = old


def _short_repr(v: Any, limit: int = 160) -> str:
    if isinstance(v, PurePath):
        v = str(v)
    elif isinstance(v, (list, tuple)) and v and all(isinstance(x, PurePath) for x in v):
        v = type(v)(str(x) for x in v)
    r = repr(v)
    return r if len(r) <= limit else r[: limit - 1] + "…"


def python_call(fn, arguments: dict) -> str:
    """``module.function(arg, ..., key=value)`` of a call of ``fn``: ``arguments`` are its parameters by name (e.g. the
    function's ``locals()`` on entry); keyword parameters left at their default and callables (progress callbacks)
    are left out; long values are cut to 160 characters."""
    parts = []
    for name, p in inspect.signature(fn).parameters.items():
        if name not in arguments or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        v = arguments[name]
        if callable(v) and not isinstance(v, type):
            continue
        if p.default is not p.empty:
            try:
                if v is p.default or bool(v == p.default):
                    continue
            except Exception:  # noqa: BLE001 - an array or an object without a plain ==: shown
                pass
        positional = p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        parts.append(_short_repr(v) if positional else f"{name}={_short_repr(v)}")
    return f"{fn.__module__}.{fn.__qualname__}({', '.join(parts)})"


@contextlib.contextmanager
def driver_call(fn, arguments: dict) -> Iterator[str | None]:
    """Record the Python call of a driver as the command line of the reports written meanwhile, unless an outer
    driver's call (or the CLI's command) is recorded already: a report names what the user called."""
    global _CALL
    if _CALL is not None:
        yield _CALL
        return
    _CALL = python_call(fn, arguments)
    try:
        yield _CALL
    finally:
        _CALL = None


def command_line() -> str | None:
    """The command line of the report being written: the CLI's, else the outermost driver's Python call, else None."""
    return _CLI or _CALL


def folders_of(paths) -> list[str]:
    """The folders of files or folders ``paths`` (a folder is its own), absolute, in order, each once."""
    out: list[str] = []
    for p in paths or []:
        q = Path(p).expanduser()
        q = q if q.is_dir() else q.parent
        s = str(q.resolve())
        if s not in out:
            out.append(s)
    return out


# ---------------------------------------------------------------------------------------------------------- header


def format_seconds(s: float) -> str:
    """``12.3 s``, ``4 min 05 s``, ``1 h 02 min``."""
    s = float(s)
    if s < 59.95:
        return f"{s:.1f} s"
    if s < 3599.5:
        k = int(round(s))
        return f"{k // 60} min {k % 60:02d} s"
    m = int(round(s / 60))
    return f"{m // 60} h {m % 60:02d} min"


def crs_text(crs: str | None) -> str | None:
    """``EPSG:32650 (WGS 84 / UTM zone 50N)`` for a CRS pyproj knows; the text as given otherwise; None for None."""
    if not crs:
        return None
    try:
        from pyproj import CRS

        c = CRS.from_user_input(crs)
        auth = c.to_authority()
        code = f"{auth[0]}:{auth[1]}" if auth else None
        return f"{code} ({c.name})" if code else c.name
    except Exception:  # noqa: BLE001 - a CRS text pyproj does not parse is shown as given
        return str(crs)


@dataclass
class ReportHeader:
    """The header of a report (see the module docstring). ``None`` = not known to the verb: the row is left out.

    ``inputs``: ``(count, what, places)`` per kind of input (``count`` None when not counted, ``places`` the folders
    or files); ``crs``: the CRS text, ``georeferenced=False`` with ``crs`` None states the local frame; ``gsd_m``,
    ``flying_height_m``, ``area_m2`` with a few words each on what they are (``*_note``); ``seconds``: processing
    time of the verb; ``command``: None = :func:`command_line`."""

    verb: str
    inputs: list = field(default_factory=list)
    crs: str | None = None
    georeferenced: bool | None = None
    gsd_m: float | None = None
    gsd_note: str = ""
    flying_height_m: float | None = None
    flying_height_note: str = ""
    area_m2: float | None = None
    area_note: str = ""
    seconds: float | None = None
    command: str | None = None
    written_utc: str | None = None
    extra: list = field(default_factory=list)  # (label, text) rows of the verb's own

    def fields(self) -> list[tuple[str, str, str]]:
        """``(key, label, text)`` of every row the header shows, in order."""
        rows = [("software", "software", f"thermogrammetry {__version__}"),
                ("date", "report written", self.written_utc or time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()))]
        cmd = self.command or command_line()
        if cmd:
            rows.append(("command", "command", cmd))
        ins = []
        for count, what, places in self.inputs:
            places = [str(p) for p in (places or [])]
            if count is None:
                ins.append(f"{what}: {', '.join(places)}" if places else str(what))
            else:
                ins.append(f"{count} {what}" + (f" in {', '.join(places)}" if places else ""))
        if ins:
            rows.append(("inputs", "inputs", "\n".join(ins)))
        if self.crs:
            rows.append(("crs", "coordinate reference system", crs_text(self.crs)))
        elif self.georeferenced is False:
            rows.append(("crs", "coordinate reference system",
                         "none: a local frame (not georeferenced; arbitrary origin, orientation and scale)"))
        if self.gsd_m is not None and np.isfinite(self.gsd_m):
            g = float(self.gsd_m)
            rows.append(("gsd", "ground sampling distance",
                         (f"{100 * g:.1f} cm" if g < 1 else f"{g:.2f} m") + (f" ({self.gsd_note})" if self.gsd_note else "")))
        if self.flying_height_m is not None and np.isfinite(self.flying_height_m):
            rows.append(("flying_height", "flying height", f"{float(self.flying_height_m):.1f} m"
                         + (f" ({self.flying_height_note})" if self.flying_height_note else "")))
        if self.area_m2 is not None and np.isfinite(self.area_m2):
            a = float(self.area_m2)
            rows.append(("area", "area covered", (f"{a / 1e4:.2f} ha ({a:,.0f} m²)" if a >= 1e4 else f"{a:,.1f} m²")
                         + (f" ({self.area_note})" if self.area_note else "")))
        if self.seconds is not None and np.isfinite(self.seconds):
            rows.append(("time", "processing time", format_seconds(self.seconds)))
        rows += [(f"extra{k}", lab, txt) for k, (lab, txt) in enumerate(self.extra)]
        return rows


HEADER_CSS = (".tg-header{border-collapse:collapse;margin:.6em 0 1.2em 0;font-size:92%;text-align:left}"
              ".tg-header th{background:#f2f2f2;text-align:left;padding:3px 10px;border:1px solid #ccc;"
              "white-space:nowrap;vertical-align:top;font-weight:600}"
              ".tg-header td{text-align:left;padding:3px 10px;border:1px solid #ccc;vertical-align:top}"
              ".tg-header code{white-space:pre-wrap;word-break:break-all;font-size:90%}")


def header_html(h: ReportHeader) -> str:
    """The header as an HTML table with its own style (``class="tg-header"``; each row ``data-field="key"``)."""
    rows = []
    for key, label, text in h.fields():
        body = f"<code>{html.escape(text)}</code>" if key == "command" else html.escape(text).replace("\n", "<br>")
        rows.append(f"<tr data-field='{key}'><th>{html.escape(label)}</th><td>{body}</td></tr>")
    return f"<style>{HEADER_CSS}</style><table class='tg-header'>{''.join(rows)}</table>"


#: the style of the reports written with :func:`html_page`
REPORT_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222;padding:0 1em}"
              "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
              "th{background:#eee}td.l,th.l{text-align:left}.bad{color:#a00}h2{border-bottom:1px solid #ccc;margin-top:1.6em}"
              "p.caption{font-size:90%;color:#444;margin-top:0}img{max-width:100%}")


def html_page(title: str, heading: str, header: ReportHeader, parts: Sequence[str]) -> str:
    """A self-contained report page: ``heading``, the header, then ``parts`` (HTML fragments)."""
    return (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{REPORT_CSS}</style></head><body><h1>{html.escape(heading)}</h1>{header_html(header)}"
            + "".join(parts) + "</body></html>")


def insert_header(page: str, h: ReportHeader) -> str:
    """``page`` (an HTML report) with the header after its first ``</h1>`` (after ``<body>`` when it has none)."""
    block = header_html(h)
    k = page.find("</h1>")
    if k >= 0:
        return page[: k + 5] + block + page[k + 5:]
    k = page.find("<body>")
    return page[: k + 6] + block + page[k + 6:] if k >= 0 else block + page


# --------------------------------------------------------------------------------------------------------- figures


def figure_png(fig, dpi: int = 110) -> str:
    """``<img>`` of a matplotlib figure as an embedded PNG (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return f'<img style="max-width:100%" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


@dataclass(frozen=True)
class ColourLimits:
    """Colour limits from percentiles of the finite values: ``lo``, ``hi`` (the ``lower``/``upper`` percentiles),
    how many values lie ``below``/``above`` them (drawn in the end colours) out of ``n``."""

    lo: float
    hi: float
    lower: float
    upper: float
    below: int
    above: int
    n: int

    @property
    def extend(self) -> str:
        """matplotlib's colour-bar ``extend`` (arrows at the ends with values beyond them)."""
        return {(True, True): "both", (True, False): "min", (False, True): "max"}.get((self.below > 0, self.above > 0),
                                                                                      "neither")

    def caption(self, unit: str = "", digits: int | None = None) -> str:
        """``colours: 1st–99th percentile, 98.2 … 104.7 m; 14 of 2000 values below, 20 above (end colours)``."""
        span = self.hi - self.lo
        d = digits if digits is not None else (0 if span >= 100 else 1 if span >= 5 else 2 if span >= 0.1 else 4)
        u = f" {unit}" if unit else ""
        out = f"colours: {_ordinal(self.lower)}–{_ordinal(self.upper)} percentile, {self.lo:.{d}f} … {self.hi:.{d}f}{u}"
        if self.below or self.above:
            out += f"; {self.below} of {self.n} values below, {self.above} above (end colours)"
        return out


def _ordinal(p: float) -> str:
    k = int(round(p))
    if abs(p - k) > 1e-9:
        return f"{p:g}th"
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


def colour_limits(values, lower: float = 1.0, upper: float = 99.0) -> ColourLimits:
    """Colour limits robust to outliers: the ``lower`` and ``upper`` percentiles of the finite values (any shape),
    widened to a non-empty interval when they are equal; (0, 1) when no value is finite."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return ColourLimits(0.0, 1.0, lower, upper, 0, 0, 0)
    lo, hi = (float(x) for x in np.percentile(v, [lower, upper]))
    if not hi > lo:
        pad = max(abs(lo) * 1e-6, 0.5)
        lo, hi = lo - pad, hi + pad
    return ColourLimits(lo, hi, lower, upper, int((v < lo).sum()), int((v > hi).sum()), int(v.size))


def colourbar(fig, ax, mappable, label: str, limits: ColourLimits | None = None, unit: str = "", **kw):
    """A colour bar as tall as the axes (also for equal-aspect maps), labelled ``label``; with ``limits`` its arrows
    show values beyond them and the limits' caption is written under the axes' labels."""
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    cax = make_axes_locatable(ax).append_axes("right", size="3.5%", pad=0.12)
    cb = fig.colorbar(mappable, cax=cax, label=label, extend=limits.extend if limits is not None else "neither", **kw)
    cb.ax.tick_params(labelsize=8)
    if limits is not None:
        caption_below(ax, limits.caption(unit))
    return cb


def caption_below(ax, text: str, *, line: int = 0) -> None:
    """A small note under the axes, below their tick labels and axis title (placed in points, not in axes fractions,
    so that it does not run into the axis title of a flat map); ``line`` 1, 2, ...: the lines under the first."""
    ax.annotate(text, (0.0, 0.0), xycoords="axes fraction", xytext=(0, -38 - 11 * line), textcoords="offset points",
                fontsize=7.5, color="#444", va="top", ha="left")


def height_colormap():
    """The colour map of heights in the reports: the land part of matplotlib's ``terrain`` (green, yellow, brown,
    light brown), without its sea blue and its white (the colour of cells without a value)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LinearSegmentedColormap

    return LinearSegmentedColormap.from_list("heights", plt.get_cmap("terrain")(np.linspace(0.25, 0.92, 256)))


def log_counts_axis(axis) -> None:
    """A log-scaled axis of counts labelled 1, 10, 100, ... (no crowded minor labels)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}" if v >= 1 else f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def nice_number(x: float) -> float:
    """The number 1, 2 or 5 × 10^k nearest below ``x`` (> 0)."""
    if not (np.isfinite(x) and x > 0):
        return 1.0
    e = np.floor(np.log10(x))
    m = x / 10**e
    return float((5 if m >= 5 else 2 if m >= 2 else 1) * 10**e)


def map_origin(x, y) -> tuple[float, float]:
    """A round origin for map axes: coordinates whose values need more than 4 digits are shown relative to the
    multiple of 1000 m (100 m for an extent below 100 m) below their minimum; (0, 0) for small coordinates."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return 0.0, 0.0
    x, y = x[ok], y[ok]
    if max(np.abs(x).max(), np.abs(y).max()) < 1e4:
        return 0.0, 0.0
    span = max(float(np.ptp(x)), float(np.ptp(y)), 1.0)
    step = 1000.0 if span >= 100 else 100.0
    return float(np.floor(x.min() / step) * step), float(np.floor(y.min() / step) * step)


def map_axes(ax, origin=(0.0, 0.0), *, nbins: int = 6, names=("E", "N"), adjustable: str = "datalim") -> None:
    """Equal-aspect map axes with at most ``nbins`` ticks per axis, short labels and axis titles that state the
    origin (``E − 512000 (m)``). ``adjustable``: matplotlib's (``"box"`` for a raster that fills the axes)."""
    from matplotlib.ticker import MaxNLocator

    ax.set_aspect("equal", adjustable=adjustable)
    for a in (ax.xaxis, ax.yaxis):
        a.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))
    ax.tick_params(labelsize=8)
    x0, y0 = origin
    ax.set_xlabel(f"{names[0]} − {x0:.0f} (m)" if x0 else f"{'X' if names[0] == 'E' else names[0]} (m)")
    ax.set_ylabel(f"{names[1]} − {y0:.0f} (m)" if y0 else f"{'Y' if names[1] == 'N' else names[1]} (m)")


def pad_to_ratio(ax, ratio: float = 0.45) -> None:
    """Widen the shorter axis range of a map to at least ``ratio`` × the longer one (a strip of cameras along one line
    is not drawn as a sliver)."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    w, h = x1 - x0, y1 - y0
    if h < ratio * w:
        c = 0.5 * (y0 + y1)
        ax.set_ylim(c - 0.5 * ratio * w, c + 0.5 * ratio * w)
    elif w < ratio * h:
        c = 0.5 * (x0 + x1)
        ax.set_xlim(c - 0.5 * ratio * h, c + 0.5 * ratio * h)


def _map_scale(ax_extent: float, largest: float, share: float) -> float:
    """Magnification (a round number) drawing ``largest`` as at most ``share`` of ``ax_extent``."""
    if not (largest > 0 and ax_extent > 0):
        return 1.0
    return nice_number(share * ax_extent / largest)


def vectors_at(ax, xy, dxy, *, origin=(0.0, 0.0), extent: float | None = None, share: float = 0.12,
               color="#c33"):
    """Arrows at the map positions ``xy`` (n, 2; map units) with components ``dxy`` (n, 2; metres), magnified so that
    the longest is about ``share`` of the map's extent (a round magnification, stated with a key arrow of a round
    length near the longest). Returns ``(quiver, magnification)``."""
    xy, d = np.asarray(xy, float).reshape(-1, 2), np.asarray(dxy, float).reshape(-1, 2)
    p = xy - np.asarray(origin, float)
    if extent is None:
        extent = max(float(np.ptp(p[:, 0])) if len(p) else 0.0, float(np.ptp(p[:, 1])) if len(p) else 0.0, 1.0)
    longest = float(np.nanmax(np.hypot(d[:, 0], d[:, 1]))) if len(d) else 0.0
    mag = _map_scale(extent, longest, share)
    q = ax.quiver(p[:, 0], p[:, 1], d[:, 0] * mag, d[:, 1] * mag, angles="xy", scale_units="xy", scale=1.0,
                  color=color, width=0.004, zorder=5)
    key = nice_number(longest) if longest > 0 else 0.01
    label = f"{key * 100:g} cm" if key < 1 else f"{key:g} m"
    ax.quiverkey(q, 0.78, 1.03, key * mag, f"{label} (arrows ×{mag:g})", labelpos="E", coordinates="axes",
                 fontproperties={"size": 8})
    return q, mag


def ellipses_at(ax, xy, cov2, *, origin=(0.0, 0.0), extent: float | None = None, share: float = 0.04,
                color: str = "#1f5fa8") -> float:
    """Error ellipses (1 σ) of the horizontal covariances ``cov2`` (n, 2, 2; m²) centred at the map positions ``xy``
    (n, 2), magnified so that the median semi-major axis is about ``share`` of the map's extent (a round
    magnification). Returns the magnification (0 when no covariance is finite)."""
    from matplotlib.patches import Ellipse

    xy = np.asarray(xy, float).reshape(-1, 2) - np.asarray(origin, float)
    C = np.asarray(cov2, float).reshape(-1, 2, 2)
    ok = np.isfinite(C).all(axis=(1, 2)) & np.isfinite(xy).all(axis=1)
    if not ok.any():
        return 0.0
    ev, evec = np.linalg.eigh(C[ok])
    a = np.sqrt(np.maximum(ev[:, 1], 0.0))
    b = np.sqrt(np.maximum(ev[:, 0], 0.0))
    ang = np.degrees(np.arctan2(evec[:, 1, 1], evec[:, 0, 1]))
    if extent is None:
        extent = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0)
    mag = _map_scale(extent, float(np.median(a)), share)
    for (x, y), ai, bi, t in zip(xy[ok], a, b, ang):
        ax.add_patch(Ellipse((x, y), 2 * ai * mag, 2 * bi * mag, angle=t, fill=False, edgecolor=color, lw=1.0,
                             zorder=4))
    return mag


def short_names(names: Sequence[str], max_len: int = 12) -> list[str]:
    """Image names shortened for an axis: the fewest trailing ``_``/``-``-separated parts that keep them apart
    (``DJI_20240806173449_0008_T`` → ``0008_T``), cut to their last ``max_len`` characters."""
    import re

    names = [str(n) for n in names]
    parts = [re.split(r"(?<=[_-])", n) for n in names]
    for k in range(1, max((len(p) for p in parts), default=1) + 1):
        tails = ["".join(p[-k:]) for p in parts]
        if len(set(tails)) == len(set(names)):
            return [t[-max_len:] for t in tails]
    return [n[-max_len:] for n in names]


def thin_labels(ax, labels: Sequence[str], *, max_labels: int = 40, rotation: float = 90, fontsize: float = 7) -> None:
    """Category tick labels on the x axis, every k-th one when there are more than ``max_labels``."""
    n = len(labels)
    k = max(1, int(np.ceil(n / max_labels)))
    idx = list(range(0, n, k))
    ax.set_xticks(idx)
    ax.set_xticklabels([labels[i] for i in idx], rotation=rotation, fontsize=fontsize)
