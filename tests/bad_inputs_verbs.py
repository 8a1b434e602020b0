"""Bad-input cases of ``survey``, ``texture``, ``facade`` and ``plan``, and the output-folder and CSV cases of every
verb that reads a survey folder, for the corpus of ``tests/test_bad_inputs.py`` (which adds :data:`CASES` to its own).

The inputs are those of :mod:`bad_inputs_products` (a 3-image survey of 16 x 12 px frames 150 m above a 20 x 20 m
DSM, EPSG:32633), a flat mesh 50 m under the cameras for ``texture``, and a few lines of CSV. Each case returns
``(argv, expected_substrings, out_dir_that_must_not_exist_or_None)``; where OUT is a folder the user already has (the
input folder itself), ``None``: the corpus then checks that every file it held is still there, byte for byte.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bad_inputs_products import CRS, X0, Y0, dense_argv, dsm, ortho_argv, tiny_survey

CASES: dict = {}


def _c(name):
    def deco(fn):
        CASES[name] = fn
        return fn
    return deco


def flat_mesh(t: Path, *, z: float = 100.0, nan_vertex: bool = False, name: str = "mesh.obj") -> Path:
    """A 20 x 20 m square of 2 triangles at height ``z`` under the tiny survey's cameras (normal up, towards them)."""
    v = [(X0, Y0 - 20.0, z), (X0 + 20.0, Y0 - 20.0, z), (X0 + 20.0, Y0, z), (X0, Y0, z)]
    if nan_vertex:
        v[2] = (float("nan"), Y0, z)
    lines = [f"v {x} {y} {zz}" for x, y, zz in v] + ["f 1 2 3", "f 1 3 4"]
    p = t / name
    p.write_text("\n".join(lines) + "\n")
    return p


def texture_argv(t: Path, sv: Path, mesh: Path, *extra, out: Path | None = None) -> list[str]:
    return ["texture", str(sv), "--mesh", str(mesh), "-o", str(out or t / "OUT"), "--fit-poses", "off", *extra]


def facade_argv(t: Path, sv: Path, *extra, out: Path | None = None) -> list[str]:
    return ["facade", str(sv), "-o", str(out or t / "OUT"), "--plane", f"{X0 + 10},{Y0 - 10},100,0,0,1", *extra]


def plan_argv(t: Path, *extra) -> list[str]:
    return ["plan", "--focal-px", "1000", "--image-size", "640x512", "-o", str(t / "OUT"), *extra]


def frames_folder(t: Path, n: int = 3) -> Path:
    """``t/in``: n float32 kelvin TIFF frames of 32 x 24 px (what ``survey`` is given)."""
    import tifffile

    (t / "in").mkdir(parents=True, exist_ok=True)
    for k in range(n):
        tifffile.imwrite(t / "in" / f"f{k}.tif", (300.0 + np.random.default_rng(k).random((24, 32))).astype(np.float32))
    return t / "in"


def survey_argv(t: Path, *extra, out: Path | None = None) -> list[str]:
    return ["survey", str(frames_folder(t)), "-o", str(out or t / "OUT"), "--workers", "0", "--input-unit", "K", *extra]


def latin1(t: Path, name: str, text: str) -> Path:
    p = t / name
    p.write_bytes(text.encode("latin-1"))
    return p


# ------------------------------------------------------------------------------------------------ OUT and the input
@_c("survey: OUT is the input folder")
def _(t):
    argv = survey_argv(t)
    argv[argv.index("-o") + 1] = argv[1]
    return argv, ["is the input images' folder", "apart from the inputs"], None


@_c("survey: OUT inside the input folder")
def _(t):
    argv = survey_argv(t)
    argv[argv.index("-o") + 1] = str(Path(argv[1]) / "OUT")
    return argv, ["OUT", "lies inside the input images' folder"], Path(argv[1]) / "OUT"


@_c("dense: OUT is the survey folder")
def _(t):
    sv = tiny_survey(t)
    return ["dense", str(sv), "-o", str(sv), "--workers", "0"], ["is the survey folder", "apart from the inputs"], None


@_c("ortho: OUT contains the survey folder")
def _(t):
    sv = tiny_survey(t)
    argv = ortho_argv(t, sv, dsm(t))
    argv[argv.index("-o") + 1] = str(t)
    return argv, ["contains the survey folder", "survey"], None


