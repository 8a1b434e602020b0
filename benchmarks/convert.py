"""Benchmark: ``convert`` time per 640x512 R-JPEG vs flyr's own decode, in one run.

    /work/venv/bin/python benchmarks/convert.py [--repeat 5] [--flyr-xt2]

Rows: our reader alone (``read_thermal``: FFF parse + full measurement equation), our full convert of one
file (read + float32 / uint16 TIFF with EXIF/GPS, atomic write), and flyr 5.x ``unpack(...).kelvin`` on the
same files.  flyr cannot read the 640x512 DJI XT2/XTR FLIR cores, so it is timed on the closest file it
reads (FLIR T640, 640x480) and the time is also given per megapixel; ``--flyr-xt2`` additionally times
flyr's failure on DJI_XT2.jpg (~30 s of byte-wise scanning before a KeyError).  Median of ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rjpeg_samples" / "images"


def _time(fn, repeat: int) -> tuple[float, object]:
    out = None
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--flyr-xt2", action="store_true", help="also time flyr failing on DJI_XT2.jpg (slow)")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"shared data absent: {DATA}")
        return 0
    from thermogrammetry.io import read_thermal
    from thermogrammetry.io.convert import ConvertOptions, convert_files

    rows = []
    files = {"DJI_XT2.jpg": "640x512", "DJI_XTR.jpg": "640x512", "FLIR_T640.jpg": "640x480"}
    with tempfile.TemporaryDirectory() as tmp:
        for name, size in files.items():
            p = DATA / name
            mp = eval(size.replace("x", "*")) / 1e6
            t, img = _time(lambda: read_thermal(p), args.repeat)
            rows.append(("thermogrammetry read_thermal", name, size, t, t / mp, "ok"))
            for enc in ("float32", "uint16"):
                opts = ConvertOptions(unit="C", encoding=enc)
                t, rep = _time(lambda: convert_files([p], Path(tmp) / enc, opts), args.repeat)
                rows.append((f"thermogrammetry convert ({enc})", name, size, t, t / mp, "ok" if rep.results[0].ok else "FAILED"))
        # batch: 16 copies of the XT2 file, one thread vs two (per-file time)
        batch = [Path(tmp) / f"xt2_{i:02d}.jpg" for i in range(16)]
        for b in batch:
            b.write_bytes((DATA / "DJI_XT2.jpg").read_bytes())
        for jobs in (1, 2):
            opts = ConvertOptions(unit="C", encoding="float32")
            t, rep = _time(lambda: convert_files(batch, Path(tmp) / f"batch{jobs}", opts, jobs=jobs), max(1, args.repeat // 2))
            rows.append((f"thermogrammetry convert, 16 files, -j {jobs}", "DJI_XT2.jpg", "640x512", t / 16,
                         t / 16 / (640 * 512 / 1e6), "ok" if not rep.failures else "FAILED"))
        try:
            import flyr
        except ImportError:
            flyr = None
        if flyr is not None:
            p = DATA / "FLIR_T640.jpg"
            t, _ = _time(lambda: flyr.unpack(str(p)).kelvin, args.repeat)
            rows.append(("flyr unpack().kelvin", "FLIR_T640.jpg", "640x480", t, t / (640 * 480 / 1e6), "ok"))
            if args.flyr_xt2:
                t0 = time.perf_counter()
                try:
                    flyr.unpack(str(DATA / "DJI_XT2.jpg")).kelvin
                    status = "ok"
                except Exception as exc:  # noqa: BLE001 - we report what flyr does
                    status = f"fails: {type(exc).__name__} {exc}"
                rows.append(("flyr unpack().kelvin", "DJI_XT2.jpg", "640x512", time.perf_counter() - t0, float("nan"), status))
            else:
                rows.append(("flyr unpack().kelvin", "DJI_XT2.jpg", "640x512", float("nan"), float("nan"), "not run (--flyr-xt2): flyr fails on it"))
    print(f"python {sys.version.split()[0]}, median of {args.repeat} run(s)")
    print(f"{'tool':38s} {'file':15s} {'size':8s} {'s/file':>9s} {'s/MP':>8s}  status")
    for tool, name, size, t, tmp_, status in rows:
        print(f"{tool:38s} {name:15s} {size:8s} {t:9.4f} {tmp_:8.4f}  {status}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
