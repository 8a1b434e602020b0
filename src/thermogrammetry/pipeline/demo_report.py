"""The demo's report: ``report.html`` (environment, timing per section, every row with its bound and verdict)."""

from __future__ import annotations

import html
import json
import math
import platform

from .demo_registry import DEMO_SECTIONS, DemoResult

__all__ = [
    "report_html",
    "rows_json",
]


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
