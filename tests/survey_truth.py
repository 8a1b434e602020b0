"""Test helper: a survey folder (cameras.json + frames/<name>.tif) built from the synthetic scene's TRUE poses.

Tests that use it start from true poses, not from ``thermogrammetry survey``; they test dense/ortho alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def small_survey_config(**kw):
    from thermogrammetry.synthetic.survey import SurveyConfig
    from thermogrammetry.synthetic.terrain import TerrainConfig

    terrain = TerrainConfig(width_m=64.0, height_m=48.0, n_buildings=2, n_trees=3, n_roads=1)
    base = dict(terrain=terrain, image_size=(320, 256), focal_mm=12.5, flight_height_m=45.0, overlap=0.8,
                sidelap=0.6, n_gcp=3, n_check=2, seed=3)
    base.update(kw)
    return SurveyConfig(**base)


#: 2 lines x 3 frames of the small survey scene (:func:`write_small_block`)
SMALL_BLOCK_FRAMES = (20, 21, 22, 34, 35, 36)


def write_small_block(root: Path):
    """Six rendered frames of the small survey scene (float TIFFs in kelvin without a unit tag) in ``root/images``,
    their RTK-like GNSS (the true centres, σ 3/5 cm) in ``root/gnss.csv`` and the true camera in
    ``root/camera.json``; returns ``(scene, the survey options every user of the block passes)``."""
    import tifffile

    from thermogrammetry.synthetic.survey import make_survey, render_frame

    sc = make_survey(small_survey_config())
    (root / "images").mkdir()
    lines = ["image,X,Y,Z,sX,sY,sZ"]
    for k in SMALL_BLOCK_FRAMES:
        f = sc.frames[k]
        tifffile.imwrite(root / "images" / f"{f.name}.tif", render_frame(sc, k)["image_k"].astype(np.float32))
        c = f.pose.center
        lines.append(f"{f.name},{c[0]:.4f},{c[1]:.4f},{c[2]:.4f},0.03,0.03,0.05")
    (root / "gnss.csv").write_text("\n".join(lines) + "\n")
    sc.camera.save(root / "camera.json")
    return sc, ["--input-unit", "K", "--gnss", str(root / "gnss.csv"), "--crs", f"EPSG:{sc.terrain.epsg}", "--workers", "0"]


def write_true_survey(folder, config=None, *, unit: str = "K", sensor: bool = True, frames=None, display: bool = False):
    """Render the frames and write a survey folder with the true poses. Returns ``(scene, folder)``.

    ``unit="counts"`` writes uint16 frames (kelvin × 100, a stand-in for raw counts: the products must keep
    the values and never call them temperatures). ``unit="dn"``: 8-bit grey renderings (per-frame stretch,
    ``synthetic.display.render_8bit``), with ``display`` a camera display burned in.
    """
    import tifffile

    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage
    from thermogrammetry.synthetic.survey import make_survey, render_frame

    folder = Path(folder)
    sc = make_survey(config or small_survey_config())
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    images = []
    idx = range(len(sc.frames)) if frames is None else frames
    for k in idx:
        fr = sc.frames[k]
        img = render_frame(sc, k, sensor=sensor)["image_k"].astype(np.float32)
        if unit == "counts":
            img = np.clip(np.rint(img * 100.0), 0, 65535).astype(np.uint16)
        elif unit == "dn":
            from thermogrammetry.synthetic.display import render_8bit

            img = render_8bit(img, display=display)
        tifffile.imwrite(folder / "frames" / f"{fr.name}.tif", img)
        images.append(OrientedImage(fr.name, "thermal", fr.pose.R, fr.pose.t, frame=f"frames/{fr.name}.tif", unit=unit))
    OrientedCameras({"thermal": sc.camera}, images, crs=f"EPSG:{sc.terrain.epsg}",
                    notes="TRUE poses of the synthetic scene (test helper)").save(folder / "cameras.json")
    return sc, folder


def true_height(scene, x, y):
    """True DSM height (m) at world (x, y)."""
    loc = scene.terrain.to_local(np.column_stack([x, y, np.zeros_like(x)]))
    return scene.terrain.height_at(loc[:, 0], loc[:, 1])


def write_true_dsm(path, scene, gsd: float, *, margin_m: float = 2.0):
    """The scene's true DSM resampled (bilinear) at ``gsd`` as a COG GeoTIFF; returns its Grid."""
    from thermogrammetry.products.raster import Grid, write_cog

    ter = scene.terrain
    x0, y0 = ter.origin_en
    grid = Grid.covering(x0 + margin_m, y0 + margin_m, x0 + ter.width_m - margin_m, y0 + ter.height_m - margin_m, gsd)

    def tile(r0, c0, rows, cols):
        X, Y = grid.cell_centres(r0, c0, rows, cols)
        return true_height(scene, X.ravel(), Y.ravel()).reshape(rows, cols).astype("float32")

    write_cog(path, grid, "float32", tile, crs=f"EPSG:{ter.epsg}", nodata=float("nan"), unit="m")
    return grid
