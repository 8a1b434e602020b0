"""Bad-input cases of the verbs that read a survey folder and rasters (``dense``, ``ortho``, ``evaluate``), for the
corpus of ``tests/test_bad_inputs.py`` (which adds :data:`CASES` to its own).

Every input is a few bytes: a 3-image survey of 16 x 12 px frames (cameras 150 m above a 20 x 20 m DSM of 1 m
cells, EPSG:32633), written here. Each case returns ``(argv, expected_substrings, out_dir_that_must_not_exist)``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

CASES: dict = {}
CRS = "EPSG:32633"
X0, Y0 = 500_000.0, 5_000_000.0  # the DSM's top-left corner; the cameras fly above it


def _c(name):
    def deco(fn):
        CASES[name] = fn
        return fn
    return deco


def tiny_survey(t: Path, *, n: int = 3, unit: str = "K", frame=None, crs=CRS, mutate=None, model: str = "pinhole",
                params: dict | None = None, look_up: bool = False) -> Path:
    """``t/survey``: cameras.json (n nadir images 150 m up, on a 4 m grid) and its frames (``frame``: the array written
    for every image, default 300 K float32). ``mutate(d)`` edits the JSON dict before it is written."""
    import tifffile

    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    sv = t / "survey"
    (sv / "frames").mkdir(parents=True, exist_ok=True)
    cam = Camera(model, (16, 12), params or {"fx": 16.0, "fy": 16.0, "cx": 7.5, "cy": 5.5})
    R = np.eye(3) if look_up else np.diag([1.0, -1.0, -1.0])  # nadir: camera z = world -Z
    a = np.full((12, 16), 300.0, np.float32) if frame is None else frame
    images = []
    for k in range(n):
        C = np.array([X0 + 6.0 + 4.0 * (k % 2), Y0 - 6.0 - 4.0 * (k // 2), 150.0])
        tifffile.imwrite(sv / "frames" / f"f{k}.tif", a)
        images.append(OrientedImage(f"f{k}", "thermal", R, -R @ C, frame=f"frames/f{k}.tif", unit=unit))
    d = OrientedCameras({"thermal": cam}, images, crs=crs).to_dict()
    if mutate is not None:
        mutate(d)
    (sv / "cameras.json").write_text(json.dumps(d))
    return sv


def dsm(t: Path, z=None, *, transform=None, crs=CRS, w: int = 20, h: int = 20, name: str = "dsm.tif", sparse=False) -> Path:
    """A float32 GeoTIFF DSM (default 100 m everywhere, 1 m cells from (X0, Y0), north-up)."""
    import rasterio
    from rasterio.transform import Affine

    p = t / name
    tr = transform or Affine(1.0, 0.0, X0, 0.0, -1.0, Y0)
    kw = dict(driver="GTiff", width=w, height=h, count=1, dtype="float32", transform=tr, nodata=float("nan"))
    if crs is not None:
        kw["crs"] = crs
    if sparse:  # a header declaring w x h cells and (almost) no data: a few hundred bytes
        kw.update(tiled=True, blockxsize=256, blockysize=256, compress="deflate", SPARSE_OK="TRUE")
        with rasterio.open(p, "w", **kw):
            pass
        return p
    with rasterio.open(p, "w", **kw) as d:
        d.write((np.full((h, w), 100.0) if z is None else np.broadcast_to(z, (h, w))).astype(np.float32), 1)
    return p


def ortho_argv(t: Path, sv: Path, d: Path, *extra) -> list[str]:
    return ["ortho", str(sv), "--dsm", str(d), "-o", str(t / "OUT"), "--workers", "0", *extra]


def dense_argv(t: Path, sv: Path, *extra) -> list[str]:
    return ["dense", str(sv), "-o", str(t / "OUT"), "--workers", "0", *extra]


# ------------------------------------------------------------------------------------------------ DSM rasters
@_c("ortho: DSM without any finite height (all NaN)")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, np.nan)), ["dsm.tif", "no finite height", "400 cells"], t / "OUT"


@_c("ortho: DSM of infinite heights only")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, np.inf)), ["dsm.tif", "400 infinite height(s)", "row 0, column 0"], t / "OUT"


@_c("ortho: DSM with one infinite height")
def _(t):
    z = np.full((20, 20), 100.0)
    z[3, 7] = -np.inf
    return ortho_argv(t, tiny_survey(t), dsm(t, z)), ["dsm.tif", "1 infinite height(s)", "row 3, column 7", "-inf"], t / "OUT"


@_c("ortho: DSM of 1x1 cell")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, w=1, h=1)), ["dsm.tif", "1 x 1 cell", "at least 2 x 2"], t / "OUT"


@_c("ortho: DSM above every camera")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, 5000.0)), ["dsm.tif", "above the highest camera", "Z 150.00"], t / "OUT"


@_c("ortho: rotated DSM")
def _(t):
    from rasterio.transform import Affine

    tr = Affine.translation(X0, Y0) * Affine.rotation(30.0) * Affine.scale(1.0, -1.0)
    return ortho_argv(t, tiny_survey(t), dsm(t, transform=tr)), ["dsm.tif", "rotated or sheared", "north-up"], t / "OUT"


@_c("ortho: south-up DSM")
def _(t):
    from rasterio.transform import Affine

    tr = Affine(1.0, 0.0, X0, 0.0, 1.0, Y0 - 20.0)
    return ortho_argv(t, tiny_survey(t), dsm(t, transform=tr)), ["dsm.tif", "south-up", "pixel height 1"], t / "OUT"


@_c("ortho: truncated DSM (the GDAL reason is kept)")
def _(t):
    p = dsm(t, np.random.default_rng(1).normal(100.0, 1.0, (200, 200)), w=200, h=200)
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return ortho_argv(t, tiny_survey(t), p), ["dsm.tif", "cannot be read", "IReadBlock failed"], t / "OUT"


@_c("ortho: DSM without georeferencing (a plain TIFF)")
def _(t):
    import tifffile

    p = t / "plain.tif"
    tifffile.imwrite(p, np.full((20, 20), 100.0, np.float32))
    return ortho_argv(t, tiny_survey(t), p), ["plain.tif", "no georeferencing"], t / "OUT"


@_c("ortho: DSM without CRS, survey in EPSG:32633")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, crs=None)), ["dsm.tif", "has no CRS", "EPSG:32633", "cameras.json"], t / "OUT"


@_c("ortho: DSM in a CRS, survey in a local frame")
def _(t):
    return ortho_argv(t, tiny_survey(t, crs=None), dsm(t)), ["dsm.tif", "EPSG:32633", "no CRS (a local frame)"], t / "OUT"


@_c("ortho: DSM in another CRS than the survey")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, crs="EPSG:32632")), ["dsm.tif", "EPSG:32632", "EPSG:32633", "reproject"], t / "OUT"


@_c("ortho: DSM declaring 50,000 x 50,000 cells")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t, w=50_000, h=50_000, sparse=True)), \
        ["dsm.tif", "50000 x 50000 = 2,500,000,000 cells", "--max-cells"], t / "OUT"


@_c("ortho: --gsd 0.0001 (a mosaic above the cell cap)")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t), "--gsd", "0.0001"), \
        ["ortho grid", "200000 x 200000 = 40,000,000,000 cells", "--max-cells"], t / "OUT"


@_c("ortho: --max-cells below the DSM's size")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t), "--max-cells", "100"), ["dsm.tif", "20 x 20 = 400 cells", "cap of 100"], t / "OUT"


@_c("ortho: --max-cells 0")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t), "--max-cells", "0"), ["--max-cells 0", "positive integer"], t / "OUT"


@_c("ortho: --workers 1000")
def _(t):
    import os

    n = len(os.sched_getaffinity(0))
    argv = ortho_argv(t, tiny_survey(t), dsm(t))
    argv[argv.index("--workers") + 1] = "1000"
    return argv, ["--workers 1000", f"the {n} core(s)", "--scheduler"], t / "OUT"


@_c("ortho: cameras that see no cell of the DSM (empty mosaic)")
def _(t):
    return ortho_argv(t, tiny_survey(t, look_up=True), dsm(t)), ["dsm.tif", "no cell of the", "is seen by any"], t / "OUT"


@_c("ortho: empty cameras.json")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d.__setitem__("images", []))
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "0 oriented thermal image(s)", "ortho needs at least 1"], t / "OUT"


@_c("ortho: every frame damaged")
def _(t):
    sv = tiny_survey(t)
    for p in (sv / "frames").glob("*.tif"):
        p.write_bytes(p.read_bytes()[:40])
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "0 usable frame(s) of 3", "f0: ", "f0.tif"], t / "OUT"


# ------------------------------------------------------------------------------------------------ cameras.json
@_c("ortho: NaN in a pose (the message keeps the bracketed value)")
def _(t):
    def nan_t(d):
        d["images"][1]["cam_from_world"]["t"] = [float("nan"), 1, 0]
        d["images"][1].pop("center")
    return ortho_argv(t, tiny_survey(t, mutate=nan_t), dsm(t)), \
        ["cameras.json", "images[1].cam_from_world.t", "got [nan, 1, 0]"], t / "OUT"


@_c("ortho: implausible distortion k1 = 1e6")
def _(t):
    sv = tiny_survey(t, model="opencv", params={"fx": 16.0, "fy": 16.0, "cx": 7.5, "cy": 5.5, "k1": 1e6})
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "cameras.thermal", "k1=1e+06", "image size"], t / "OUT"


@_c("ortho: implausible focal length")
def _(t):
    sv = tiny_survey(t, params={"fx": 1e9, "fy": 16.0, "cx": 7.5, "cy": 5.5})
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "fx = 1e+09 px", "0.64..3200"], t / "OUT"


@_c("ortho: infinite sigma of a centre")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d["images"][2].__setitem__("center_std", [0.1, float("inf"), 0.1]))
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "images[2].center_std[1] = inf", "finite sigma"], t / "OUT"


@_c("ortho: frame path /etc/passwd")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d["images"][0].__setitem__("frame", "/etc/passwd"))
    return ortho_argv(t, sv, dsm(t)), ["cameras.json", "images[0].frame = '/etc/passwd'", "outside the survey folder"], t / "OUT"


@_c("ortho: frame path escaping with ..")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d["images"][1].__setitem__("frame", "frames/../../secret.tif"))
    return ortho_argv(t, sv, dsm(t)), ["images[1].frame = 'frames/../../secret.tif'", "outside the survey folder"], t / "OUT"


@_c("ortho: inline camera disagreeing with the file's cameras")
def _(t):
    def other(d):
        d["images"][0]["camera"] = json.loads(json.dumps(d["cameras"]["thermal"]))
        d["images"][0]["camera"]["params"]["fx"] = 20.0
    return ortho_argv(t, tiny_survey(t, mutate=other), dsm(t)), \
        ["images[0].camera", "disagrees with cameras.thermal", "fx"], t / "OUT"


@_c("ortho: colour 8-bit frames labelled K")
def _(t):
    sv = tiny_survey(t, frame=np.zeros((12, 16, 3), np.uint8))
    return ortho_argv(t, sv, dsm(t)), ["f0.tif", "uint8 3-band (colour)", "declares kelvin"], t / "OUT"


@_c("ortho: float kelvin frames labelled counts")
def _(t):
    sv = tiny_survey(t, unit="counts")
    return ortho_argv(t, sv, dsm(t)), ["f0.tif", "float32 1-band", "declares raw sensor counts"], t / "OUT"


@_c("ortho: a projection centre 1e12 m away")
def _(t):
    def far(d):
        d["images"][0]["cam_from_world"]["t"] = [1e12, 0, 0]
        d["images"][0].pop("center")
    return ortho_argv(t, tiny_survey(t, mutate=far), dsm(t)), ["images[0]", "projection centre", "beyond 1e+08 m"], t / "OUT"


@_c("dense: unknown EPSG code in cameras.json")
def _(t):
    return dense_argv(t, tiny_survey(t, crs="EPSG:999999")), ["cameras.json", "'EPSG:999999'", "not a coordinate reference system"], t / "OUT"


@_c("dense: empty cameras.json")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d.__setitem__("images", []))
    return dense_argv(t, sv), ["cameras.json", "0 oriented thermal image(s)", "dense needs at least 3"], t / "OUT"


@_c("dense: --workers 1000")
def _(t):
    argv = dense_argv(t, tiny_survey(t))
    argv[argv.index("--workers") + 1] = "1000"
    return argv, ["--workers 1000", "core(s)"], t / "OUT"


@_c("dense: --gsd 0.0001 (a DSM above the cell cap)")
def _(t):
    return dense_argv(t, tiny_survey(t, n=4), "--gsd", "0.0001"), ["--gsd 0.0001", "cells", "--max-cells"], t / "OUT"


@_c("dense: 40,000 images, each name twice (linear-time check)")
def _(t):
    def many(d):
        im = {k: v for k, v in d["images"][0].items() if k not in ("camera", "center", "source")}
        d["images"] = [dict(im, name=f"i{k % 20_000}") for k in range(40_000)]
    return dense_argv(t, tiny_survey(t, mutate=many)), ["cameras.json", "unique", "'i0'"], t / "OUT"


# ------------------------------------------------------------------------------------------------ evaluate
@_c("evaluate: DSM without any finite height")
def _(t):
    return ["evaluate", "--dsm", str(dsm(t, np.nan)), "--reference", str(dsm(t, name="ref.tif")), "-o", str(t / "OUT")], \
        ["dsm.tif", "no finite height"], t / "OUT"


@_c("evaluate: rotated DSM")
def _(t):
    from rasterio.transform import Affine

    tr = Affine.translation(X0, Y0) * Affine.rotation(10.0) * Affine.scale(1.0, -1.0)
    return ["evaluate", "--dsm", str(dsm(t, transform=tr)), "--reference", str(dsm(t, name="ref.tif")), "-o", str(t / "OUT")], \
        ["dsm.tif", "rotated or sheared"], t / "OUT"


@_c("evaluate: reference without CRS")
def _(t):
    return ["evaluate", "--dsm", str(dsm(t)), "--reference", str(dsm(t, name="ref.tif", crs=None)), "-o", str(t / "OUT")], \
        ["ref.tif", "no CRS", "EPSG:32633"], t / "OUT"


@_c("evaluate: reference declaring 50,000 x 50,000 cells")
def _(t):
    return ["evaluate", "--dsm", str(dsm(t)), "--reference", str(dsm(t, name="ref.tif", w=50_000, h=50_000, sparse=True)),
            "-o", str(t / "OUT")], ["ref.tif", "2,500,000,000 cells", "--max-cells"], t / "OUT"


@_c("evaluate: reference not overlapping the DSM (nothing to compare)")
def _(t):
    from rasterio.transform import Affine

    ref = dsm(t, name="ref.tif", transform=Affine(1.0, 0.0, X0 + 1000.0, 0.0, -1.0, Y0))
    return ["evaluate", "--dsm", str(dsm(t)), "--reference", str(ref), "-o", str(t / "OUT")], \
        ["ref.tif", "no cell of the DSM", "in both rasters"], t / "OUT"


@_c("evaluate: check points outside the DSM")
def _(t):
    cp = t / "cp.csv"
    cp.write_text(f"id,X,Y,Z\n1,{X0 - 500},{Y0},100\n2,{X0 - 600},{Y0},100\n")
    return ["evaluate", "--dsm", str(dsm(t)), "--checkpoints", str(cp), "-o", str(t / "OUT")], \
        ["cp.csv", "none of the 2 check point(s)"], t / "OUT"


# ------------------------------------------------------------------------------------------------ the task runner
@_c("survey: --workers 1000")
def _(t):
    (t / "in").mkdir()
    for k in range(3):
        np.savetxt(t / "in" / f"f{k}.csv", 300.0 + np.random.default_rng(k).random((24, 32)), delimiter=",")
    return ["survey", str(t / "in"), "-o", str(t / "OUT"), "--workers", "1000"], ["--workers 1000", "core(s)"], t / "OUT"