@_c("texture: OUT a symlink to the survey folder")
def _(t):
    sv = tiny_survey(t)
    (t / "link").symlink_to(sv, target_is_directory=True)
    return texture_argv(t, sv, flat_mesh(t), out=t / "link"), ["link (a link to", "is the survey folder"], None


@_c("facade: OUT is the survey folder")
def _(t):
    sv = tiny_survey(t)
    return facade_argv(t, sv, out=sv), ["is the survey folder", "apart from the inputs"], None


# ------------------------------------------------------------------------------------------------ texture
@_c("texture: mesh with a NaN vertex")
def _(t):
    return texture_argv(t, tiny_survey(t), flat_mesh(t, nan_vertex=True)), ["mesh.obj", "1 of its 4 vertices", "[nan, 5000000.0, 100.0]"], t / "OUT"


def _bad_mesh(t, name, text):
    """``texture`` on a mesh file ``name`` holding ``text``: refused, naming the file."""
    p = t / name
    p.write_text(text)
    return texture_argv(t, tiny_survey(t), p), [name], t / "OUT"


@_c("texture: empty mesh file")
def _(t):
    return _bad_mesh(t, "mesh.obj", "")


@_c("texture: mesh file of text, not a mesh")
def _(t):
    return _bad_mesh(t, "mesh.ply", "this is a shopping list\nmilk\n")


@_c("texture: face index beyond the vertices")
def _(t):
    return _bad_mesh(t, "mesh.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")


@_c("texture: empty cameras.json")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d.__setitem__("images", []))
    return texture_argv(t, sv, flat_mesh(t)), ["survey", "no usable thermal image", "cameras.json lists none"], t / "OUT"


@_c("texture: frame path /etc/passwd")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d["images"][0].__setitem__("frame", "/etc/passwd"))
    return texture_argv(t, sv, flat_mesh(t)), ["cameras.json", "'/etc/passwd'", "outside the survey folder"], t / "OUT"


@_c("texture: NaN in a pose")
def _(t):
    def nan_t(d):
        d["images"][1]["cam_from_world"]["t"] = [float("nan"), 1, 0]
        d["images"][1].pop("center")
    return texture_argv(t, tiny_survey(t, mutate=nan_t), flat_mesh(t)), \
        ["cameras.json", "images[1].cam_from_world.t", "got [nan, 1, 0]"], t / "OUT"


@_c("texture: --texel-size 0")
def _(t):
    return texture_argv(t, tiny_survey(t), flat_mesh(t), "--texel-size", "0"), ["texel_size_m=0.0", "positive"], t / "OUT"


@_c("texture: --texel-size nan")
def _(t):
    return texture_argv(t, tiny_survey(t), flat_mesh(t), "--texel-size", "nan"), ["texel_size_m=nan", "positive"], t / "OUT"


@_c("texture: --texel-size 1e-6 (an atlas of 4e14 texels)")
def _(t):
    return texture_argv(t, tiny_survey(t), flat_mesh(t), "--texel-size", "1e-6"), ["--texel-size 1e-06", "mesh.obj", "4e+14 texels", "at least 0.00488 m"], t / "OUT"


@_c("texture: mesh far from the cameras (another CRS)")
def _(t):
    return texture_argv(t, tiny_survey(t), flat_mesh(t, z=-1e6)), ["mesh.obj", "no face of the mesh"], t / "OUT"


# ------------------------------------------------------------------------------------------------ facade
@_c("facade: empty cameras.json")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d.__setitem__("images", []))
    return facade_argv(t, sv), ["survey", "no usable thermal image", "cameras.json lists none"], t / "OUT"


@_c("facade: --plane with NaN")
def _(t):
    argv = facade_argv(t, tiny_survey(t))
    argv[argv.index("--plane") + 1] = f"{X0},{Y0},nan,0,0,1"
    return argv, ["--plane '500000.0,5000000.0,nan,0,0,1'", "six numbers"], t / "OUT"


@_c("facade: --cell 1e-5 (a mosaic above the cell cap)")
def _(t):
    return facade_argv(t, tiny_survey(t), "--cell", "1e-5"), ["1e-05 per cell", "over 60 million cells", "larger --cell"], t / "OUT"


@_c("facade: --cell nan")
def _(t):
    return facade_argv(t, tiny_survey(t), "--cell", "nan"), ["--cell nan", "> 0"], t / "OUT"


