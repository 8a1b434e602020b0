"""Test helper: the header of a report.html (``thermogrammetry.reporting.header_html``) as ``{field: text}``."""

from __future__ import annotations

import re


def header_fields(page: str) -> dict:
    """``data-field`` → the text of its cell (tags removed, ``<br>`` as a newline, HTML entities decoded)."""
    import html

    out = {}
    for key, cell in re.findall(r"<tr data-field='([a-z_0-9]+)'><th>[^<]*</th><td>(.*?)</td></tr>", page):
        out[key] = html.unescape(re.sub(r"<[^>]+>", "", cell.replace("<br>", "\n")))
    return out
