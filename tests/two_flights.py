"""Test helper: two synthetic flights of the same scene with one roof warmed between them, each made into an ortho
with its ``ortho_sigma.tif`` (for ``evaluate --ortho A --against B``).

The scene is the small synthetic survey of tests/survey_truth.py (the frames of tests/test_ortho_sigma.py: two lines
over building 0, a gable roof of bitumen, ε 0.94). Flight A is rendered from the scene, flight B from the same scene
with building 0's roof warmer by ``warming_k`` in the true surface-temperature field
(:func:`thermogrammetry.synthetic.changes.warm_roof`). Each flight: the frames noise-free (``sensor=False``) plus its
own white sensor noise of ``netd``, every pose drawn from the true one with the σ it states in ``cameras.json``
(centre ``center_std`` m, rotation ``rotation_std_deg`` about the camera axes: the GNSS/adjustment noise of a flight),
then ``ortho`` on the true DSM (its σ 0: exact) with the NETD estimated from the frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FRAMES = [18, 19, 20, 33, 34]
ROOF = 0  # building 0: 20 x 12 m, bitumen, under all five frames


def _render(scene, frames):
    from thermogrammetry.synthetic.survey import render_frame

    return [render_frame(scene, k, sensor=False)["image_k"].astype(np.float64) for k in frames]


def _flight(folder, scene, frames, clean, rng, *, netd, center_std, rotation_std_deg):
    """One flight's folder: the noise-free frames ``clean`` plus white noise, the true poses drawn with their σ."""
    import tifffile

    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage
    from thermogrammetry.products.ortho_sigma import _rot

    folder = Path(folder)
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    images = []
    for k, img in zip(frames, clean):
        fr = scene.frames[k]
        tifffile.imwrite(folder / "frames" / f"{fr.name}.tif", (img + rng.normal(0.0, netd, img.shape)).astype(np.float32))
        C = fr.pose.center + rng.normal(0.0, center_std, 3)
        R = _rot(np.radians(rng.normal(0.0, rotation_std_deg, 3))) @ fr.pose.R
        im = OrientedImage(fr.name, "thermal", R, -R @ C, frame=f"frames/{fr.name}.tif", unit="K")
        im.center_std = np.full(3, center_std)
        im.rotation_std_deg = np.full(3, rotation_std_deg)
        images.append(im)
    OrientedCameras({"thermal": scene.camera}, images, crs=f"EPSG:{scene.terrain.epsg}",
                    notes="synthetic flight: true poses drawn with their stated sigma (test helper)").save(folder / "cameras.json")


def two_flights(root, *, pairs=1, first_seed: int = 0, frames=FRAMES, roof: int = ROOF, warming_k: float = 0.5,
                netd: float = 0.05, center_std: float = 0.005, rotation_std_deg: float = 0.005, dsm_gsd: float = 0.2,
                sampling: str = "nearest") -> dict:
    """Build ``pairs`` pairs of flights, ``root/pair<k>/oA/ortho.tif`` and ``root/pair<k>/oB/ortho.tif`` (each with
    ``ortho_sigma.tif``), pair ``k`` drawn with the seed ``first_seed + k`` (the frames are rendered once).

    Returns ``pairs`` (per pair ``A``, ``B`` (ortho paths), ``netd`` (the two orthos' estimated NETD), ``dir``),
    ``A``, ``B`` (those of the first pair), ``scene``, ``roof``, ``frames`` (the noise-free frames of flight A)
    and ``apparent_warming`` (K: the median of B − A over the noise-free frames' pixels that see the change, i.e.
    the warming as the camera sees it through the roof's emissivity and the air)."""
    from survey_truth import small_survey_config, write_true_dsm

    from thermogrammetry.pipeline.ortho import run_ortho
    from thermogrammetry.products.ortho import OrthoConfig
    from thermogrammetry.products.ortho_sigma import SigmaConfig
    from thermogrammetry.synthetic.changes import warm_roof
    from thermogrammetry.synthetic.survey import make_survey

    root = Path(root)
    sc = make_survey(small_survey_config())
    write_true_dsm(root / "dsm.tif", sc, dsm_gsd)
    clean_a = _render(sc, frames)
    clean_b = _render(warm_roof(sc, roof, warming_k), frames)
    dk = np.concatenate([(b - a).ravel() for a, b in zip(clean_a, clean_b)])
    kw = dict(netd=netd, center_std=center_std, rotation_std_deg=rotation_std_deg)
    out = []
    for k in range(pairs):
        d = root / f"pair{k}"
        rng = np.random.default_rng([first_seed + k, 0xE7])
        _flight(d / "A", sc, frames, clean_a, rng, **kw)
        _flight(d / "B", sc, frames, clean_b, rng, **kw)
        netds = []
        for f in ("A", "B"):
            rep = run_ortho(d / f, root / "dsm.tif", d / f"o{f}", workers=0, config=OrthoConfig(sampling=sampling),
                            sigma=SigmaConfig(dsm_sigma_m=0.0))
            netds.append(rep["sigma"]["netd"])
        out.append({"A": d / "oA" / "ortho.tif", "B": d / "oB" / "ortho.tif", "netd": netds, "dir": d})
    return {"pairs": out, "A": out[0]["A"], "B": out[0]["B"], "scene": sc, "roof": roof, "frames": clean_a,
            "apparent_warming": float(np.median(dk[np.abs(dk) > 0.1 * warming_k]))}


def cell_classes(scene, ortho_path, roof: int = ROOF, margin_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """On the ortho's grid: the roof's interior (the roof rectangle shrunk by ``margin_m``) and the unchanged area
    (outside the rectangle grown by ``margin_m``: the cells near the roof's edge, whose pixels may mix roof and
    wall or ground, are in neither)."""
    import rasterio

    from thermogrammetry.synthetic.changes import building_footprint

    with rasterio.open(ortho_path) as s:
        tr, h, w = s.transform, s.height, s.width
    ter = scene.terrain
    x = tr.c + (np.arange(w) + 0.5) * tr.a - ter.origin_en[0]
    y = tr.f + (np.arange(h) + 0.5) * tr.e - ter.origin_en[1]
    X, Y = np.meshgrid(x, y)
    return (building_footprint(ter, roof, X, Y, grow_m=-margin_m),
            ~building_footprint(ter, roof, X, Y, grow_m=margin_m))
