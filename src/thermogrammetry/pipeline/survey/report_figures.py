"""The survey report's maps and the block's ground geometry (:func:`block_geometry`).

The footprints are those of ``cameras.gpkg`` (:func:`thermogrammetry.products.gpkg.footprint`): each oriented
image's four corners intersected with the horizontal plane at the sparse cloud's median height. From them: the
overlap map (how many images cover each ground cell), the area covered (the cells covered by at least one image),
the flying height (median camera height above that plane) and the images' ground sampling distance at nadir
(flying height / focal length in pixels). The camera-centre error ellipses come from the a-posteriori covariance
of the final adjustment (``survey.json`` ``images[].center_cov_m2``); the GCP and check-point residuals are drawn
as vectors at the points' map positions.
"""

from __future__ import annotations

import numpy as np

from ...reporting import (caption_below, colour_limits, colourbar, ellipses_at, figure_png, height_colormap,
                          map_axes, map_origin, pad_to_ratio, short_names, thin_labels, vectors_at)

__all__ = ["MAX_GRID", "footprints", "overlap_counts", "block_geometry", "control_points", "sparse_figure",
           "overlap_figure", "ellipse_figure", "control_figure", "residual_bars"]

#: largest side (cells) of the overlap map's grid
MAX_GRID = 300


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def footprints(cams_doc: dict, ground_z: float) -> list[tuple[str, np.ndarray]]:
    """``(name, (4, 2) corners)`` of every image of a parsed ``cameras.json`` whose corner rays meet the plane
    ``z = ground_z`` below the camera (as in ``cameras.gpkg``)."""
    from ...io.oriented import OrientedCameras
    from ...products.gpkg import footprint

    oc = OrientedCameras.from_dict(cams_doc, confine_frames=False)
    out = []
    for im in oc.images:
        q = footprint(oc.camera_of(im), im.R, im.center, float(ground_z))
        if q is not None and np.isfinite(q).all():
            out.append((im.name, q))
    return out


def _inside_convex(px, py, q) -> np.ndarray:
    """Points inside the convex polygon ``q`` (k, 2), either orientation."""
    q = np.asarray(q, float)
    k = len(q)
    area2 = sum(q[i, 0] * q[(i + 1) % k, 1] - q[(i + 1) % k, 0] * q[i, 1] for i in range(k))
    sgn = 1.0 if area2 >= 0 else -1.0
    inside = np.ones(np.shape(px), bool)
    for i in range(k):
        a, b = q[i], q[(i + 1) % k]
        inside &= ((b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])) * sgn >= 0
    return inside


def overlap_counts(polys, max_cells: int = MAX_GRID) -> tuple[np.ndarray, tuple[float, float, float, float], float]:
    """How many of the convex polygons ``polys`` ((4, 2) each, m) cover each cell of a grid over their union's box.

    Returns ``(counts (h, w) int, extent (xmin, xmax, ymin, ymax), cell size m)``; row 0 is the north edge. The cell
    is the box's longer side / ``max_cells`` (a map, not a product)."""
    Q = np.array([np.asarray(q, float) for q in polys]).reshape(-1, 4, 2)
    if not len(Q):
        return np.zeros((0, 0), int), (0.0, 0.0, 0.0, 0.0), 0.0
    xmin, ymin = Q[:, :, 0].min(), Q[:, :, 1].min()
    xmax, ymax = Q[:, :, 0].max(), Q[:, :, 1].max()
    cell = max(xmax - xmin, ymax - ymin, 1e-9) / max_cells
    w, h = int(np.ceil((xmax - xmin) / cell)), int(np.ceil((ymax - ymin) / cell))
    counts = np.zeros((h, w), np.int32)
    for q in Q:  # each polygon in its own box's window
        c0, c1 = int(np.floor((q[:, 0].min() - xmin) / cell)), int(np.ceil((q[:, 0].max() - xmin) / cell))
        r0, r1 = int(np.floor((ymax - q[:, 1].max()) / cell)), int(np.ceil((ymax - q[:, 1].min()) / cell))
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, w), min(r1, h)
        if c1 <= c0 or r1 <= r0:
            continue
        X = xmin + (np.arange(c0, c1) + 0.5) * cell
        Y = ymax - (np.arange(r0, r1) + 0.5) * cell
        gx, gy = np.meshgrid(X, Y)
        counts[r0:r1, c0:c1] += _inside_convex(gx, gy, q)
    return counts, (float(xmin), float(xmin + w * cell), float(ymax - h * cell), float(ymax)), float(cell)


