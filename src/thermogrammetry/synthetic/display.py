"""8-bit renderings of thermal frames as a camera exports them: a per-frame stretch (AGC), grey or a palette, and
optionally the camera's display burned in.

Hand-held thermal cameras and their apps export JPEGs and record videos of what the screen shows: the frame through
a palette with an automatic range, and on top of it the maker's name, the spot meter's reading and cross-hair, a
colour bar labelled with the frame's range, the date. Those marks stay at the same pixels while the scene moves:
the case :func:`thermogrammetry.sfm.features.static_overlay` finds and masks. :func:`display_mask` gives the pixels
the display covers, for tests.
"""

from __future__ import annotations

import numpy as np

__all__ = ["render_8bit", "burn_display", "display_mask"]


def render_8bit(frame, *, mode: str = "grey", display: bool = False, percentiles=(1.0, 99.0)) -> np.ndarray:
    """An 8-bit rendering of one frame, stretched between its own ``percentiles`` (the camera's AGC).

    Parameters
    ----------
    frame : (H, W) float kelvin (NaN = no data, drawn black)
    mode : "grey" -> (H, W) uint8, or "palette" -> (H, W, 3) uint8 RGB through matplotlib's 'inferno'
    display : burn the camera's display in (:func:`burn_display`), with this frame's range and centre reading
    """
    a = np.asarray(frame, float)
    ok = np.isfinite(a)
    lo, hi = np.percentile(a[ok], percentiles) if ok.any() else (0.0, 1.0)
    g = np.clip((np.where(ok, a, lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    if mode == "grey":
        img = np.round(g * 255).astype(np.uint8)
        cmap = None
    elif mode == "palette":
        import matplotlib

        cmap = matplotlib.colormaps["inferno"]
        img = (cmap(g)[..., :3] * 255).round().astype(np.uint8)
    else:
        raise ValueError(f"mode={mode!r}: expected 'grey' or 'palette'")
    if display:
        h, w = a.shape
        spot = float(a[h // 2, w // 2]) if ok[h // 2, w // 2] else float(lo)
        img = burn_display(img, float(lo), float(hi), spot, cmap)
    return img


def burn_display(img: np.ndarray, lo_k: float, hi_k: float, spot_k: float, cmap=None) -> np.ndarray:
    """A copy of an 8-bit frame (grey or RGB) with a hand-held camera's display burned in: the maker's name and the
    spot meter's reading in °C (top left), a centre cross-hair, a colour bar on the right with the frame's range above
    and below it (the numbers change with the AGC), the date (bottom left); white with a dark outline. ``cmap``: the
    palette of the colour bar (None: grey). Sizes scale with the frame's height (designed at 512 px)."""
    import cv2

    out = np.ascontiguousarray(np.array(img, np.uint8, copy=True))
    for shape in _display_shapes(out.shape[0], out.shape[1], lo_k, hi_k, spot_k):
        _draw(out, shape, cmap)
    return out


def display_mask(height: int, width: int) -> np.ndarray:
    """(H, W) bool: the pixels that :func:`burn_display` may change on a frame of this size (every reading's digits
    drawn over each other: the union of the marks for readings of 0.0 .. 99.9 °C, 1 px of anti-aliasing added)."""
    import cv2

    m = np.zeros((height, width), np.uint8)
    for digits in ("0.0", "11.1", "44.4", "88.8", "-8.8", "77.7", "55.5", "22.2", "99.9", "33.3", "66.6"):
        v = float(digits) + 273.15
        for shape in _display_shapes(height, width, v, v, v):
            _draw(m, shape, None, mask=True)
    return cv2.dilate(m, np.ones((3, 3), np.uint8)).astype(bool)


def _display_shapes(h: int, w: int, lo_k: float, hi_k: float, spot_k: float) -> list:
    s = h / 512.0
    cx, cy, r = w // 2, h // 2, int(18 * s)
    x0, x1, y0, y1 = w - int(34 * s), w - int(16 * s), int(70 * s), h - int(70 * s)
    return [("text", "TGCAM", (int(12 * s), int(30 * s)), 0.8, s),
            ("text", f"Sp1 {spot_k - 273.15:4.1f} C", (int(12 * s), int(62 * s)), 0.7, s),
            ("cross", (cx, cy), r, s),
            ("bar", (x0, x1, y0, y1)),
            ("text", f"{hi_k - 273.15:4.1f}", (x0 - int(40 * s), y0 - int(12 * s)), 0.6, s),
            ("text", f"{lo_k - 273.15:4.1f}", (x0 - int(40 * s), y1 + int(28 * s)), 0.6, s),
            ("text", "2026-11-28 10:42", (int(12 * s), h - int(14 * s)), 0.6, s)]


def _draw(out: np.ndarray, shape, cmap, mask: bool = False) -> None:
    import cv2

    colour = 1 if mask else ((255, 255, 255) if out.ndim == 3 else 255)
    dark = 1 if mask else ((0, 0, 0) if out.ndim == 3 else 0)
    kind = shape[0]
    if kind == "text":
        _, t, org, scale, s = shape
        for c, th in ((dark, 4), (colour, 2)):
            cv2.putText(out, t, org, cv2.FONT_HERSHEY_SIMPLEX, scale * s, c, max(1, int(round(th * s))), cv2.LINE_AA)
    elif kind == "cross":
        _, (cx, cy), r, s = shape
        for c, th in ((dark, 4), (colour, 2)):
            t = max(1, int(th * s))
            cv2.line(out, (cx - r, cy), (cx - r // 3, cy), c, t)
            cv2.line(out, (cx + r // 3, cy), (cx + r, cy), c, t)
            cv2.line(out, (cx, cy - r), (cx, cy - r // 3), c, t)
            cv2.line(out, (cx, cy + r // 3), (cx, cy + r), c, t)
    else:
        _, (x0, x1, y0, y1) = shape
        if mask:
            out[y0:y1, x0:x1] = 1
            return
        ramp = np.linspace(1.0, 0.0, y1 - y0)
        if cmap is None:
            bar = np.round(ramp * 255).astype(np.uint8)[:, None]
            out[y0:y1, x0:x1] = bar if out.ndim == 2 else bar[..., None]
        else:
            out[y0:y1, x0:x1] = (cmap(ramp)[:, :3] * 255).round().astype(np.uint8)[:, None, :]