@_c("facade: frame path escaping with ..")
def _(t):
    sv = tiny_survey(t, mutate=lambda d: d["images"][1].__setitem__("frame", "frames/../../secret.tif"))
    return facade_argv(t, sv), ["images[1].frame = 'frames/../../secret.tif'", "outside the survey folder"], t / "OUT"


@_c("facade: colour 8-bit frames labelled K")
def _(t):
    sv = tiny_survey(t, frame=np.zeros((12, 16, 3), np.uint8))
    return facade_argv(t, sv), ["f0: frame shape (12, 16, 3)", "single-band temperature image"], t / "OUT"


# ------------------------------------------------------------------------------------------------ plan
@_c("plan: --gsd nan")
def _(t):
    return plan_argv(t, "--gsd", "nan", "--corners", "0,0 100,0 100,50 0,50"), ["gsd_m=nan", "positive"], t / "OUT"


@_c("plan: --gsd 0")
def _(t):
    return plan_argv(t, "--gsd", "0", "--corners", "0,0 100,0 100,50 0,50"), ["gsd_m=0.0", "positive"], t / "OUT"


@_c("plan: --gsd 1e6 (a flight 1e9 m up)")
def _(t):
    return plan_argv(t, "--gsd", "1e6", "--corners", "0,0 100,0 100,50 0,50"), \
        ["gsd_m=1e+06", "1e+09 m above ground", "above 20000 m"], t / "OUT"


@_c("plan: corner with inf")
def _(t):
    return plan_argv(t, "--gsd", "0.1", "--corners", "0,0 inf,0 100,50 0,50"), ["vertex 2 of 4 is [inf, 0.0]", "finite"], t / "OUT"


@_c("plan: --image-size 0x0")
def _(t):
    return ["plan", "--focal-px", "1000", "--image-size", "0x0", "--gsd", "0.1", "--corners", "0,0 100,0 100,50 0,50",
            "-o", str(t / "OUT")], ["--image-size '0x0'", "WxH"], t / "OUT"


@_c("plan: --forward 1.0 (no advance between photos)")
def _(t):
    return plan_argv(t, "--gsd", "0.1", "--corners", "0,0 100,0 100,50 0,50", "--forward", "1.0"), \
        ["forward_overlap=1.0", "[0, 1)"], t / "OUT"


@_c("plan: area GeoJSON not JSON")
def _(t):
    p = t / "area.geojson"
    p.write_text("{type: Polygon")
    return plan_argv(t, "--gsd", "0.1", "--area", str(p)), ["area.geojson", "not valid JSON", "line 1"], t / "OUT"


@_c("plan: area GeoJSON in Latin-1")
def _(t):
    area = {"type": "Feature", "properties": {"name": "Gro\xdfe Wiese"}, "geometry": {"type": "Polygon", "coordinates": [[
        [6.5600, 46.5200], [6.5650, 46.5200], [6.5650, 46.5230], [6.5600, 46.5230], [6.5600, 46.5200]]]}}
    p = latin1(t, "area.geojson", json.dumps(area, ensure_ascii=False))
    return plan_argv(t, "--gsd", "0.1", "--area", str(p)), ["area.geojson", "utf-8", "0xdf"], t / "OUT"


@_c("plan: polygon of 2 corners")
def _(t):
    return plan_argv(t, "--gsd", "0.1", "--corners", "0,0 100,0"), ["at least 3 (x, y) vertices", "(2, 2)"], t / "OUT"


# ------------------------------------------------------------------------------------------------ survey
@_c("survey: GNSS CSV in Latin-1")
def _(t):
    g = latin1(t, "gnss.csv", "image,X,Y,Z\nf0,1.0,2.0,3.0\nf1,1.5,2.0,3.0\nf\xe42,2.0,2.0,3.0\n")
    return survey_argv(t, "--gnss", str(g), "--crs", CRS), ["gnss.csv", "not a UTF-8 text file"], t / "OUT"


@_c("survey: GNSS CSV with NaN height")
def _(t):
    g = t / "gnss.csv"
    g.write_text("image,X,Y,Z\nf0,1.0,2.0,3.0\nf1,1.5,2.0,nan\nf2,2.0,2.0,3.0\n")
    return survey_argv(t, "--gnss", str(g), "--crs", CRS), ["gnss.csv", "row 3", "Z = 'nan' is not finite"], t / "OUT"