def block_geometry(cams_doc: dict, ground_z: float | None) -> dict:
    """``survey.json``'s ``footprints``: the ground plane's height, the flying height, the images' GSD at nadir, the
    area covered and the overlap (median images per covered cell), from the footprints on ``z = ground_z`` (the
    sparse cloud's median height; None: nothing is known, an empty dict)."""
    if ground_z is None or not np.isfinite(ground_z) or not cams_doc.get("images"):
        return {}
    polys = footprints(cams_doc, ground_z)
    C = np.array([im["center"] for im in cams_doc["images"]], float)
    above = float(np.median(C[:, 2] - float(ground_z)))
    out = {"ground_z_m": float(ground_z), "images_with_footprint": len(polys),
           "definition": "footprints of cameras.gpkg: image corners on the plane at the sparse cloud's median height"}
    if above > 0:
        out["flying_height_m"] = above
        g = nadir_gsd(cams_doc, above)
        if g is not None:
            out["gsd_m"] = g
    if polys:
        counts, ext, cell = overlap_counts([q for _, q in polys])
        cov = counts[counts > 0]
        out.update(area_m2=float(cov.size * cell**2), overlap_cell_m=cell,
                   images_per_cell_median=float(np.median(cov)) if cov.size else None,
                   images_per_cell_max=int(cov.max()) if cov.size else None)
    return out


def _focal_px(cams_doc: dict) -> float | None:
    """The median focal length (px) of the images' cameras in a parsed ``cameras.json``."""
    from ...camera import Camera

    fs = []
    for d in cams_doc.get("cameras", {}).values():
        try:
            fs.append(float(Camera.from_dict(d).K[0, 0]))
        except Exception:  # noqa: BLE001 - a camera that does not parse has no focal length here
            continue
    return float(np.median(fs)) if fs else None


def nadir_gsd(cams_doc: dict, flying_height_m: float | None) -> float | None:
    """The images' ground sampling distance at nadir (m): flying height / focal length (px)."""
    f = _focal_px(cams_doc)
    return float(flying_height_m) / f if f and flying_height_m else None


def control_points(s: dict) -> list[dict]:
    """The GCPs and check points of ``survey.json`` with a residual and a map position: ``kind`` (``GCP`` /
    ``check point``), ``id``, ``xy`` (given x, y), ``dxy`` (dx, dy, m), ``dz`` (m)."""
    out = []
    for kind, rows in (("GCP", s.get("gcp_residuals", [])), ("check point", s.get("checkpoint_errors", []))):
        for r in rows:
            if "dx" in r and "x" in r and r["dx"] is not None:
                out.append({"kind": kind, "id": r["id"], "xy": (r["x"], r["y"]), "dxy": (r["dx"], r["dy"]), "dz": r["dz"]})
    return out


def sparse_figure(P: np.ndarray, C: np.ndarray, names, origin=None) -> str:
    """Camera centres over the sparse cloud, coloured by height with 1st–99th percentile limits. ``origin``: the
    maps' origin (default: :func:`~thermogrammetry.reporting.map_origin` of the camera centres)."""
    plt = _plt()
    ox, oy = origin or map_origin(C[:, 0], C[:, 1])
    fig, ax = plt.subplots(figsize=(7.6, 6.2))
    if len(P):
        lim = colour_limits(P[:, 2], 1.0, 99.0)
        sc = ax.scatter(P[:, 0] - ox, P[:, 1] - oy, c=P[:, 2], s=1.5, cmap=height_colormap(), vmin=lim.lo, vmax=lim.hi,
                        rasterized=True)
        colourbar(fig, ax, sc, "height of the tie points (m)", lim, "m")
    ax.plot(C[:, 0] - ox, C[:, 1] - oy, "r^", ms=5, label="camera centres")
    if len(C) <= 15:
        for k, n in enumerate(short_names(names)):
            ax.annotate(n, (C[k, 0] - ox, C[k, 1] - oy), fontsize=6, xytext=(3, 3), textcoords="offset points")
    map_axes(ax, (ox, oy), adjustable="box")
    if len(P) >= 20:  # the map's box: the cameras and the 0.5th-99.5th percentiles of the points (strays left out)
        lo = np.minimum(np.percentile(P[:, :2], 0.5, axis=0), C[:, :2].min(axis=0))
        hi = np.maximum(np.percentile(P[:, :2], 99.5, axis=0), C[:, :2].max(axis=0))
        pad = 0.05 * max(float(np.max(hi - lo)), 1.0)
        ax.set_xlim(lo[0] - pad - ox, hi[0] + pad - ox)
        ax.set_ylim(lo[1] - pad - oy, hi[1] + pad - oy)
        out = int(np.sum(np.any((P[:, :2] < lo - pad) | (P[:, :2] > hi + pad), axis=1)))
        if out:
            caption_below(ax, f"{out} of the {len(P)} points drawn lie outside the map", line=1)
    pad_to_ratio(ax)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("Camera centres over the sparse cloud", fontsize=10)
    return figure_png(fig)


