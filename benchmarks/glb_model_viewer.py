"""Check: the textured GLB of ``thermogrammetry texture`` in a generic glTF viewer (Google's <model-viewer>).

A synthetic building, moved to UTM coordinates (``synthetic.building``: flat roof at 276 K, ground 279 K, walls 279-285 K warmer upwards, a
286 K occluder) is seen from a ring of stations 12 m above the ground, so that the roof is textured too. The frames
(noise-free renderings, TRUE poses) go through ``thermogrammetry texture --unit C``; its ``textured.glb`` is served
from 127.0.0.1 with the npm package ``@google/model-viewer`` (installed into a scratch folder outside the repository
with the machine's npm, together with ``playwright-core``, which drives Debian's Chromium: no browser download) and
rendered headless with the viewer's defaults apart from the camera orbit and a green background. Checked on the
screenshot:

(a) non-blank: the model covers part of the frame and its pixels carry the preview palette (inferno), i.e. pixels
    whose colour lies within a tolerance of the palette, spread over its range;
(b) upright: each textured pixel is mapped back to a temperature through the palette; the roof's pixels (within the
    roof's true temperature range and not the walls') lie above the walls' pixels (rows of the image grow downwards):
    the median roof row is above the median warm-wall row by more than 10 % of the model's height on screen;
(c) unshaded: the median distance of the model's pixels to the nearest palette colour is at most 5 RGB units (the
    GLB's material is ``KHR_materials_unlit``, so the viewer's lights do not alter the colours the legend explains).

A negative control (``--control``, on by default) renders the same GLB with its positions turned back to the survey's
Z-up axes (what a GLB without the Y-up conversion looks like in a Y-up viewer): the same check must report it as not
upright, so the check can fail.

Usage::

    python benchmarks/glb_model_viewer.py [--save docs/images/glb_model_viewer.png] [--npm-dir DIR] [--keep DIR]

Exit status 0 when (a), (b) and (c) hold (and the control fails (b)), 1 otherwise, 2 when Chromium, node or npm is missing.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
NPM_PACKAGES = ("@google/model-viewer@4", "playwright-core@1")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
UTM_OFFSET = (512_000.0, 5_213_000.0, 420.0)  # the scene moved to projected coordinates (m)
ORBIT = "35deg 55deg auto"  # model-viewer's camera orbit: azimuth from +Z (south), polar angle from +Y (up), radius

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>GLB in model-viewer</title><link rel="icon" href="data:,">
<script type="module" src="model-viewer.min.js"></script>
<style>html,body{margin:0;background:#00ff00}model-viewer{width:800px;height:600px;background-color:#00ff00}</style>
</head><body><model-viewer id="mv" src="__GLB__" camera-orbit="__ORBIT__" interaction-prompt="none"></model-viewer>
</body></html>
"""

SHOOT_JS = r"""
const { chromium } = require(process.argv[2] + '/node_modules/playwright-core');
(async () => {
  const [url, png, exe, flags] = [process.argv[3], process.argv[4], process.argv[5], JSON.parse(process.argv[6])];
  const browser = await chromium.launch({ executablePath: exe, args: flags, headless: true });
  const page = await browser.newPage({ viewport: { width: 800, height: 600 } });
  const logs = [];
  page.on('console', m => logs.push(m.type() + ': ' + m.text()));
  page.on('pageerror', e => logs.push('pageerror: ' + e.message));
  await page.goto(url);
  const state = await page.evaluate(() => new Promise((resolve) => {
    const mv = document.getElementById('mv');
    const done = (what) => requestAnimationFrame(() => requestAnimationFrame(() => resolve(what)));
    if (mv.loaded) done('loaded');
    mv.addEventListener('load', () => done('load'));
    mv.addEventListener('error', (e) => resolve('error: ' + JSON.stringify(e.detail && e.detail.type)));
    setTimeout(() => resolve('timeout'), 60000);
  }));
  await page.waitForTimeout(1500);
  await page.locator('#mv').screenshot({ path: png });
  console.log(JSON.stringify({ state, logs }));
  await browser.close();
})().catch(e => { console.error(e); process.exit(1); });
"""