@_c("survey: GCP CSV in Latin-1")
def _(t):
    g = latin1(t, "gcps.csv", "id,X,Y,Z\nGCP1,1.0,2.0,3.0\nGCP\xb02,1.5,2.0,3.0\n")
    m = t / "gcp_measurements.csv"
    m.write_text("image,id,x,y\nf0,GCP1,10,10\n")
    return survey_argv(t, "--gcps", str(g), "--gcp-measurements", str(m), "--crs", CRS), ["gcps.csv", "not a UTF-8 text file"], t / "OUT"


@_c("survey: GCP with an infinite coordinate")
def _(t):
    g = t / "gcps.csv"
    g.write_text("id,X,Y,Z\nGCP1,1.0,2.0,3.0\nGCP2,inf,2.0,3.0\n")
    m = t / "gcp_measurements.csv"
    m.write_text("image,id,x,y\nf0,GCP1,10,10\n")
    return survey_argv(t, "--gcps", str(g), "--gcp-measurements", str(m), "--crs", CRS), ["gcps.csv", "row 3", "X = 'inf' is not finite"], t / "OUT"


@_c("survey: unknown --crs EPSG:999999")
def _(t):
    g = t / "gnss.csv"
    g.write_text("image,X,Y,Z\nf0,1.0,2.0,3.0\nf1,1.5,2.0,3.0\nf2,2.0,2.0,3.0\n")
    return survey_argv(t, "--gnss", str(g), "--crs", "EPSG:999999"), ["'EPSG:999999'", "not a coordinate reference system"], t / "OUT"


@_c("survey: every frame truncated")
def _(t):
    argv = survey_argv(t)
    for p in Path(argv[1]).glob("*.tif"):
        p.write_bytes(p.read_bytes()[:50])
    return argv, ["no usable input image", "f0.tif", "truncated or damaged"], t / "OUT"


@_c("survey: camera.json with NaN focal length")
def _(t):
    from thermogrammetry.camera import Camera

    Camera("pinhole", (32, 24), {"fx": 30.0, "fy": 30.0, "cx": 15.5, "cy": 11.5}).save(t / "camera.json")
    d = json.loads((t / "camera.json").read_text())
    text = json.dumps(d).replace("30.0", "NaN", 1)
    (t / "camera.json").write_text(text)
    return survey_argv(t, "--camera", str(t / "camera.json")), ["camera.json", "params['fx']", "got nan"], t / "OUT"


# ------------------------------------------------------------------------------------------------ dense, ortho, evaluate
@_c("dense: every frame truncated")
def _(t):
    sv = tiny_survey(t)
    for p in (sv / "frames").glob("*.tif"):
        p.write_bytes(p.read_bytes()[:40])
    return dense_argv(t, sv), ["cameras.json", "0 usable frame(s) of 3"], t / "OUT"


@_c("ortho: --gsd 1e6 (one cell larger than the DSM)")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t), "--gsd", "1e6"), ["--gsd 1e+06 m", "1 x 1 cell(s)", "at most 10 m"], t / "OUT"


@_c("ortho: --gsd nan")
def _(t):
    return ortho_argv(t, tiny_survey(t), dsm(t), "--gsd", "nan"), ["--gsd nan", "positive cell size"], t / "OUT"


@_c("evaluate: check-point CSV in Latin-1")
def _(t):
    cp = latin1(t, "cp.csv", f"id,X,Y,Z\nP\xe41,{X0 + 5},{Y0 - 5},100\n")
    return ["evaluate", "--dsm", str(dsm(t)), "--checkpoints", str(cp), "-o", str(t / "OUT")], \
        ["cp.csv", "not a UTF-8 text file"], t / "OUT"


@_c("evaluate: check-point CSV with a NaN height")
def _(t):
    cp = t / "cp.csv"
    cp.write_text(f"id,X,Y,Z\n1,{X0 + 5},{Y0 - 5},nan\n2,{X0 + 6},{Y0 - 6},100\n")
    return ["evaluate", "--dsm", str(dsm(t)), "--checkpoints", str(cp), "-o", str(t / "OUT")], \
        ["cp.csv", "line 2", "Z = 'nan' is not finite"], t / "OUT"


