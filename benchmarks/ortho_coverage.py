"""Where the orthophoto leaves the images' joint footprint empty, and why: a per-cell account.

The joint footprint is the union of the images' footprints as ``dense`` records them (``dense.json`` ``pairs``: each
frame's corners cast to its matched depth), on the ortho's grid extended to cover them all; "on the surface" it is the
cells whose surface height projects into some frame (and, where the surface has no height, the former). Every cell of
either that the mosaic leaves empty is put in the first class that applies:

1. **outside the ortho's box** (the mosaic's grid is the DSM's: cells beyond it cannot hold a value);
2. **no surface height**: the surface the mosaic is drawn on (the DSM, with its holes filled as that ``ortho`` filled
   them: :func:`~thermogrammetry.products.dsm.fill_surface` with the ``ortho.json`` ``fill`` limit and grid) has no
   height there;
3. **in no frame**: at its surface height the cell projects into no frame (the footprint at the matched depth is an
   approximation of the true one);
4. **viewing angle**: in some frame, but seen at more than ``max_angle_deg`` from the surface normal in every frame
   that has it (the normal as that ``ortho`` took it: Horn's 3 × 3 slope, or central differences over two cells for
   an ortho whose ``ortho.json`` names no ``normals``);
5. **hidden**: within the angle limit in some frame, but behind a nearer surface in every such frame (the z-buffer;
   by elimination: the mosaic left it empty).

Usage::

    python benchmarks/ortho_coverage.py PROJECT               # a `thermogrammetry run` folder (survey/ dense/ ortho/)
    python benchmarks/ortho_coverage.py PROJECT --ortho DIR   # another OUT of `thermogrammetry ortho` on the same survey

``--png FILE`` draws it as a map (``--label`` its title). Prints a JSON account (cells and shares of the joint footprint, of the cells in >= 3 footprints, and of the ortho's
box).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _in_quad(px, py, quad) -> np.ndarray:
    q = np.asarray(quad, float)
    area2 = sum(q[k, 0] * q[(k + 1) % 4, 1] - q[(k + 1) % 4, 0] * q[k, 1] for k in range(4))
    sgn = 1.0 if area2 >= 0 else -1.0
    inside = np.ones(px.shape, bool)
    for k in range(4):
        (x1, y1), (x2, y2) = q[k], q[(k + 1) % 4]
        inside &= sgn * ((x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)) >= 0
    return inside


def _central_normals(Z, gsd):
    gx = np.full_like(Z, np.nan)
    gy = np.full_like(Z, np.nan)
    gx[:, 1:-1] = (Z[:, 2:] - Z[:, :-2]) / (2 * gsd)
    gy[1:-1] = (Z[:-2] - Z[2:]) / (2 * gsd)
    n = np.stack([-gx, -gy, np.ones_like(Z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(np.isfinite(n), n, np.array([0.0, 0.0, 1.0]))


COLOURS = {0: (255, 255, 255), 1: (230, 25, 75), 2: (0, 130, 200), 3: (245, 130, 48), 4: (145, 30, 180), 5: (60, 180, 75)}


def account(project: Path, ortho_dir: Path, png: Path | None = None, label: str | None = None) -> dict:
    sys.path.insert(0, str(REPO / "src"))
    import rasterio

    from thermogrammetry.pipeline.frames import SurveyFrames
    from thermogrammetry.products.dsm import fill_surface
    from thermogrammetry.products.ortho import project_world


    dense = json.loads((project / "dense" / "dense.json").read_text())
    info = json.loads((ortho_dir / "ortho.json").read_text())
    from thermogrammetry.products.ortho import surface_normals

    # the normals and the fill as this ortho took them (ortho.json): an ortho of an older version took central
    # differences of 2 cells and filled within max_hole / 2 everywhere
    normals = surface_normals if "normals" in info else _central_normals
    feet = [p["footprint"] for p in dense["pairs"] if "footprint" in p]
    with rasterio.open(ortho_dir / "ortho.tif") as src:
        ortho = src.read(1)
        ot = src.transform
    with rasterio.open(project / "dense" / "dsm.tif") as src:
        dsm = src.read(1).astype(float)
        dt = src.transform
    gsd = ot.a
    # the extended grid: the ortho's cells plus whole cells out to the footprints' box
    fx = np.array([p for q in feet for p in q])
    c_lo = int(np.floor((fx[:, 0].min() - ot.c) / gsd)) - 1
    c_hi = int(np.ceil((fx[:, 0].max() - ot.c) / gsd)) + 1
    r_lo = int(np.floor((ot.f - fx[:, 1].max()) / gsd)) - 1
    r_hi = int(np.ceil((ot.f - fx[:, 1].min()) / gsd)) + 1
    r_lo, c_lo = min(r_lo, 0), min(c_lo, 0)
    r_hi, c_hi = max(r_hi, ortho.shape[0]), max(c_hi, ortho.shape[1])
    H, W = r_hi - r_lo, c_hi - c_lo
    cols, rows = np.meshgrid(np.arange(c_lo, c_hi), np.arange(r_lo, r_hi))
    X = ot.c + (cols + 0.5) * gsd
    Y = ot.f - (rows + 0.5) * gsd
    n_feet = np.zeros((H, W), np.int32)
    for q in feet:
        n_feet += _in_quad(X, Y, q)
    union = n_feet >= 1
    in_box = (rows >= 0) & (rows < ortho.shape[0]) & (cols >= 0) & (cols < ortho.shape[1])
    val = np.full((H, W), np.nan)
    val[in_box] = ortho[rows[in_box], cols[in_box]]
    have = np.isfinite(val)
    # the surface the mosaic is drawn on, on the ortho's grid (the DSM's cells, or the DSM's grid extended by whole
    # cells: ortho.json fill.grid), filled as ortho fills it
    assert abs(dt.a - gsd) < 1e-9, "expected the ortho at the DSM's cell size"
    dc, dr = (dt.c - ot.c) / gsd, (ot.f - dt.f) / gsd
    assert abs(dc - round(dc)) < 1e-6 and abs(dr - round(dr)) < 1e-6, "ortho grid not aligned with the DSM's"
    dc, dr = int(round(dc)), int(round(dr))
    fill = info.get("fill")
    canvas = np.full(ortho.shape, np.nan)
    canvas[dr:dr + dsm.shape[0], dc:dc + dsm.shape[1]] = dsm
    open_edges = bool(fill) and "convex hull" in fill["method"]
    if fill and "grid" in fill:
        surf = fill_surface(canvas, fill["max_hole_m"] / gsd, open_edges=open_edges)[0]
    elif fill:
        surf = np.full(ortho.shape, np.nan)
        surf[dr:dr + dsm.shape[0], dc:dc + dsm.shape[1]] = fill_surface(dsm, fill["max_hole_m"] / gsd, open_edges=open_edges)[0]
    else:
        surf = canvas
    Z = np.full((H, W), np.nan)
    Z[in_box] = surf[rows[in_box], cols[in_box]]
    measured = np.zeros((H, W), bool)
    measured[in_box] = np.isfinite(canvas[rows[in_box], cols[in_box]])
    in_dsm = (rows >= dr) & (rows < dr + dsm.shape[0]) & (cols >= dc) & (cols < dc + dsm.shape[1])
    nrm = normals(Z, gsd)
    sv = SurveyFrames(str(project / "survey"), need=1, check=False)
    tested = np.isfinite(Z)  # every cell with a surface height: in which frames, at which angle
    P = np.column_stack([X[tested], Y[tested], Z[tested]])
    n = nrm[tested]
    in_frame = np.zeros(len(P), bool)
    in_angle = np.zeros(len(P), bool)
    min_angle = np.full(len(P), np.inf)
    cos_max = np.cos(np.radians(info["max_angle_deg"]))
    for k in range(len(sv)):
        cam, (R, t) = sv.cameras[k], sv.poses[k]
        wpx, hpx = cam.image_size
        uv, z = project_world(cam, R, t, P)
        with np.errstate(invalid="ignore"):
            ins = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < wpx - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < hpx - 0.5)
        d = (-R.T @ t)[None] - P
        cth = np.einsum("ij,ij->i", n, d) / np.linalg.norm(d, axis=1)
        in_frame |= ins
        in_angle |= ins & (cth > cos_max)
        min_angle = np.where(ins, np.minimum(min_angle, np.degrees(np.arccos(np.clip(cth, -1, 1)))), min_angle)
    frame_map = np.zeros((H, W), bool)
    frame_map[tested] = in_frame
    angle_map = np.zeros((H, W), bool)
    angle_map[tested] = in_angle
    amin = np.full((H, W), np.inf)
    amin[tested] = min_angle
    # the joint footprint on the surface: cells with a height that project into a frame; cells without one, the
    # frames' footprints at their matched depth
    on_surface = np.where(np.isfinite(Z), frame_map, union)
    cls = np.zeros((H, W), np.int8)  # 0 = has a value or in neither footprint
    either = (union | on_surface) & ~have
    cls[either & ~in_box] = 1
    cls[either & in_box & ~np.isfinite(Z)] = 2
    cls[either & tested & ~frame_map] = 3
    cls[either & frame_map & ~angle_map] = 4
    cls[either & angle_map] = 5
    names = {1: "outside the ortho's box", 2: "no surface height", 3: "in no frame at its height",
             4: "viewing angle above the limit in every frame", 5: "hidden (z-buffer) in every frame within the limit"}
    U = int(union.sum())
    U3 = int((n_feet >= 3).sum())
    S = int(on_surface.sum())
    out = {"ortho": str(ortho_dir), "gsd_m": gsd, "max_angle_deg": info["max_angle_deg"], "fill": fill and fill["max_hole_m"],
           "union_cells": U, "cells_in_3_footprints": U3, "union_on_surface_cells": S,
           "ortho_box_cells": int(ortho.size), "union_cells_in_box": int((union & in_box).sum()),
           "covered": {"union": round(float((union & have).sum() / U), 4),
                       ">=3 footprints": round(float(((n_feet >= 3) & have).sum() / U3), 4),
                       "union on the surface": round(float((on_surface & have).sum() / S), 4),
                       "ortho box": round(float(np.isfinite(ortho).mean()), 4)},
           "empty": {}}
    for c, name in names.items():
        m = cls == c
        out["empty"][name] = {"of union": round(float((m & union).sum() / U), 4),
                              "of >=3 footprints": round(float((m & (n_feet >= 3)).sum() / U3), 4),
                              "of union on the surface": round(float((m & on_surface).sum() / S), 4),
                              "cells (union)": int((m & union).sum())}
    m4 = (cls == 4) & union
    if m4.any():
        out["empty"][names[4]]["smallest angle (deg) median/p90"] = [float(np.median(amin[m4])),
                                                                      float(np.percentile(amin[m4], 90))]
        out["empty"][names[4]]["of which on filled heights"] = int((m4 & ~measured).sum())
    # the empty cells with no height: inside a DSM hole, next to the box's border or not
    m2 = (cls == 2) & union
    if m2.any():
        from scipy.ndimage import label

        holes = in_box & ~np.isfinite(Z)
        lab, _ = label(holes)
        border_labels = np.unique(np.r_[lab[rows == 0], lab[rows == ortho.shape[0] - 1], lab[cols == 0],
                                        lab[cols == ortho.shape[1] - 1]])
        touches = np.isin(lab, border_labels[border_labels > 0]) & m2
        out["empty"][names[2]]["of which in holes open to the box's border"] = int(touches.sum())
    # the DSM's measured box against the footprints
    out["dsm_measured_cells"] = int(np.isfinite(dsm).sum())
    out["union_cells_in_dsm_box"] = int((union & in_dsm).sum())
    out["covered"]["union inside the DSM's box"] = round(float((union & in_dsm & have).sum() / max(1, (union & in_dsm).sum())), 4)
    out["union_box_m"] = [float(fx[:, 0].min()), float(fx[:, 1].min()), float(fx[:, 0].max()), float(fx[:, 1].max())]
    out["ortho_box_m"] = [ot.c, ot.f - ortho.shape[0] * gsd, ot.c + ortho.shape[1] * gsd, ot.f]
    out["dsm_box_m"] = [dt.c, dt.f - dsm.shape[0] * gsd, dt.c + dsm.shape[1] * gsd, dt.f]
    if png is not None:
        _figure(png, cls, union | on_surface, have, in_box, in_dsm, names, out, label or Path(out["ortho"]).name)
    return out


def _figure(png: Path, cls, union, have, in_box, in_dsm, names, out, label: str) -> None:
    """The account as a map: covered cells light grey, the union's empty cells coloured by class, the ortho's box
    outlined in black, the DSM's box (when smaller) dashed in dark grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from scipy.ndimage import binary_erosion

    img = np.full(cls.shape + (3,), 255, np.uint8)
    img[union & have] = (200, 200, 200)
    img[have & ~union] = (235, 235, 235)
    for c, col in COLOURS.items():
        if c:
            img[cls == c] = col
    dsm_edge = in_dsm & ~binary_erosion(in_dsm)
    img[dsm_edge & ((np.indices(in_dsm.shape).sum(axis=0) // 6) % 2 == 0)] = (90, 90, 90)
    edge = in_box & ~binary_erosion(in_box)
    img[edge] = (0, 0, 0)
    fig, ax = plt.subplots(figsize=(11, 5.6), dpi=110)
    ax.imshow(img, interpolation="nearest")
    ax.set_axis_off()
    cov = out["covered"]
    ax.set_title(f"{label}: {100 * cov['union']:.1f} % of the joint footprint covered "
                 f"({100 * cov['union on the surface']:.1f} % of it on the surface, {100 * cov['>=3 footprints']:.1f} % "
                 f"of the cells in >= 3 footprints); max angle {out['max_angle_deg']:g} deg", fontsize=9)
    handles = [Patch(color=np.array((200, 200, 200)) / 255, label="covered")]
    handles += [Patch(color=np.array(COLOURS[c]) / 255, label=f"{names[c]}: {100 * out['empty'][names[c]]['of union']:.2f} %")
                for c in names]
    handles.append(Patch(facecolor="white", edgecolor="black", label="the ortho's box"))
    if not np.array_equal(in_dsm, in_box):
        handles.append(Patch(facecolor="white", edgecolor=(0.35, 0.35, 0.35), linestyle="--", label="the DSM's box"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=2, fontsize=8, frameon=False)
    fig.savefig(png, bbox_inches="tight", pad_inches=0.15)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("project", help="a `thermogrammetry run` folder (survey/, dense/, ortho/)")
    ap.add_argument("--ortho", default=None, help="the OUT of `thermogrammetry ortho` to account for (default PROJECT/ortho)")
    ap.add_argument("--png", default=None, help="write the account as a map (PNG)")
    ap.add_argument("--label", default=None, help="the map's title (default: the ortho folder's name)")
    a = ap.parse_args(argv)
    p = Path(a.project)
    print(json.dumps(account(p, Path(a.ortho) if a.ortho else p / "ortho", Path(a.png) if a.png else None, a.label),
                     indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
