"""Coverage-guided fuzzing (atheris/libFuzzer) of every thermal reader and every CSV/JSON parser.

Run one harness::

    pip install -e '.[fuzz]'            # atheris
    python fuzz/fuzz_targets.py TARGET -runs=1000000 [-max_len=65536] [corpus_dir]
    python fuzz/fuzz_targets.py --list  # the targets

A harness passes bytes to the parser exactly as the CLI would and accepts only the project's own exceptions
(:class:`thermogrammetry.errors.ThermogrammetryError`, which also derive from ``ValueError``/``OSError``);
any other exception, a hang or a crash is a finding.  The seed corpus is generated (``seeds(TARGET)``): small
valid files built in code, so mutations start near valid input.  The counts of the last runs are in the
issue-14 notes.
"""

from __future__ import annotations

import io
import json
import os
import struct
import sys
from pathlib import Path

import numpy as np

_THERMAL_READERS = {  # target -> reader name in the registry
    "tiff": "tiff", "flir_jpeg": "flir_rjpeg", "workswell_jpeg": "workswell_rjpeg", "fff": "flir_fff",
    "dji": "dji_rjpeg", "matrix": "matrix",
}
_SUFFIX = {"fff": ".seq", "matrix": ".csv", "dji": ".jpg", "flir_jpeg": ".jpg", "workswell_jpeg": ".jpg", "tiff": ".tif"}


def _fff(w=6, h=4) -> bytes:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_bad_inputs import counts_img, fff_frame

    return fff_frame(counts_img(h, w)) + fff_frame(counts_img(h, w, level=17000))


def _jpeg_with(app_segments: list[tuple[int, bytes]], w=6, h=4) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("L", (w, h), 128).save(buf, "JPEG")
    j = buf.getvalue()
    segs = b"".join(b"\xff" + bytes([m]) + struct.pack(">H", len(p) + 2) + p for m, p in app_segments)
    return j[:2] + segs + j[2:]