@_c("evaluate: truncated reference DSM")
def _(t):
    ref = dsm(t, np.random.default_rng(2).normal(100.0, 1.0, (200, 200)), w=200, h=200, name="ref.tif")
    ref.write_bytes(ref.read_bytes()[: ref.stat().st_size // 2])
    return ["evaluate", "--dsm", str(dsm(t)), "--reference", str(ref), "-o", str(t / "OUT")], \
        ["ref.tif", "cannot be read"], t / "OUT"


# ------------------------------------------------------------------------------------------------ evaluate --ortho
def tiny_ortho(t: Path, name: str = "A", *, unit: str | None = "K", x0: float = X0, sigma: bool | str = True,
               value: float = 300.0) -> Path:
    """``t/name/ortho.tif``: 20 x 20 cells of 1 m from (x0, Y0) holding ``value`` with the unit tag ``unit``, and (with
    ``sigma``) its ``ortho_sigma.tif`` of 0.05 (``sigma="shifted"``: on a grid one cell east)."""
    import rasterio
    from rasterio.transform import Affine

    d = t / name
    d.mkdir(parents=True, exist_ok=True)
    kw = dict(driver="GTiff", width=20, height=20, dtype="float32", crs=CRS, nodata=float("nan"))
    with rasterio.open(d / "ortho.tif", "w", count=1, transform=Affine(1.0, 0.0, x0, 0.0, -1.0, Y0), **kw) as o:
        o.write(np.full((1, 20, 20), value, np.float32))
        if unit:
            o.update_tags(unit=unit)
    if sigma:
        sx = x0 + (1.0 if sigma == "shifted" else 0.0)
        with rasterio.open(d / "ortho_sigma.tif", "w", count=4, transform=Affine(1.0, 0.0, sx, 0.0, -1.0, Y0), **kw) as s:
            s.write(np.full((4, 20, 20), 0.05, np.float32))
            if unit:
                s.update_tags(unit=unit)
    return d / "ortho.tif"


def compare_argv(t: Path, a: Path, *extra) -> list[str]:
    return ["evaluate", "--ortho", str(a), "-o", str(t / "OUT"), *extra]


@_c("evaluate: orthos in different units (K against counts)")
def _(t):
    a, b = tiny_ortho(t, "A"), tiny_ortho(t, "B", unit="counts", value=16000.0)
    return compare_argv(t, a, "--against", str(b)), [f"{b} is in 'counts'", f"{a} in 'K'", "different units"], t / "OUT"


@_c("evaluate: orthos in K and °C")
def _(t):
    a, b = tiny_ortho(t, "A"), tiny_ortho(t, "B", unit="°C", value=27.0)
    return compare_argv(t, a, "--against", str(b)), [f"{b} is in '°C'", f"{a} in 'K'", "--unit K"], t / "OUT"


@_c("evaluate: orthos that do not overlap")
def _(t):
    a, b = tiny_ortho(t, "A"), tiny_ortho(t, "B", x0=X0 + 1000.0)
    return compare_argv(t, a, "--against", str(b)), [str(b), "does not overlap", str(a), "X 501000.00..501020.00"], t / "OUT"


@_c("evaluate: --against ortho without its ortho_sigma.tif")
def _(t):
    a, b = tiny_ortho(t, "A"), tiny_ortho(t, "B", sigma=False)
    return compare_argv(t, a, "--against", str(b)), [str(b), "no ortho_sigma.tif beside", "--reference-sigma"], t / "OUT"


@_c("evaluate: ortho_sigma.tif on another grid than its ortho")
def _(t):
    a, b = tiny_ortho(t, "A", sigma="shifted"), tiny_ortho(t, "B")
    return compare_argv(t, a, "--against", str(b)), ["A/ortho_sigma.tif", "differs from", "one ortho run"], t / "OUT"


@_c("evaluate: ortho of display numbers")
def _(t):
    a, b = tiny_ortho(t, "A", unit="dn", value=128.0), tiny_ortho(t, "B", unit="dn", value=128.0)
    return compare_argv(t, a, "--against", str(b)), [str(a), "display numbers"], t / "OUT"


@_c("evaluate: reading outside the ortho")
def _(t):
    cp = t / "readings.csv"
    cp.write_text(f"id,X,Y,T\nin,{X0 + 5},{Y0 - 5},300.1\nfar,{X0 + 500},{Y0 - 5},300.2\n")
    return compare_argv(t, tiny_ortho(t), "--readings", str(cp)), \
        ["readings.csv, row 3", "point 'far'", "outside the ortho", "X 500000.00..500020.00"], t / "OUT"


@_c("evaluate: readings without a temperature column")
def _(t):
    cp = t / "readings.csv"
    cp.write_text(f"id,X,Y,Z\n1,{X0 + 5},{Y0 - 5},100\n")
    return compare_argv(t, tiny_ortho(t), "--readings", str(cp)), ["readings.csv", "missing column(s) T"], t / "OUT"


@_c("evaluate: readings against an ortho of counts")
def _(t):
    cp = t / "readings.csv"
    cp.write_text(f"X,Y,T\n{X0 + 5},{Y0 - 5},300.1\n")
    return compare_argv(t, tiny_ortho(t, unit="counts", value=16000.0), "--readings", str(cp)), \
        ["raw sensor counts", "readings.csv"], t / "OUT"


@_c("evaluate: --alpha 1.5")
def _(t):
    return compare_argv(t, tiny_ortho(t, "A"), "--against", str(tiny_ortho(t, "B")), "--alpha", "1.5"), \
        ["--alpha 1.5", "between 0 and 1"], t / "OUT"


@_c("evaluate: --offset-box without --remove-offset median")
def _(t):
    return compare_argv(t, tiny_ortho(t, "A"), "--against", str(tiny_ortho(t, "B")), "--offset-box",
                        f"{X0},{Y0 - 10},{X0 + 10},{Y0}"), ["--offset-box", "needs --remove-offset median"], t / "OUT"


@_c("evaluate: --offset-box outside the overlap")
def _(t):
    return compare_argv(t, tiny_ortho(t, "A"), "--against", str(tiny_ortho(t, "B")), "--remove-offset", "median",
                        "--offset-box", f"{X0 + 100},{Y0 - 10},{X0 + 110},{Y0}"), \
        ["--offset-box", "no compared cell has its centre in the box"], t / "OUT"


@_c("evaluate: --reference-sigma with --against")
def _(t):
    return compare_argv(t, tiny_ortho(t, "A"), "--against", str(tiny_ortho(t, "B")), "--reference-sigma", "0.1"), \
        ["--reference-sigma", "give --reference"], t / "OUT"


@_c("evaluate: --against with --dsm")
def _(t):
    return ["evaluate", "--dsm", str(dsm(t)), "--against", str(tiny_ortho(t, "B")), "-o", str(t / "OUT")], \
        ["--against", "temperature mode"], t / "OUT"


@_c("evaluate: --ortho and nothing to compare it with")
def _(t):
    return compare_argv(t, tiny_ortho(t)), ["nothing to compare the ortho with", "--against"], t / "OUT"


@_c("evaluate: OUT is the ortho's folder")
def _(t):
    a = tiny_ortho(t, "A")
    argv = compare_argv(t, a, "--against", str(tiny_ortho(t, "B")))
    argv[argv.index("-o") + 1] = str(a.parent)
    return argv, ["is the ortho's folder", "apart from the inputs"], None


# ------------------------------------------------------------------------------------------------ mesh
def plane_cloud(t: Path, *, name: str = "plane.xyz", n: int = 40, offset=(X0, Y0, 100.0)) -> Path:
    """An n x n grid of points, 5 cm apart, on a horizontal plane at ``offset`` (x y z text, 3 decimals)."""
    g = np.arange(n) * 0.05
    x, y = np.meshgrid(g, g)
    P = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)] + np.asarray(offset)
    p = t / name
    np.savetxt(p, P, fmt="%.3f")
    return p


