"""QGIS layer style (``.qml``) for a single-band thermal raster: pseudocolour over band 1 with a thermal palette.

QGIS applies ``ortho.qml`` automatically when it opens ``ortho.tif`` from the same folder (a style file beside a
raster of the same base name is its default style). The style is QGIS's ``singlebandpseudocolor`` renderer with an
interpolated colour ramp (``colorrampshader``) from the robust minimum to the robust maximum of the values
(:func:`robust_limits`: the 2nd and 98th percentiles, so that a few hot or cold outliers do not take the ramp), each
legend entry labelled in the raster's unit (``°C``, ``K``, ``counts``: the raster's own, never converted). The
continuous legend QGIS draws (a ramp with its end values) takes the unit as its suffix and the entries' decimals (a
number format; without it QGIS prints four decimals, "41.3209 °C").
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

__all__ = ["THERMAL_PALETTE", "robust_limits", "thermal_qml"]

#: the "inferno"-like thermal palette (perceptually uniform, dark = cold, bright = warm): (position 0..1, "#rrggbb")
THERMAL_PALETTE = (
    (0.0, "#000004"), (0.125, "#1b0c41"), (0.25, "#4a0c6b"), (0.375, "#781c6d"), (0.5, "#a52c60"),
    (0.625, "#cf4446"), (0.75, "#ed6925"), (0.875, "#fb9b06"), (1.0, "#fcffa4"),
)


def robust_limits(values: np.ndarray, lower: float = 2.0, upper: float = 98.0) -> tuple[float, float]:
    """(lo, hi): the ``lower`` and ``upper`` percentiles of the finite values (any shape); (0, 1) when none is
    finite; widened to a non-empty interval when every value is the same."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [lower, upper]))
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def _label(v: float, unit: str, digits: int) -> str:
    return f"{v:.{digits}f} {unit}"


def thermal_qml(lo: float, hi: float, unit: str, *, band: int = 1) -> str:
    """The text of a QGIS style file: band ``band`` in pseudocolour from ``lo`` to ``hi`` (values outside take the
    end colours), legend entries labelled ``"<value> <unit>"`` (``unit``: ``"°C"``, ``"K"``, ``"counts"``...)."""
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValueError(f"style limits {lo!r}..{hi!r}: expected finite numbers with lo < hi")
    span = hi - lo
    digits = 0 if span >= 50 else 1 if span >= 5 else 2
    items = []
    for pos, colour in THERMAL_PALETTE:
        v = lo + pos * span
        items.append(f'          <item alpha="255" value="{v:.6g}" label={quoteattr(_label(v, unit, digits))} '
                     f'color="{colour}"/>')
    stops = ":".join(f"{pos:g};{int(c[1:3], 16)},{int(c[3:5], 16)},{int(c[5:7], 16)},255"
                     for pos, c in THERMAL_PALETTE[1:-1])
    c0, c1 = THERMAL_PALETTE[0][1], THERMAL_PALETTE[-1][1]

    def rgba(c):
        return f"{int(c[1:3], 16)},{int(c[3:5], 16)},{int(c[5:7], 16)},255"

    suffix = quoteattr(f" {unit}")
    return f"""<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.28.0" styleCategories="AllStyleCategories">
  <pipe>
    <rasterrenderer type="singlebandpseudocolor" band="{int(band)}" opacity="1" alphaBand="-1" nodataColor=""
                    classificationMin="{lo:.6g}" classificationMax="{hi:.6g}">
      <rasterTransparency/>
      <minMaxOrigin>
        <limits>None</limits>
        <extent>WholeRaster</extent>
        <statAccuracy>Exact</statAccuracy>
        <cumulativeCutLower>0.02</cumulativeCutLower>
        <cumulativeCutUpper>0.98</cumulativeCutUpper>
        <stdDevFactor>2</stdDevFactor>
      </minMaxOrigin>
      <rastershader>
        <colorrampshader colorRampType="INTERPOLATED" classificationMode="1" clip="0"
                         minimumValue="{lo:.6g}" maximumValue="{hi:.6g}" labelPrecision="{digits}">
          <colorramp type="gradient" name="[source]">
            <Option type="Map">
              <Option type="QString" name="color1" value="{rgba(c0)}"/>
              <Option type="QString" name="color2" value="{rgba(c1)}"/>
              <Option type="QString" name="discrete" value="0"/>
              <Option type="QString" name="rampType" value="gradient"/>
              <Option type="QString" name="stops" value="{stops}"/>
            </Option>
          </colorramp>
{chr(10).join(items)}
          <rampLegendSettings minimumLabel="" maximumLabel="" prefix="" suffix={suffix} direction="0"
                              useContinuousLegend="1" orientation="2">
            <numericFormat id="basic">
              <Option type="Map">
                <Option type="QChar" name="decimal_separator" value=""/>
                <Option type="int" name="decimals" value="{digits}"/>
                <Option type="int" name="rounding_type" value="0"/>
                <Option type="bool" name="show_plus" value="false"/>
                <Option type="bool" name="show_thousand_separator" value="false"/>
                <Option type="bool" name="show_trailing_zeros" value="true"/>
                <Option type="QChar" name="thousand_separator" value=""/>
              </Option>
            </numericFormat>
          </rampLegendSettings>
        </colorrampshader>
      </rastershader>
    </rasterrenderer>
    <brightnesscontrast brightness="0" contrast="0" gamma="1"/>
    <huesaturation saturation="0" grayscaleMode="0" colorizeOn="0" colorizeRed="255" colorizeGreen="128"
                   colorizeBlue="128" colorizeStrength="100"/>
    <rasterresampler maxOversampling="2"/>
  </pipe>
  <blendMode>0</blendMode>
</qgis>
"""