def ensure_npm(folder: Path) -> Path:
    """The scratch npm folder with model-viewer and playwright-core (installed once with the machine's npm)."""
    mv = folder / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer.min.js"
    pw = folder / "node_modules" / "playwright-core"
    if not (mv.is_file() and pw.is_dir()):
        folder.mkdir(parents=True, exist_ok=True)
        if not (folder / "package.json").is_file():
            (folder / "package.json").write_text('{"name": "glb-check", "private": true}\n')
        subprocess.run(["npm", "install", "--no-audit", "--no-fund", *NPM_PACKAGES], cwd=folder, check=True,
                       capture_output=True, text=True)
    return mv


def textured_building(work: Path) -> Path:
    """``thermogrammetry texture`` on a synthetic building seen from above: the OUT folder."""
    from thermogrammetry.cli.main import main as cli
    from thermogrammetry.pipeline.project import FolderProject
    from thermogrammetry.synthetic.building import BuildingConfig, make_building, write_building_survey

    scene = make_building(BuildingConfig(ground_margin_m=2.0, camera_height_m=12.0, n_stations=12))
    survey = work / "survey"
    write_building_survey(FolderProject(survey), scene, sensor=False)
    # moved to UTM coordinates (EPSG:32632): the GLB must still sit at the viewer's origin (a translation of
    # kilometres on its node left model-viewer's frame blank)
    off = np.asarray(UTM_OFFSET)
    cams = json.loads((survey / "cameras.json").read_text())
    cams["crs"] = "EPSG:32632"
    for im in cams["images"]:
        R = np.asarray(im["cam_from_world"]["R"], float)
        im["cam_from_world"]["t"] = (np.asarray(im["cam_from_world"]["t"], float) - R @ off).tolist()
        im["center"] = (np.asarray(im["center"], float) + off).tolist()
    (survey / "cameras.json").write_text(json.dumps(cams, indent=1) + "\n")
    lines = (survey / "mesh.obj").read_text().splitlines()
    lines = [" ".join(["v"] + [f"{float(c) + o:.6f}" for c, o in zip(ln.split()[1:], off)]) if ln.startswith("v ") else ln
             for ln in lines]
    (survey / "mesh.obj").write_text("\n".join(lines) + "\n")
    out = work / "tex"
    rc = cli(["texture", str(survey), "--mesh", str(survey / "mesh.obj"), "-o", str(out), "--unit", "C",
              "--texel-size", "0.05", "--fit-poses", "off"])
    if rc != 0:
        raise SystemExit(f"thermogrammetry texture failed (exit {rc})")
    return out


def z_up_copy(glb: bytes) -> bytes:
    """The GLB with its Y-up positions turned back to the survey's Z-up axes ((X, Y, Z) -> (X, -Z, Y)): the
    orientation a GLB without the conversion has (negative control)."""
    n_json = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20:20 + n_json])
    binary = bytearray(glb[20 + n_json + 8:])
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            acc = doc["accessors"][prim["attributes"]["POSITION"]]
            view = doc["bufferViews"][acc["bufferView"]]
            off = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
            p = np.frombuffer(bytes(binary[off:off + 12 * acc["count"]]), "<f4").reshape(-1, 3)
            q = np.column_stack([p[:, 0], -p[:, 2], p[:, 1]]).astype("<f4")
            binary[off:off + q.nbytes] = q.tobytes()
            acc["min"], acc["max"] = q.min(axis=0).tolist(), q.max(axis=0).tolist()
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + glb[20 + n_json:20 + n_json + 8] + bytes(binary)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def serve(folder: Path):
    """An HTTP server of ``folder`` on 127.0.0.1 (a free port) in a thread: (server, base URL)."""
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(folder)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, f"http://127.0.0.1:{httpd.server_address[1]}"


