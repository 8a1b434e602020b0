"""Regression corpus of bad inputs (issue 14): every case is built here from a few bytes, run through the CLI
as a user would, and must end in exit 2 with a one-paragraph message naming the file/value -- never a
traceback, never exit 0, never a partial output set, never a hang (:data:`HANG_S`), and every file the case
made (the user's inputs, a folder given as OUT) still there byte for byte.

``CASES`` is the corpus; ``python -m pytest tests/test_bad_inputs.py -q`` runs it (CI too).  Each case
returns ``(argv, expected_substrings, out_dir_that_must_not_exist_or_None)``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from thermogrammetry.cli.main import main

# ------------------------------------------------------------------------------------------------ builders

PLANCK = dict(r1=21106.77, b=1501.0, f=1.0, o=-7340, r2=0.012545258)


def fff_frame(counts: np.ndarray, *, planck=PLANCK, emissivity=0.95) -> bytes:
    """A minimal little-endian FLIR FFF frame: header, 2-entry directory, RawData (plain uint16), CameraInfo."""
    h, w = counts.shape
    raw = struct.pack("<HHH", 2, w, h).ljust(0x20, b"\0") + counts.astype("<u2").tobytes()
    ci = bytearray(0x390)
    ci[0:2] = struct.pack("<H", 2)
    for off, v in ((0x20, emissivity), (0x24, 1.0), (0x28, 293.15), (0x2C, 293.15), (0x30, 293.15), (0x34, 1.0),
                   (0x3C, 0.5), (0x58, planck["r1"]), (0x5C, planck["b"]), (0x60, planck["f"]),
                   (0x70, 0.006569), (0x74, 0.01262), (0x78, -0.002276), (0x7C, -0.00667), (0x80, 1.9),
                   (0x30C, planck["r2"])):
        ci[off:off + 4] = struct.pack("<f", v)
    ci[0x308:0x30C] = struct.pack("<i", planck["o"])
    dir_off = 0x40
    raw_off = dir_off + 2 * 0x20
    ci_off = raw_off + len(raw)
    head = bytearray(b"FFF\0".ljust(0x40, b"\0"))
    head[0x14:0x20] = struct.pack("<III", 100, dir_off, 2)
    ent = lambda t, off, n: struct.pack("<HHII", t, 0, 0, 0) + struct.pack("<II", off, n).ljust(0x14, b"\0")  # noqa: E731
    return bytes(head) + ent(1, raw_off, len(raw)) + ent(0x20, ci_off, len(ci)) + raw + bytes(ci)


def counts_img(h=6, w=8, level=16000):
    return (level + np.arange(h * w).reshape(h, w) * 5).astype(np.uint16)


def tiff_bytes(arr: np.ndarray, extratags=()) -> bytes:
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, arr, extratags=list(extratags))
    return buf.getvalue()


def huge_tiff(w=80, h=4_000_000) -> bytes:
    """A ~200-byte TIFF declaring w x h uint16 pixels in one strip."""
    entries = [(256, 4, 1, w), (257, 4, 1, h), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, w * h * 2)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHI", t, typ, n) + (struct.pack("<H", v) + b"\0\0" if typ == 3 else struct.pack("<I", v))
        for t, typ, n, v in entries) + b"\0\0\0\0"
    return b"II*\0" + struct.pack("<I", 8 + 16) + b"\0" * 16 + ifd


def png_header(w, h) -> bytes:
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 10)) + chunk(b"IEND", b""))


def write(p: Path, data) -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return p


def matrix_csv(tmp: Path) -> Path:
    return write(tmp / "in" / "m.csv", "20.5,21,22\n23,24,25\n")


def unwritable(tmp: Path) -> Path:
    """An output location no one (not even root) can create: under /proc."""
    return Path("/proc/self/thermogrammetry-out")


# correct: a 40x30 pinhole camera at the origin looking along +Z at the plane Z = 5
def correct_inputs(tmp: Path) -> dict[str, Path]:
    from thermogrammetry.camera import Camera
    from thermogrammetry.io.tiff import write_temperature_tiff

    cam = Camera("pinhole", (40, 30), {"fx": 40.0, "fy": 40.0, "cx": 19.5, "cy": 14.5})
    cam.save(tmp / "camera.json")
    write_temperature_tiff(tmp / "thermal.tif", np.full((30, 40), 300.0, np.float32))
    write(tmp / "pose.json", json.dumps({"R": np.eye(3).tolist(), "t": [0, 0, 0]}))
    return {"camera": tmp / "camera.json", "thermal": tmp / "thermal.tif", "pose": tmp / "pose.json"}


def correct_argv(tmp: Path, *extra, pose=None, planes=("0,0,1,-5",)) -> list[str]:
    f = correct_inputs(tmp)
    argv = ["correct", "--thermal-image", str(f["thermal"]), "--camera", str(f["camera"]),
            "--pose", str(pose or f["pose"]), "-o", str(tmp / "OUT")]
    for p in planes:
        argv += ["--plane", p]
    return argv + list(extra)


# closerange: the synthetic replica's tables
def closerange_argv(tmp: Path, *, control=None, measurements=None, planes=None) -> list[str]:
    from thermogrammetry.synthetic.closerange import make_closerange_scene, measure, measurements_csv

    s = make_closerange_scene()
    rows = measure(s, 0.5, np.random.default_rng(5))
    c = write(tmp / "control.csv", control if control is not None else s.control_csv())
    m = write(tmp / "measurements.csv", measurements if measurements is not None else measurements_csv(rows))
    p = write(tmp / "planes.csv", planes if planes is not None else s.planes_csv())
    return ["closerange", "--control", str(c), "--measurements", str(m), "--thermal", "thermal", "--planes", str(p),
            "-o", str(tmp / "OUT")]


# ------------------------------------------------------------------------------------------------ corpus

def _c(name):
    def deco(fn):
        CASES[name] = fn
        return fn
    return deco


CASES: dict = {}


@_c("convert -j 0")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "-o", str(t / "OUT"), "-j", "0"], ["'--jobs'", "greater than or equal to 1"], t / "OUT"


@_c("convert -o is a file")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "-o", str(write(t / "afile", "x"))], ["is an existing file"], None


@_c("convert -o cannot be created")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "-o", str(unwritable(t))], ["thermogrammetry-out"], None


@_c("convert --distance nan")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "-o", str(t / "OUT"), "--distance", "nan"], \
        ["--distance nan", "finite"], t / "OUT"


@_c("convert --emissivity 0")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "-o", str(t / "OUT"), "--emissivity", "0"], \
        ["--emissivity 0", "(0, 1]"], t / "OUT"


@_c("convert --scale without unit")
def _(t):
    return ["convert", str(matrix_csv(t)), "-o", str(t / "OUT"), "--scale", "0.01"], ["--input-unit"], t / "OUT"


@_c("convert --range reversed")
def _(t):
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "--encoding", "uint16", "-o", str(t / "OUT"),
            "--range", "40", "10"], ["MIN < MAX"], t / "OUT"


@_c("TIFF declaring 80x4,000,000 pixels")
def _(t):
    return ["convert", str(write(t / "huge.tif", huge_tiff())), "-o", str(t / "OUT")], \
        ["huge.tif", "80x4000000", "size cap"], t / "OUT"


@_c("TIFF with garbage GDAL_NODATA")
def _(t):
    data = tiff_bytes(np.full((4, 5), 300.0, np.float32),
                      [(42112, "s", 0, '<GDALMetadata><Item name="UNITTYPE" sample="0" role="unittype">K</Item></GDALMetadata>', True),
                       (42113, "s", 0, "abc", True)])
    return ["convert", str(write(t / "nodata.tif", data)), "-o", str(t / "OUT")], \
        ["nodata.tif", "GDAL_NODATA", "'abc' is not a number"], t / "OUT"


@_c("TIFF with garbage GDAL SCALE")
def _(t):
    xml = ('<GDALMetadata><Item name="SCALE" sample="0" role="scale">zz</Item>'
           '<Item name="OFFSET" sample="0" role="offset">0</Item>'
           '<Item name="UNITTYPE" sample="0" role="unittype">K</Item></GDALMetadata>')
    data = tiff_bytes(np.full((4, 5), 30000, np.uint16), [(42112, "s", 0, xml, True)])
    return ["convert", str(write(t / "scale.tif", data)), "-o", str(t / "OUT")], ["scale.tif", "SCALE", "'zz'"], t / "OUT"


@_c("TIFF with a NaN GDAL SCALE")
def _(t):
    xml = ('<GDALMetadata><Item name="SCALE" sample="0" role="scale">nan</Item>'
           '<Item name="UNITTYPE" sample="0" role="unittype">K</Item></GDALMetadata>')
    data = tiff_bytes(np.full((4, 5), 30000, np.uint16), [(42112, "s", 0, xml, True)])
    return ["convert", str(write(t / "nanscale.tif", data)), "-o", str(t / "OUT")], ["nanscale.tif", "not a finite number"], t / "OUT"


@_c("FFF with a corrupted CameraInfo (all pixels NaN)")
def _(t):
    bad = dict(PLANCK, f=-30000.0)  # a damaged PlanckF: no pixel gets a valid temperature
    return ["convert", str(write(t / "bad.fff", fff_frame(counts_img(), planck=bad))), "-o", str(t / "OUT")], \
        ["bad.fff", "invalid"], t / "OUT"


@_c("CSV matrix with infinity")
def _(t):
    return ["convert", str(write(t / "inf.csv", "20,21\n22,inf\n")), "--input-unit", "C", "-o", str(t / "OUT")], \
        ["inf.csv", "line 2", "infinite"], t / "OUT"


@_c("CSV matrix not UTF-8")
def _(t):
    return ["convert", str(write(t / "latin.csv", "20,21\n22,2\xb03\n".encode("latin-1"))), "--input-unit", "C",
            "-o", str(t / "OUT")], ["latin.csv", "line 2", "non-numeric"], t / "OUT"


@_c("NPY declaring 100000x100000")
def _(t):
    hdr = b"{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }"
    hdr = hdr + b" " * (63 - len(hdr) % 64) + b"\n"
    data = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(hdr)) + hdr + b"\0" * 64
    return ["convert", str(write(t / "big.npy", data)), "--input-unit", "K", "-o", str(t / "OUT")], \
        ["big.npy", "size cap"], t / "OUT"


@_c("truncated FFF")
def _(t):
    return ["convert", str(write(t / "cut.fff", fff_frame(counts_img())[:300])), "-o", str(t / "OUT")], ["cut.fff"], t / "OUT"


@_c("empty file")
def _(t):
    return ["convert", str(write(t / "empty.jpg", b"")), "-o", str(t / "OUT")], ["empty.jpg", "empty file"], t / "OUT"


@_c("DJI-like JPEG cut in its header")
def _(t):
    return ["convert", str(write(t / "dji.jpg", b"\xff\xd8\xff\xe1\x00\x40DJI" + b"\0" * 10)), "-o", str(t / "OUT")], \
        ["dji.jpg"], t / "OUT"


@_c("references file not UTF-8")
def _(t):
    refs = write(t / "refs.csv", "image,x,y,temperature_c\nm.csv,0,0,2\xb0\n".encode("latin-1"))
    return ["convert", str(matrix_csv(t)), "--input-unit", "C", "--references", str(refs), "-o", str(t / "OUT")], \
        ["refs.csv", "not UTF-8"], t / "OUT"


@_c("references with one row")
def _(t):
    fff = write(t / "a.fff", fff_frame(counts_img()))
    refs = write(t / "refs.csv", "image,x,y,temperature_c\na.fff,1,1,20\n")
    return ["convert", str(fff), "--references", str(refs), "-o", str(t / "OUT")], ["refs.csv", ">= 2"], t / "OUT"


@_c("references naming a missing image")
def _(t):
    fff = write(t / "a.fff", fff_frame(counts_img()))
    refs = write(t / "refs.csv", "image,x,y,temperature_c\nb.fff,1,1,20\nb.fff,2,2,30\n")
    return ["convert", str(fff), "--references", str(refs), "-o", str(t / "OUT")], ["refs.csv", "line 2", "'b.fff'"], t / "OUT"


@_c("references with text temperature")
def _(t):
    fff = write(t / "a.fff", fff_frame(counts_img()))
    refs = write(t / "refs.csv", "image,x,y,temperature_c\na.fff,1,1,warm\na.fff,2,2,30\n")
    return ["convert", str(fff), "--references", str(refs), "-o", str(t / "OUT")], ["refs.csv", "line 2", "'warm'"], t / "OUT"


@_c("correct: pose file not JSON")
def _(t):
    return correct_argv(t, pose=write(t / "p.json", "{R: [1, 0")), ["p.json", "not valid JSON", "line 1"], t / "OUT"


@_c("correct: pose file is a list")
def _(t):
    return correct_argv(t, pose=write(t / "p.json", "[1, 2, 3]")), ["p.json", "JSON object"], t / "OUT"


@_c("correct: 2x2 rotation")
def _(t):
    return correct_argv(t, pose=write(t / "p.json", json.dumps({"R": [[1, 0], [0, 1]], "t": [0, 0, 0]}))), \
        ["p.json", "R", "expected 9 numbers"], t / "OUT"


@_c("correct: NaN pose")
def _(t):
    return correct_argv(t, pose=write(t / "p.json", '{"R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0, NaN, 0]}')), \
        ["p.json", "finite"], t / "OUT"


@_c("correct: non-rotation R")
def _(t):
    return correct_argv(t, pose=write(t / "p.json", json.dumps({"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0]}))), \
        ["p.json", "not a rotation"], t / "OUT"


@_c("correct: NaN plane")
def _(t):
    return correct_argv(t, planes=("0,0,nan,-5",)), ["--plane", "finite"], t / "OUT"


@_c("correct: zero plane normal")
def _(t):
    return correct_argv(t, planes=("0,0,0,-5",)), ["--plane", "normal is zero"], t / "OUT"


@_c("correct: inf plane")
def _(t):
    return correct_argv(t, planes=("0,0,1,inf",)), ["--plane", "finite"], t / "OUT"


@_c("correct: plane behind the camera (nothing corrected)")
def _(t):
    return correct_argv(t, planes=("0,0,1,5",)), ["no pixel", "thermal.tif"], t / "OUT"


@_c("correct: planes.csv with text in a numeric column")
def _(t):
    p = write(t / "planes.csv", "name,normal_x,normal_y,normal_z,d_m\nwall,0,0,one,-5\n")
    return correct_argv(t, "--planes", str(p), planes=()), ["planes.csv", "line 2", "must be numbers"], t / "OUT"


@_c("correct: planes.csv missing columns")
def _(t):
    p = write(t / "planes.csv", "name,a,b\nwall,0,0\n")
    return correct_argv(t, "--planes", str(p), planes=()), ["planes.csv", "expected columns"], t / "OUT"


@_c("correct: planes.csv not UTF-8")
def _(t):
    p = write(t / "planes.csv", "name,normal_x,normal_y,normal_z,d_m\nw\xe4ll,0,0,1,-5\n".encode("latin-1"))
    return correct_argv(t, "--planes", str(p), planes=()), ["planes.csv", "not UTF-8"], t / "OUT"


@_c("correct: missing DSM")
def _(t):
    return correct_argv(t, "--dsm", str(t / "nope.tif"), planes=()), ["nope.tif", "no such file"], t / "OUT"


@_c("correct: truncated DSM")
def _(t):
    d = write(t / "dsm.tif", tiff_bytes(np.zeros((20, 20), np.float32))[:60])
    return correct_argv(t, "--dsm", str(d), planes=()), ["dsm.tif", "cannot be read"], t / "OUT"


@_c("correct: cameras.json of another kind")
def _(t):
    c = write(t / "cameras.json", json.dumps({"cameras": {"thermal": {"fx": 1}}}))
    f = correct_inputs(t)
    return ["correct", "--thermal-image", str(f["thermal"]), "--cameras", str(c), "--thermal", "thermal",
            "--plane", "0,0,1,-5", "-o", str(t / "OUT")], ["cameras.json", "not an oriented-cameras file"], t / "OUT"


@_c("correct: closerange cameras.json with NaN DLT")
def _(t):
    c = write(t / "cameras.json", json.dumps({"format": "thermogrammetry.closerange.cameras/1",
                                              "cameras": {"thermal": {"dlt_L_world": [float("nan")] * 11}}}).replace("NaN", "NaN"))
    f = correct_inputs(t)
    return ["correct", "--thermal-image", str(f["thermal"]), "--cameras", str(c), "--thermal", "thermal",
            "--plane", "0,0,1,-5", "-o", str(t / "OUT")], ["cameras.json", "dlt_L_world", "finite"], t / "OUT"


@_c("correct: oriented cameras.json without the image")
def _(t):
    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    cam = Camera("pinhole", (40, 30), {"fx": 40.0, "fy": 40.0, "cx": 19.5, "cy": 14.5})
    OrientedCameras({"c": cam}, [OrientedImage("other", "c", np.eye(3), np.zeros(3))]).save(t / "cameras.json")
    f = correct_inputs(t)
    return ["correct", "--thermal-image", str(f["thermal"]), "--cameras", str(t / "cameras.json"), "--thermal", "thermal",
            "--plane", "0,0,1,-5", "-o", str(t / "OUT")], ["cameras.json", "no image 'thermal'"], t / "OUT"


@_c("correct: -o is a file")
def _(t):
    argv = correct_argv(t)
    write(t / "OUT", "x")
    return argv, ["OUT", "is an existing file"], None


@_c("closerange: control.csv not UTF-8")
def _(t):
    return closerange_argv(t, control="id,X,Y,Z\n1,0,0,0\n2,1,0,0\n3,0,1,0\n4,\xb01,1,0\n".encode("latin-1")), \
        ["control.csv", "not UTF-8", "line 5"], t / "OUT"


@_c("closerange: text in a coordinate")
def _(t):
    return closerange_argv(t, control="id,X,Y,Z\n1,0,0,0\n2,one,0,0\n"), ["control.csv"], t / "OUT"


@_c("closerange: unknown thermal image")
def _(t):
    argv = closerange_argv(t)
    argv[argv.index("--thermal") + 1] = "nosuch"
    return argv, ["--thermal 'nosuch'", "measurements.csv"], t / "OUT"


@_c("calibrate: PNG declaring 60000x60000")
def _(t):
    write(t / "imgs" / "a.png", png_header(60000, 60000))
    return ["calibrate", str(t / "imgs"), "-o", str(t / "OUT"), "--target", "chessboard", "--corners", "6x5",
            "--spacing-mm", "100"], ["a.png", "size cap"], t / "OUT"


@_c("calibrate: unknown --model")
def _(t):
    write(t / "imgs" / "a.png", png_header(64, 48))
    return ["calibrate", str(t / "imgs"), "-o", str(t / "OUT"), "--target", "chessboard", "--corners", "6x5",
            "--spacing-mm", "100", "--model", "fisheye"], ["--model 'fisheye'", "photogrammetric, opencv"], t / "OUT"


@_c("demo: OUT is a file")
def _(t):
    return ["demo", str(write(t / "afile", "x")), "--sections", "closerange"], ["afile", "is an existing file"], None


@_c("demo: OUT cannot be created")
def _(t):
    return ["demo", str(unwritable(t)), "--sections", "closerange"], ["thermogrammetry-out"], None


@_c("survey: a folder holding side files, its frames in a subfolder")
def _(t):
    write(t / "flight" / "gcps.csv", "id,X,Y,Z\n1,2600000.1,1200000.2,500.0\n")
    write(t / "flight" / "frames" / "f0.csv", "\n".join(",".join(["300.5"] * 16) for _ in range(12)))
    return ["survey", str(t / "flight"), "-o", str(t / "OUT")], \
        ["no input images", "gcps.csv", "subfolder(s) not entered: frames"], t / "OUT"


def test_folder_scan_takes_matrices_and_skips_side_files(tmp_path):
    from thermogrammetry.pipeline.survey import expand_inputs

    write(tmp_path / "a_matrix.csv", "\n".join(",".join(["300.5"] * 16) for _ in range(12)))
    write(tmp_path / "b_matrix_with_header.csv", "T (K) of frame 7\n" + "\n".join(";".join(["300.5"] * 8) for _ in range(4)))
    write(tmp_path / "gcps.csv", "id,X,Y,Z\n1,2600000.1,1200000.2,500.0\n")  # numbers, but 4 of them: a side file
    write(tmp_path / "gnss.csv", "image,X,Y,Z\nT0001,1.0,2.0,3.0\n")
    files, notes = expand_inputs([str(tmp_path)])
    assert [f.name for f in files] == ["a_matrix.csv", "b_matrix_with_header.csv"]
    assert len(notes) == 1 and "2 CSV file(s) that are not temperature matrices" in notes[0]
    assert "gcps.csv" in notes[0] and "gnss.csv" in notes[0]
    # named on the command line, a file is always tried (and a bad one is reported as failed with its reason)
    assert [f.name for f in expand_inputs([str(tmp_path / "gcps.csv")])[0]] == ["gcps.csv"]


@_c("references contradicting each other (warmer = fewer counts)")
def _(t):
    fff = write(t / "a.fff", fff_frame(counts_img()))  # counts rise along rows
    refs = write(t / "refs.csv", "image,x,y,temperature_c\na.fff,0,0,40\na.fff,7,5,20\n")
    return ["convert", str(fff), "--references", str(refs), "-o", str(t / "OUT")], \
        ["refs.csv", "falling with raw counts", "line 2"], t / "OUT"


@_c("correct: oriented cameras.json with a ragged rotation (found by fuzzing)")
def _(t):
    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    cam = Camera("pinhole", (40, 30), {"fx": 40.0, "fy": 40.0, "cx": 19.5, "cy": 14.5})
    d = OrientedCameras({"c": cam}, [OrientedImage("thermal", "c", np.eye(3), np.zeros(3))]).to_dict()
    d["images"][0]["cam_from_world"]["R"] = [[1, 0, 0], [0, [1], 0], [0, 0, 1]]
    d["images"][0].pop("center")
    c = write(t / "cameras.json", json.dumps(d))
    f = correct_inputs(t)
    return ["correct", "--thermal-image", str(f["thermal"]), "--cameras", str(c), "--thermal", "thermal",
            "--plane", "0,0,1,-5", "-o", str(t / "OUT")], ["cameras.json", "cam_from_world.R", "expected a list of 9 numbers"], t / "OUT"


# the verbs that read a survey folder and rasters (dense, ortho, evaluate), and survey, texture, facade, plan and the
# output folders of all of them: cases built in their own modules
from bad_inputs_products import CASES as _PRODUCT_CASES  # noqa: E402
from bad_inputs_verbs import CASES as _VERB_CASES  # noqa: E402

CASES.update(_PRODUCT_CASES)
CASES.update(_VERB_CASES)

#: a case running longer than this (s) is a hang (each takes well under a second)
HANG_S = 60


class CaseHung(Exception):
    """A case ran past :data:`HANG_S`."""


@contextlib.contextmanager
def deadline(seconds: int = HANG_S):
    """Raise :class:`CaseHung` in the main thread when the block runs longer than ``seconds``."""
    def on_alarm(signum, frame):
        raise CaseHung(f"still running after {seconds} s")
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def file_digests(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``folder`` (symlinks not followed)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


def files_lost(folder: Path, before: dict[str, str]) -> list[str]:
    """The files of ``before`` that are no longer under ``folder`` with the same bytes."""
    now = file_digests(folder)
    return [f for f, h in before.items() if now.get(f) != h]


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_refused_with_a_message(name, tmp_path, capsys):
    argv, expected, must_not_exist = CASES[name](tmp_path)
    before = file_digests(tmp_path)
    with deadline():
        code = main(argv)  # an escaping exception (a traceback, a hang) fails the test here
    cap = capsys.readouterr()
    text = " ".join((cap.out + cap.err).replace("│", " ").split())  # rich boxes wrap long lines
    assert code == 2, f"{name}: exit {code}\n{text}"
    assert "Traceback" not in text
    for s in expected:
        assert s in text, f"{name}: {s!r} not in {text!r}"
    if must_not_exist is not None:  # nothing half-written
        assert not Path(must_not_exist).exists(), f"{name}: {must_not_exist} was created"
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name], "staging folder left behind"
    assert files_lost(tmp_path, before) == [], f"{name}: a file the user gave was changed or removed"
