"""Flight planning for a thermal survey: height, line spacing, trigger distance, video extraction rate.

For a nadir camera over flat ground at height ``H`` above it, with focal length ``f`` (px) and image size
``W × H_img`` (px)::

    GSD          = H / f                       (m per pixel)
    footprint    = GSD · W  across,  GSD · H_img  along track   (image y axis along the flight)
    trigger      = (1 − p) · footprint_along   (p: forward overlap)
    line spacing = (1 − q) · footprint_across  (q: sidelap)
    video        : keep every k-th frame, k = floor(trigger / (v / fps)); extraction rate fps / k

Khodaei et al. (2015) plan a thermal video flight with 80 % forward overlap and 60 % sidelap (more than
the 60 %/20 % of manned photogrammetry, for a platform that rolls and pitches) and extract frames at the
rate that the frame rate, the speed and the height give. Lines are laid parallel to the longest side of
the area's minimum-area rectangle (or a given heading), cover the polygon with half a footprint of margin
at both ends, and are flown in a serpentine.

Coordinates: a projected CRS (metres). :func:`plan_flight` is pure; reading an area file and writing
CSV/KML are separate (:func:`read_area`, :func:`waypoints_csv`, :func:`waypoints_kml`).

References
----------
.. [1] Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
   thermal imagery. ISPRS Archives XL-1/W5, 401–405 (§2.2 flight planning, §2.3.1 frame extraction).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import ConfigError, DataFileError

__all__ = ["FlightPlan", "Waypoint", "plan_flight", "read_area", "waypoints_csv", "waypoints_kml", "utm_epsg", "DEFAULT_MAX_PHOTOS"]


@dataclass(frozen=True)
class Waypoint:
    """A waypoint: ``kind`` is ``start``/``end`` of a line or ``photo`` (a trigger position)."""

    id: int
    line: int
    kind: str
    x: float
    y: float
    z: float


@dataclass
class FlightPlan:
    """A planned flight (lengths in metres, angles in degrees from north, clockwise)."""

    height_m: float
    gsd_m: float
    footprint_along_m: float
    footprint_across_m: float
    forward_overlap: float
    sidelap: float
    trigger_distance_m: float
    line_spacing_m: float
    heading_deg: float
    n_lines: int
    n_photos: int
    flight_length_m: float
    area_m2: float
    speed_mps: float | None = None
    flight_time_s: float | None = None
    video_fps: float | None = None
    extract_every_n_frames: int | None = None
    extraction_rate_hz: float | None = None
    trigger_interval_s: float | None = None
    crs: str | None = None
    notes: list[str] = field(default_factory=list)
    waypoints: list[Waypoint] = field(default_factory=list)

    def summary(self) -> dict:
        d = asdict(self)
        d.pop("waypoints")
        return d


#: the highest flight a plan is made for (m above ground): above any survey aircraft; a GSD or a height in the wrong
#: unit (cm for m) is refused rather than planned 1000 km up
MAX_HEIGHT_M = 20_000.0


def _check_positive(name, v):
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}={v!r}: expected a positive number") from None
    if not (np.isfinite(v) and v > 0):
        raise ConfigError(f"{name}={v!r}: expected a positive number")
    return v


def _polygon_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _long_axis_angle(poly: np.ndarray) -> float:
    """Angle (rad, from the x axis) of the longer side of the minimum-area rectangle (rotating calipers)."""
    best = None
    for i in range(len(poly)):
        e = poly[(i + 1) % len(poly)] - poly[i]
        n = float(np.hypot(*e))
        if n == 0:
            continue
        a = e / n
        b = np.array([-a[1], a[0]])
        pa, pb = poly @ a, poly @ b
        la, lb = np.ptp(pa), np.ptp(pb)
        if best is None or la * lb < best[0] - 1e-9:
            ang = np.arctan2(a[1], a[0]) if la >= lb else np.arctan2(b[1], b[0])
            best = (la * lb, ang)
    return float(best[1])


def _line_intervals(poly: np.ndarray, y: float) -> list[tuple[float, float]]:
    """x intervals where the horizontal line at ``y`` lies inside the polygon (even-odd rule)."""
    xs = []
    n = len(poly)
    for i in range(n):
        (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % n]
        if (y1 <= y < y2) or (y2 <= y < y1):
            xs.append(x1 + (y - y1) * (x2 - x1) / (y2 - y1))
    xs.sort()
    return [(xs[k], xs[k + 1]) for k in range(0, len(xs) - 1, 2)]


#: photos per plan above which :func:`plan_flight` refuses (a mission of several thousand frames is far below it)
DEFAULT_MAX_PHOTOS = 200_000


def plan_flight(focal_px: float, image_size: tuple[int, int], area_xy, *, gsd_m: float | None = None,
                height_m: float | None = None, forward_overlap: float = 0.8, sidelap: float = 0.6,
                heading_deg: float | None = None, speed_mps: float | None = None, video_fps: float | None = None,
                ground_z_m: float = 0.0, crs: str | None = None, max_photos: int | None = None) -> FlightPlan:
    """Plan parallel flight lines over a polygon.

    Parameters
    ----------
    focal_px : float
        Focal length in pixels (``fx`` of the camera file).
    image_size : (int, int)
        Image width and height in pixels; the image's y axis is taken along the flight.
    area_xy : array_like, shape (N, 2)
        Polygon vertices (easting, northing) in metres, N ≥ 3, not closed or closed.
    gsd_m, height_m : float
        Exactly one: target ground sampling distance, or flight height above ground.
    forward_overlap, sidelap : float
        Fractions in [0, 1).
    heading_deg : float, optional
        Line direction (degrees from north, clockwise); default along the longest side of the area's
        minimum-area rectangle.
    speed_mps, video_fps : float, optional
        Ground speed; with a video frame rate as well, the frame-extraction stride and rate.
    ground_z_m : float
        Ground elevation added to the flight height in the waypoints' z.
    max_photos : int, optional
        Refuse an area that needs more photos than this (default :data:`DEFAULT_MAX_PHOTOS`), judged from the
        area's bounding box in the flight frame before any waypoint is made: a mistyped GSD or a 1-degree square
        is refused at once instead of planning millions of waypoints.

    Returns
    -------
    FlightPlan
    """
    f = _check_positive("focal_px", focal_px)
    try:
        w, h = (int(v) for v in image_size)
    except (TypeError, ValueError):
        raise ConfigError(f"image_size={image_size!r}: expected (width, height) in pixels") from None
    if w <= 0 or h <= 0:
        raise ConfigError(f"image_size={image_size!r}: expected positive (width, height) in pixels")
    if (gsd_m is None) == (height_m is None):
        raise ConfigError("give exactly one of gsd_m (target GSD) and height_m (flight height above ground)")
    for name, v in (("forward_overlap", forward_overlap), ("sidelap", sidelap)):
        if not (np.isfinite(v) and 0 <= v < 1):
            raise ConfigError(f"{name}={v!r}: expected a fraction in [0, 1)")
    poly = np.asarray(area_xy, float)
    if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3:
        raise ConfigError(f"area: expected at least 3 (x, y) vertices, got an array of shape {poly.shape}")
    if not np.isfinite(poly).all():
        k = int(np.flatnonzero(~np.isfinite(poly).all(axis=1))[0])
        raise ConfigError(f"area: vertex {k + 1} of {len(poly)} is {poly[k].tolist()}; expected finite coordinates in metres")
    if np.allclose(poly[0], poly[-1]) and len(poly) > 3:
        poly = poly[:-1]
    area = _polygon_area(poly)
    if area <= 0:
        raise ConfigError("area: the polygon has zero area (collinear vertices)")
    if gsd_m is not None:
        gsd = _check_positive("gsd_m", gsd_m)
        height = gsd * f
    else:
        height = _check_positive("height_m", height_m)
        gsd = height / f
    if height > MAX_HEIGHT_M:
        given = f"gsd_m={gsd:g} m with focal_px={f:g}" if gsd_m is not None else f"height_m={height:g}"
        raise ConfigError(f"{given}: a flight {height:.4g} m above ground, above {MAX_HEIGHT_M:g} m (no survey flies "
                          "there); expected the GSD in metres per pixel (e.g. 0.05) or the height in metres")
    along, across = gsd * h, gsd * w
    trigger = (1 - forward_overlap) * along
    spacing = (1 - sidelap) * across
    notes = []
    if heading_deg is None:
        theta = _long_axis_angle(poly)
        heading = (90.0 - np.rad2deg(theta)) % 180.0
        notes.append("heading along the longest side of the area's minimum-area rectangle")
    else:
        heading = float(heading_deg) % 360.0
        if not np.isfinite(heading):
            raise ConfigError(f"heading_deg={heading_deg!r}: expected degrees from north")
    # flight frame: u along the lines, v across
    t = np.deg2rad(90.0 - heading)
    du = np.array([np.cos(t), np.sin(t)])
    dv = np.array([-du[1], du[0]])
    o = poly.mean(axis=0)
    uv = np.c_[(poly - o) @ du, (poly - o) @ dv]
    vmin, vmax = uv[:, 1].min(), uv[:, 1].max()
    # every point of the area inside m = floor(across / spacing) strips, edges included: the first line lies
    # at most across/2 − (m − 1)·spacing above the lower edge, the last as far below the upper edge
    m = max(1, int(np.floor(across / spacing + 1e-9)))
    reach = across / 2 - (m - 1) * spacing
    n_lines = max(1, int(np.ceil((vmax - vmin - 2 * reach) / spacing - 1e-9)) + 1)
    v0 = 0.5 * (vmin + vmax) - 0.5 * (n_lines - 1) * spacing
    cap = DEFAULT_MAX_PHOTOS if max_photos is None else int(max_photos)
    if cap < 1:
        raise ConfigError(f"max_photos={max_photos!r}: expected a positive number of photos")
    bound = n_lines * (np.ceil((uv[:, 0].max() - uv[:, 0].min() + along) / trigger) + 1)
    if bound > cap:
        raise ConfigError(f"area of {area / 1e6:.3g} km^2 at a GSD of {gsd * 100:.3g} cm: about {bound:.3g} photos "
                          f"({n_lines} lines), above the cap of {cap} photos per plan; check the area and the GSD, or "
                          f"raise the cap (--max-photos N)")
    wps: list[Waypoint] = []
    length = 0.0
    photos = 0
    z = float(ground_z_m) + height
    prev_end = None
    k = 0
    for li in range(n_lines):
        v = v0 + li * spacing
        # the strip of half a footprint each side must be covered: take the union over the strip
        ivs = []
        for vv in np.linspace(v - across / 2, v + across / 2, 9):
            ivs += _line_intervals(uv, float(np.clip(vv, vmin + 1e-9, vmax - 1e-9)))
        if not ivs:
            continue
        u_lo = min(a for a, _ in ivs) - along / 2
        u_hi = max(b for _, b in ivs) + along / 2
        n_ph = int(np.ceil((u_hi - u_lo) / trigger)) + 1
        us = u_lo + trigger * np.arange(n_ph)
        if li % 2 == 1:
            us = us[::-1]
        pts = o + us[:, None] * du + v * dv
        wps.append(Waypoint(k, li, "start", *pts[0], z))
        k += 1
        for p in pts:
            wps.append(Waypoint(k, li, "photo", float(p[0]), float(p[1]), z))
            k += 1
        wps.append(Waypoint(k, li, "end", *pts[-1], z))
        k += 1
        length += float(np.linalg.norm(pts[-1] - pts[0]))
        if prev_end is not None:
            length += float(np.linalg.norm(pts[0] - prev_end))
        prev_end = pts[-1]
        photos += n_ph
    plan = FlightPlan(height_m=height, gsd_m=gsd, footprint_along_m=along, footprint_across_m=across,
                      forward_overlap=float(forward_overlap), sidelap=float(sidelap), trigger_distance_m=trigger,
                      line_spacing_m=spacing, heading_deg=heading, n_lines=len({w.line for w in wps}), n_photos=photos,
                      flight_length_m=length, area_m2=area, crs=crs, notes=notes, waypoints=wps)
    if speed_mps is not None:
        v = _check_positive("speed_mps", speed_mps)
        plan.speed_mps = v
        plan.flight_time_s = length / v
        plan.trigger_interval_s = trigger / v
        if video_fps is not None:
            fps = _check_positive("video_fps", video_fps)
            step = v / fps
            plan.video_fps = fps
            plan.extract_every_n_frames = max(1, int(np.floor(trigger / step + 1e-9)))
            plan.extraction_rate_hz = fps / plan.extract_every_n_frames
            if trigger < step:
                plan.notes.append(f"at {v:g} m/s and {fps:g} Hz consecutive frames are {step:.2f} m apart, more than "
                                  f"the {trigger:.2f} m the overlap needs: fly slower or higher")
    elif video_fps is not None:
        raise ConfigError("video_fps needs speed_mps (the ground speed) to give an extraction rate")
    return plan


def utm_epsg(lon_deg: float, lat_deg: float) -> int:
    """EPSG code of the WGS 84 / UTM zone holding a point."""
    zone = int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat_deg >= 0 else 32700) + zone


def read_area(text: str, source: str) -> tuple[np.ndarray, str | None]:
    """Polygon vertices from GeoJSON text (Polygon, MultiPolygon's first, Feature, FeatureCollection's first).

    Returns (vertices (N, 2), crs): crs is ``"EPSG:4326"`` (RFC 7946) unless the file names another in a
    legacy ``crs`` member.
    """
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFileError(f"{source}: not valid JSON (line {exc.lineno}: {exc.msg}); expected a GeoJSON polygon") from None
    crs = "EPSG:4326"
    if isinstance(d, dict) and isinstance(d.get("crs"), dict):
        name = str(d["crs"].get("properties", {}).get("name", ""))
        if "EPSG" in name.upper():
            crs = "EPSG:" + name.upper().split("EPSG")[-1].strip(":").strip()
    geom = d
    if isinstance(geom, dict) and geom.get("type") == "FeatureCollection":
        feats = geom.get("features") or []
        if not feats:
            raise DataFileError(f"{source}: FeatureCollection without features; expected a polygon")
        geom = feats[0]
    if isinstance(geom, dict) and geom.get("type") == "Feature":
        geom = geom.get("geometry")
    if not isinstance(geom, dict) or geom.get("type") not in ("Polygon", "MultiPolygon"):
        got = geom.get("type") if isinstance(geom, dict) else type(geom).__name__
        raise DataFileError(f"{source}: geometry type {got!r}; expected Polygon or MultiPolygon")
    coords = geom.get("coordinates")
    try:
        ring = coords[0] if geom["type"] == "Polygon" else coords[0][0]
        xy = np.asarray([[float(c[0]), float(c[1])] for c in ring])
    except (TypeError, IndexError, ValueError):
        raise DataFileError(f"{source}: polygon coordinates {str(coords)[:80]!r} are not [[x, y], ...] numbers") from None
    if len(xy) < 3 or not np.isfinite(xy).all():
        raise DataFileError(f"{source}: polygon with {len(xy)} vertices; expected at least 3 finite vertices")
    return xy, crs


def waypoints_csv(plan: FlightPlan, lonlat: np.ndarray | None = None) -> str:
    """CSV text: id,line,kind,X,Y,Z[,lon,lat]."""
    head = "id,line,kind,X,Y,Z" + (",lon,lat" if lonlat is not None else "")
    rows = [head]
    for i, w in enumerate(plan.waypoints):
        r = f"{w.id},{w.line},{w.kind},{w.x:.3f},{w.y:.3f},{w.z:.3f}"
        if lonlat is not None:
            r += f",{lonlat[i, 0]:.8f},{lonlat[i, 1]:.8f}"
        rows.append(r)
    return "\n".join(rows) + "\n"


def waypoints_kml(plan: FlightPlan, lonlat: np.ndarray, name: str = "thermogrammetry flight plan") -> str:
    """KML text: the flight path as a LineString and the line ends as placemarks (heights above ground)."""
    from xml.sax.saxutils import escape

    agl = plan.height_m
    path = " ".join(f"{lo:.8f},{la:.8f},{agl:.2f}" for (lo, la), w in zip(lonlat, plan.waypoints) if w.kind != "photo")
    marks = "".join(
        f"<Placemark><name>line {w.line} {w.kind}</name><Point><altitudeMode>relativeToGround</altitudeMode>"
        f"<coordinates>{lo:.8f},{la:.8f},{agl:.2f}</coordinates></Point></Placemark>"
        for (lo, la), w in zip(lonlat, plan.waypoints) if w.kind != "photo")
    desc = (f"height {plan.height_m:.1f} m AGL, GSD {plan.gsd_m * 100:.1f} cm, trigger every {plan.trigger_distance_m:.2f} m, "
            f"line spacing {plan.line_spacing_m:.2f} m, {plan.n_lines} lines, {plan.n_photos} photos")
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2"><Document>'
            f"<name>{escape(name)}</name><description>{escape(desc)}</description>"
            "<Placemark><name>flight path</name><LineString><altitudeMode>relativeToGround</altitudeMode>"
            f"<coordinates>{path}</coordinates></LineString></Placemark>{marks}</Document></kml>\n")