def overlap_figure(counts: np.ndarray, ext, C: np.ndarray, ground_z: float, origin=None) -> str:
    """The overlap map: images covering each ground cell (0: not covered, drawn blank)."""
    from matplotlib.colors import BoundaryNorm

    plt = _plt()
    ox, oy = origin or map_origin(C[:, 0], C[:, 1])
    fig, ax = plt.subplots(figsize=(7.6, 6.2))
    top = max(1, int(counts.max()))
    step = max(1, int(np.ceil(top / 12)))
    bounds = np.arange(1, top + step + 1, step) - 0.5  # bins of ``step`` counts, lower edges 1, 1 + step, ...
    cmap = plt.get_cmap("viridis", len(bounds) - 1).with_extremes(bad="white")
    im = ax.imshow(np.ma.masked_equal(counts, 0), extent=(ext[0] - ox, ext[1] - ox, ext[2] - oy, ext[3] - oy),
                   origin="upper", interpolation="nearest", cmap=cmap, norm=BoundaryNorm(bounds, cmap.N))
    if step == 1:
        colourbar(fig, ax, im, "images covering the cell", ticks=np.arange(1, top + 1))
    else:
        cb = colourbar(fig, ax, im, f"images covering the cell (bins of {step})", ticks=bounds[:-1])
        cb.ax.set_yticklabels([f"{int(b + 0.5)}" for b in bounds[:-1]])
    ax.plot(C[:, 0] - ox, C[:, 1] - oy, ".", color="#c33", ms=3, label="camera centres")
    map_axes(ax, (ox, oy), adjustable="box")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"Overlap: images per ground cell (footprints on z = {ground_z:.1f} m)", fontsize=10)
    return figure_png(fig)


def ellipse_figure(C: np.ndarray, cov: np.ndarray, origin=None) -> tuple[str, float]:
    """1 σ horizontal error ellipses of the camera centres (``cov`` (n, 3, 3) m², NaN = unknown), magnified; the
    centres coloured by σZ. Returns ``(figure, magnification)``."""
    plt = _plt()
    ox, oy = origin or map_origin(C[:, 0], C[:, 1])
    fig, ax = plt.subplots(figsize=(7.6, 6.2))
    extent = max(float(np.ptp(C[:, 0])), float(np.ptp(C[:, 1])), 1.0)
    mag = ellipses_at(ax, C[:, :2], cov[:, :2, :2], origin=(ox, oy), extent=extent)
    sz = 100 * np.sqrt(np.maximum(cov[:, 2, 2], 0))
    lim = colour_limits(sz, 1.0, 99.0)
    sc = ax.scatter(C[:, 0] - ox, C[:, 1] - oy, c=sz, s=14, cmap="plasma", vmin=lim.lo, vmax=lim.hi, zorder=5)
    colourbar(fig, ax, sc, "σZ of the camera centre (cm)", lim, "cm")
    map_axes(ax, (ox, oy), adjustable="box")
    ax.margins(0.08)
    ax.autoscale_view()
    pad_to_ratio(ax)
    ax.set_title(f"Camera centres: 1 σ horizontal error ellipses, magnified ×{mag:g}", fontsize=10)
    return figure_png(fig), mag


def control_figure(points: list[dict], C: np.ndarray, origin=None) -> tuple[str, float]:
    """GCP and check-point planimetric residuals as arrows at the points' map positions, dZ written beside each.
    Returns ``(figure, magnification)``."""
    plt = _plt()
    xy = np.array([p["xy"] for p in points], float)
    ox, oy = origin or map_origin(C[:, 0], C[:, 1])
    fig, ax = plt.subplots(figsize=(7.6, 6.2))
    ax.plot(C[:, 0] - ox, C[:, 1] - oy, ".", color="#bbb", ms=3, label="camera centres")
    extent = max(float(np.ptp(np.r_[xy[:, 0], C[:, 0]])), float(np.ptp(np.r_[xy[:, 1], C[:, 1]])), 1.0)
    style = {"GCP": ("#1f5fa8", "^"), "check point": ("#c33", "o")}
    for kind, (colour, marker) in style.items():
        sel = np.array([p["xy"] for p in points if p["kind"] == kind], float).reshape(-1, 2)
        if len(sel):
            ax.plot(sel[:, 0] - ox, sel[:, 1] - oy, marker, color=colour, ms=6, mfc="none", label=f"{kind}s")
    _, mag = vectors_at(ax, xy, [p["dxy"] for p in points], origin=(ox, oy), extent=extent,
                        color=[style[p["kind"]][0] for p in points])
    for p in points:
        ax.annotate(f"{p['id']}\ndZ {100 * p['dz']:+.1f} cm", (p["xy"][0] - ox, p["xy"][1] - oy), fontsize=7,
                    xytext=(5, -14), textcoords="offset points", color=style[p["kind"]][0])
    map_axes(ax, (ox, oy), adjustable="box")
    ax.margins(0.08)
    ax.autoscale_view()
    pad_to_ratio(ax)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    ax.set_title("Residuals at the points (arrows: dX, dY; text: dZ)", fontsize=10, loc="left")
    return figure_png(fig), mag


def residual_bars(ims: list[dict]) -> str:
    """Tie-point reprojection RMS per oriented image (every k-th name on the axis when there are many)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(min(max(6.0, 0.18 * len(ims)), 11.0), 3.0))
    ax.bar(range(len(ims)), [im["rms_px"] or 0 for im in ims], color="#47a")
    thin_labels(ax, short_names([im["name"] for im in ims]))
    ax.set_ylabel("reprojection RMS (px)")
    ax.set_title("Tie-point residuals per image", fontsize=10)
    return figure_png(fig)