def seeds(target: str) -> list[bytes]:
    """Small valid inputs for ``target``."""
    from thermogrammetry.io.tiff import encode_counts_tiff, encode_temperature_tiff

    t = np.linspace(290, 300, 20, dtype=np.float32).reshape(4, 5)
    if target == "tiff":
        return [encode_temperature_tiff(t)[0], encode_temperature_tiff(t, encoding="uint16")[0],
                encode_counts_tiff((t * 50).astype(np.uint16))]
    if target == "fff":
        return [_fff()]
    if target == "flir_jpeg":
        f = _fff()[: len(_fff()) // 2]
        return [_jpeg_with([(0xE1, b"FLIR\x00\x01\x00\x00" + f)])]
    if target == "workswell_jpeg":
        f = _fff()[: len(_fff()) // 2]
        return [_jpeg_with([(0xE1, b"WORK\x00\x01\x00\x00" + f)])]
    if target == "dji":
        raw = (np.arange(24, dtype="<u2") + 19000).tobytes()
        params = b"\xff\xd2\xd1\xffiirp".ljust(0x20, b"\0") + struct.pack("<5f", 25.0, 5.0, 0.95, 0.5, 25.0)
        return [_jpeg_with([(0xE1, b"Exif\0\0"), (0xE3, raw), (0xE4, params), (0xE1, b"DJI")], 6, 4)]
    if target == "matrix":
        return [b"20.5,21,22\n23,24,25\n", b"a;b\n1;2\n3;4\n"]
    if target == "npy":
        b = io.BytesIO()
        np.save(b, t)
        return [b.getvalue()]
    if target == "exif":
        return [encode_temperature_tiff(t)[0]]
    if target == "references":
        return [b"image,x,y,temperature_c,sigma_k\na.jpg,1,2,20,0.5\na.jpg,3,3,30,0.5\n",
                b"image,polygon,temperature_k\na.jpg,1 1; 3 1; 3 3,300\n"]
    if target in ("testfield_control", "closerange_control"):
        return [b"id,X,Y,Z,sX,sY,sZ\n1,0,0,0,0.001,0.001,0.001\n2,1,0,0,0.001,0.001,0.001\n"]
    if target in ("testfield_measurements", "closerange_measurements"):
        return [b"image,id,x,y,sx,sy\nimg1,1,10.5,20.25,0.3,0.3\nimg1,2,30,40,0.3,0.3\n"]
    if target == "gnss":
        return [b"image,X,Y,Z,sX,sY,sZ\nimg1,584512.3,5697001.2,141.2,0.01,0.01,0.02\n"]
    if target == "closerange_planes":
        return [b"name,id1,id2,id3\nfront,1,2,3\n"]
    if target == "cameras_json":
        from thermogrammetry.camera import Camera
        from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

        cam = Camera("pinhole", (40, 30), {"fx": 40.0, "fy": 40.0, "cx": 19.5, "cy": 14.5})
        oc = OrientedCameras({"c": cam}, [OrientedImage("a", "c", np.eye(3), np.zeros(3))])
        return [json.dumps(oc.to_dict()).encode()]
    raise SystemExit(f"unknown target {target!r}; targets: {', '.join(TARGETS)}")


def _text(data: bytes) -> str:
    return data.decode("utf-8", "replace")


def make_target(target: str):
    """The one-input function of ``target`` (raises only ThermogrammetryError on bad input); it returns what it
    parsed (the images read, the table, the cameras), so that a test can tell a valid input accepted from one
    refused or read as nothing."""
    from thermogrammetry.io.thermal import ReadOptions, read_with, registered_readers

    if target in _THERMAL_READERS:
        spec = {r.name: r for r in registered_readers()}[_THERMAL_READERS[target]]
        opts = ReadOptions(unit="K", on_damaged=lambda i, m: None)
        path = Path("fuzz" + _SUFFIX.get(target, ".bin"))

        def run(data: bytes):
            images = list(read_with(spec, path, data, opts))
            for img in images:
                img.signal()
            return images
        return run
    if target == "npy":
        from thermogrammetry.io.matrix import read_matrix

        opts = ReadOptions(unit="K")
        return lambda data: list(read_matrix(Path("fuzz.npy"), b"\x93NUMPY" + data[6:] if len(data) > 6 else data, opts))
    if target == "exif":
        from thermogrammetry.io.exif import jpeg_segments, parse_xmp, read_exif

        def run(data: bytes):
            tags = read_exif(data)
            parse_xmp(data)
            if data[:2] == b"\xff\xd8":
                jpeg_segments(data, "fuzz.jpg")
            return tags
        return run
    if target == "references":
        import tempfile

        from thermogrammetry.radiometry.empirical import read_references_csv

        d = tempfile.mkdtemp(prefix="fuzzrefs")
        p = Path(d) / "refs.csv"

        def run(data: bytes):
            p.write_bytes(data)
            return read_references_csv(p)
        return run
    if target.startswith("testfield_") or target == "gnss":
        from thermogrammetry.io import testfield_csv as tc

        fn = {"testfield_control": tc.parse_control_csv, "testfield_measurements": tc.parse_measurements_csv,
              "gnss": tc.parse_gnss_csv}[target]
        return lambda data: fn(_text(data), "fuzz.csv")
    if target.startswith("closerange_"):
        from thermogrammetry.closerange import tables

        fn = {"closerange_control": tables.parse_control, "closerange_measurements": tables.parse_measurements,
              "closerange_planes": tables.parse_planes}[target]
        return lambda data: fn(_text(data), "fuzz.csv")
    if target == "cameras_json":
        from thermogrammetry.io.oriented import OrientedCameras

        def run(data: bytes):
            try:
                d = json.loads(_text(data))
            except (json.JSONDecodeError, RecursionError):
                return None  # the loader reports invalid JSON itself (OrientedCameras.load)
            return OrientedCameras.from_dict(d, source="fuzz.json")
        return run
    raise SystemExit(f"unknown target {target!r}; targets: {', '.join(TARGETS)}")


TARGETS = (*_THERMAL_READERS, "npy", "exif", "references", "testfield_control", "testfield_measurements", "gnss",
           "closerange_control", "closerange_measurements", "closerange_planes", "cameras_json")


def one_input_factory(target: str):
    from thermogrammetry.errors import ThermogrammetryError

    fn = make_target(target)

    def test_one_input(data: bytes) -> None:
        try:
            fn(bytes(data))
        except ThermogrammetryError:
            pass  # a clear refusal: what we want for bad input
    return test_one_input


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help", "--list"):
        print(__doc__)
        print("targets:", ", ".join(TARGETS))
        return
    target = sys.argv.pop(1)
    os.environ.setdefault("THERMOGRAMMETRY_MAX_PIXELS", str(1 << 22))  # keep each input cheap
    import logging

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)  # it logs every odd tag it skips
    import atheris

    import thermogrammetry.closerange.tables  # noqa: F401
    import thermogrammetry.io  # noqa: F401
    import thermogrammetry.io.testfield_csv  # noqa: F401
    import thermogrammetry.radiometry.empirical  # noqa: F401
    from thermogrammetry.io.thermal import registered_readers

    registered_readers()  # import every reader module before instrumenting
    atheris.instrument_all()  # coverage feedback from every loaded Python function (ours and the decoders')
    corpus = [a for a in sys.argv[1:] if not a.startswith("-")]
    if not corpus:  # write the generated seeds into a fresh corpus folder
        import tempfile

        d = Path(tempfile.mkdtemp(prefix=f"fuzz-{target}-"))
        for i, s in enumerate(seeds(target)):
            (d / f"seed{i}").write_bytes(s)
        sys.argv.append(str(d))
    atheris.Setup(sys.argv, one_input_factory(target))
    atheris.Fuzz()


if __name__ == "__main__":
    main()