def screenshot(npm: Path, url: str, png: Path, chromium: str) -> dict:
    js = png.parent / "shoot.cjs"
    js.write_text(SHOOT_JS)
    r = subprocess.run(["node", str(js), str(npm), url, str(png), chromium, json.dumps(CHROMIUM_FLAGS)],
                       capture_output=True, text=True, timeout=180)
    if r.returncode != 0 or not png.is_file():
        raise SystemExit(f"the screenshot failed (exit {r.returncode}): {r.stderr.strip()[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def analyse(png: Path, lo: float, hi: float, bands: dict, *, tol: float = 12.0) -> dict:
    """What the screenshot shows: pixels of the model (not the green background), those within ``tol`` (RGB units)
    of the inferno palette, their values through the palette over ``lo..hi``, and the image rows of the pixels in
    each of ``bands`` (name -> (vmin, vmax), values in the palette's unit)."""
    import matplotlib
    from PIL import Image
    from scipy.spatial import cKDTree

    img = np.asarray(Image.open(png).convert("RGB")).astype(float)
    green = (img[..., 0] < 40) & (img[..., 1] > 215) & (img[..., 2] < 40)
    model = ~green
    lut = matplotlib.colormaps["inferno"](np.linspace(0, 1, 256))[:, :3] * 255
    d, k = cKDTree(lut).query(img[model].reshape(-1, 3))
    on_palette = d <= tol
    value = np.full(img.shape[:2], np.nan)
    vals = np.where(on_palette, lo + k / 255.0 * (hi - lo), np.nan)
    value[model] = vals
    rows_model = np.nonzero(model)[0]
    out = {"model_fraction": float(model.mean()), "palette_fraction_of_model": float(on_palette.mean()) if len(d) else 0.0,
           "palette_spread": float(np.ptp(k[on_palette]) / 255.0) if on_palette.any() else 0.0,
           "median_palette_distance": float(np.median(d)) if len(d) else float("nan"),
           "model_rows": [int(rows_model.min()), int(rows_model.max())] if len(rows_model) else None, "bands": {}}
    for name, (a, b) in bands.items():
        r = np.nonzero((value >= a) & (value <= b))[0]
        out["bands"][name] = {"pixels": int(len(r)), "median_row": float(np.median(r)) if len(r) else None}
    return out


def verdict(a: dict) -> dict:
    blank_ok = a["model_fraction"] > 0.05 and a["palette_fraction_of_model"] > 0.5 and a["palette_spread"] > 0.5
    roof, wall = a["bands"]["roof"], a["bands"]["warm wall"]
    upright = False
    if a["model_rows"] and roof["pixels"] > 200 and wall["pixels"] > 200:
        height = a["model_rows"][1] - a["model_rows"][0] + 1
        upright = (wall["median_row"] - roof["median_row"]) > 0.10 * height
    unshaded = a["median_palette_distance"] <= 5.0  # unlit: the screen shows the palette's colours themselves
    return {"non_blank": bool(blank_ok), "upright": bool(upright), "colours_as_palette": bool(unshaded)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--save", default=None, help="copy the screenshot here (e.g. docs/images/glb_model_viewer.png)")
    ap.add_argument("--npm-dir", default=str(Path(tempfile.gettempdir()) / "thermogrammetry-model-viewer"),
                    help="scratch folder for the npm packages (outside the repository)")
    ap.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    ap.add_argument("--no-control", action="store_true", help="skip the Z-up negative control")
    ap.add_argument("--keep", default=None, help="keep the survey, the texture and the screenshots in this folder")
    args = ap.parse_args(argv)
    if not args.chromium or not shutil.which("node") or not shutil.which("npm"):
        print("needs Chromium (apt-get install chromium), node and npm", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO / "src"))
    from thermogrammetry.products.texture_export import palette_range
    from thermogrammetry.synthetic.building import GROUPS, BuildingConfig, make_building, surface_temperature

    import tifffile

    npm = Path(args.npm_dir)
    mv_js = ensure_npm(npm)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="glb_model_viewer_"))
    work.mkdir(parents=True, exist_ok=True)
    out = textured_building(work)
    pal = json.loads((out / "texture.json").read_text())["preview_palette"]  # what the GLB's colours mean
    lo, hi = float(pal["min"]), float(pal["max"])
    assert (pal["colormap"], pal["unit"]) == ("inferno", "°C"), pal
    assert np.allclose((lo, hi), palette_range(tifffile.imread(out / "temperature_texture.tif")))
    # the roof's and the walls' true temperatures (°C) over their faces: the bands the palette maps them to
    sc = make_building(BuildingConfig(ground_margin_m=2.0, camera_height_m=12.0, n_stations=12))
    cen = sc.vertices[sc.faces].mean(axis=1)
    tc = surface_temperature(sc, cen, sc.face_group) - 273.15
    roof = tc[sc.face_group == GROUPS.index("roof")]
    others = tc[sc.face_group != GROUPS.index("roof")]
    wall = tc[(sc.face_group == GROUPS.index("wall")) & (cen[:, 2] > 0.5 * sc.config.height_m)]
    bands = {"roof": (float(roof.min()), float(min(roof.max(), np.percentile(others, 1)))),
             "warm wall": (float(max(np.percentile(wall, 5), roof.max() + 0.5)), float(np.percentile(wall, 95)))}
    site = work / "site"
    site.mkdir(exist_ok=True)
    shutil.copy(mv_js, site / "model-viewer.min.js")
    shutil.copy(out / "textured.glb", site / "textured.glb")
    (site / "textured_zup.glb").write_bytes(z_up_copy((out / "textured.glb").read_bytes()))
    httpd, base = serve(site)
    glb_bytes = (out / "textured.glb").read_bytes()
    n_json = struct.unpack_from("<I", glb_bytes, 12)[0]
    doc = json.loads(glb_bytes[20:20 + n_json])
    report = {"palette_C": [lo, hi], "bands_C": bands, "orbit": ORBIT,
              "glb": {"asset_offset": doc["asset"]["extras"]["thermogrammetry"]["offset"],
                      "crs": doc["asset"]["extras"]["thermogrammetry"]["crs"],
                      "position_max_abs_m": float(np.max(np.abs(doc["accessors"][doc["meshes"][0]["primitives"][0]
                                                                            ["attributes"]["POSITION"]]["max"]
                                                                 + doc["accessors"][doc["meshes"][0]["primitives"][0]
                                                                   ["attributes"]["POSITION"]]["min"]))),
                      "node_transforms": [k for nd in doc["nodes"] for k in ("translation", "matrix", "rotation") if k in nd],
                      "extensionsUsed": doc.get("extensionsUsed", [])}}
    try:
        for name, glb in [("glb", "textured.glb")] + ([] if args.no_control else [("control_z_up", "textured_zup.glb")]):
            (site / f"{name}.html").write_text(PAGE.replace("__GLB__", glb).replace("__ORBIT__", ORBIT))
            png = work / f"{name}.png"
            state = screenshot(npm, f"{base}/{name}.html", png, args.chromium)
            a = analyse(png, lo, hi, bands)
            report.setdefault(name, {}).update({"viewer": state, "analysis": a, "verdict": verdict(a), "screenshot": str(png)})
    finally:
        httpd.shutdown()
    print(json.dumps(report, indent=1))
    ok = all(report["glb"]["verdict"].values())
    if not args.no_control:
        ok = ok and not report["control_z_up"]["verdict"]["upright"]
    if args.save:
        shutil.copy(work / "glb.png", args.save)
    print("OK" if ok else "FAILED", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