def mesh_argv(t: Path, cloud: Path, *extra, out: Path | None = None) -> list[str]:
    return ["mesh", str(cloud), "-o", str(out or t / "OUT"), "--workers", "0", *extra]


@_c("mesh: OUT is the dense folder")
def _(t):
    d = t / "dense"
    d.mkdir()
    (d / "dense.json").write_text(json.dumps({"crs": CRS, "cloud_files": ["cloud.xyz"]}))
    return mesh_argv(t, d, out=d), ["is the dense folder", "apart from the inputs"], None


@_c("mesh: OUT inside the dense folder")
def _(t):
    d = t / "dense"
    d.mkdir()
    (d / "dense.json").write_text(json.dumps({"crs": CRS}))
    return mesh_argv(t, d, out=d / "OUT"), ["lies inside the dense folder", "apart from the inputs"], d / "OUT"


@_c("mesh: folder without dense.json")
def _(t):
    (t / "clouds").mkdir()
    return mesh_argv(t, t / "clouds"), ["clouds: a folder without dense.json", "output folder of `thermogrammetry dense`"], t / "OUT"


@_c("mesh: dense.json listing no cloud that exists")
def _(t):
    d = t / "dense"
    d.mkdir()
    (d / "dense.json").write_text(json.dumps({"crs": CRS, "cloud_files": ["cloud.las", "cloud.ply"]}))
    return mesh_argv(t, d), ["dense.json lists ['cloud.las', 'cloud.ply']", "none of them is in the folder"], t / "OUT"


@_c("mesh: unknown cloud suffix")
def _(t):
    p = t / "scan.pcd"
    p.write_text("VERSION .7\n")
    return mesh_argv(t, p), ["scan.pcd: unknown cloud suffix '.pcd'", ".las, .laz, .ply, .e57, .xyz"], t / "OUT"


@_c("mesh: cloud file missing")
def _(t):
    return mesh_argv(t, t / "nope.las"), ["nope.las: no such file or folder"], t / "OUT"


@_c("mesh: LAS file of text")
def _(t):
    p = t / "scan.las"
    p.write_text("not a point cloud\n")
    return mesh_argv(t, p), ["scan.las: cannot read as LAS/LAZ"], t / "OUT"


@_c("mesh: PLY without x y z")
def _(t):
    p = t / "scan.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float u\nproperty float v\nend_header\n1 2\n")
    return mesh_argv(t, p), ["scan.ply: the PLY vertex element has ['u', 'v']", "expected x y z"], t / "OUT"


@_c("mesh: XYZ with a word in a coordinate")
def _(t):
    p = t / "scan.xyz"
    p.write_text("1 2 3\n4 5 6\n7 eight 9\n")
    return mesh_argv(t, p), ["scan.xyz, line 3: '7 eight 9'", "at least three numbers"], t / "OUT"


@_c("mesh: XYZ with a NaN coordinate")
def _(t):
    p = plane_cloud(t)
    p.write_text(p.read_text() + "1 nan 3\n")
    return mesh_argv(t, p), ["plane.xyz: point 1600 (0-based) has non-finite coordinates", "[1.0, nan, 3.0]"], t / "OUT"


@_c("mesh: too few points")
def _(t):
    p = t / "few.xyz"
    p.write_text("0 0 0\n1 0 0\n0 1 0\n")
    return mesh_argv(t, p), ["few.xyz: 3 point(s)", "at least 100"], t / "OUT"


@_c("mesh: --edge 0")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--edge", "0"), ["--edge 0.0", "positive target edge length"], t / "OUT"


@_c("mesh: --edge nan")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--edge", "nan"), ["--edge nan", "positive target edge length"], t / "OUT"


@_c("mesh: --faces 2")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--faces", "2"), ["--faces 2", "whole number of triangles >= 4"], t / "OUT"


@_c("mesh: --edge and --faces")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--edge", "0.1", "--faces", "100"), ["--edge 0.1 and --faces 100", "give one of them"], t / "OUT"


@_c("mesh: --fill-holes -1")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--fill-holes", "-1"), ["--fill-holes -1.0", "in m² (>= 0"], t / "OUT"


@_c("mesh: --crs not a CRS")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--crs", "EPSG:999999"), ["--crs 'EPSG:999999'", "not a coordinate reference system"], t / "OUT"


@_c("mesh: --crs geographic")
def _(t):
    return mesh_argv(t, plane_cloud(t), "--crs", "EPSG:4326"), ["CRS EPSG:4326 is geographic", "projected CRS in metres"], t / "OUT"


@_c("mesh: --crs contradicting the file's")
def _(t):
    p = t / "scan.ply"
    p.write_text("ply\nformat ascii 1.0\ncomment crs EPSG:32633\nelement vertex 1\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n1 2 3\n")
    return mesh_argv(t, p, "--crs", "EPSG:32632"), ["--crs EPSG:32632", "states its CRS as EPSG:32633", "reproject"], t / "OUT"


@_c("mesh: --workers 1000")
def _(t):
    return mesh_argv(t, plane_cloud(t))[:-2] + ["--workers", "1000"], ["--workers 1000", "more worker processes"], t / "OUT"


@_c("mesh: E57 without pye57, or a damaged E57")
def _(t):
    p = t / "scan.e57"
    p.write_bytes(b"ASTM-E57" + bytes(40))
    try:
        import pye57  # noqa: F401
        expected = ["scan.e57: cannot read as E57"]
    except ImportError:
        expected = ["scan.e57: reading E57 needs the pye57 package", "pip install pye57"]
    return mesh_argv(t, p), expected, t / "OUT"
