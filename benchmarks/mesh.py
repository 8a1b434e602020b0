"""Time and peak memory of ``thermogrammetry mesh`` per million points, at 1, 5 and 20 million points.

The cloud: the synthetic building (``make_building(BuildingConfig(ground_margin_m=1.0))``) scanned with 5 mm noise and a
1 m² hole (:func:`thermogrammetry.synthetic.scan.building_scan`), at the density that gives N points, written as a
binary PLY of doubles. Each run is ``thermogrammetry mesh CLOUD -o OUT --workers 0`` in a process of its own: wall
time, and peak resident memory from ``getrusage(RUSAGE_CHILDREN)`` (the largest child so far: run the sizes in
increasing order, or one size per call). The mesh's accuracy against the true surface is printed too.

    python benchmarks/mesh.py --points 1e6 5e6          # a few minutes
    python benchmarks/mesh.py --points 20e6              # alone: ~20 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _write_ply(path, P):
    n = len(P)
    hdr = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty double x\nproperty double y\n"
           "property double z\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(hdr.encode("ascii"))
        for s in range(0, n, 2_000_000):
            fh.write(np.ascontiguousarray(P[s:s + 2_000_000], "<f8").tobytes())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, nargs="+", default=[1e6, 5e6])
    ap.add_argument("--keep", type=Path, default=None, help="folder to keep the clouds and meshes in")
    a = ap.parse_args(argv)
    from thermogrammetry.products.mesh_decimate import point_mesh_distance
    from thermogrammetry.synthetic.building import BuildingConfig, make_building
    from thermogrammetry.synthetic.scan import building_scan

    scene = make_building(BuildingConfig(ground_margin_m=1.0))
    probe, _ = building_scan(scene, density=10.0, noise_m=0.005, seed=1)
    area = len(probe.points) / 10.0
    rows = []
    for n in sorted(a.points):
        work = Path(tempfile.mkdtemp(prefix="mesh-bench-", dir=a.keep))
        cloud, _ = building_scan(scene, density=n / area, noise_m=0.005, seed=1)
        _write_ply(work / "cloud.ply", cloud.points)
        npts = len(cloud.points)
        del cloud
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "thermogrammetry", "mesh", str(work / "cloud.ply"), "-o",
                            str(work / "out"), "--workers", "0"], capture_output=True, text=True)
        dt = time.perf_counter() - t0
        peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2 ** 20
        if r.returncode != 0:
            print(r.stderr[-2000:], file=sys.stderr)
            return 1
        d = json.loads((work / "out" / "mesh.json").read_text())
        from plyfile import PlyData

        ply = PlyData.read(str(work / "out" / "mesh.ply"))
        V = np.stack([np.asarray(ply["vertex"][k], float) for k in "xyz"], axis=1)
        pick = np.random.default_rng(0).choice(len(V), min(len(V), 100_000), replace=False)
        import trimesh

        tv, tf = trimesh.remesh.subdivide_to_size(scene.vertices, scene.faces, 0.1)
        dist = point_mesh_distance(V[pick], tv, tf)
        rows.append({"points": npts, "seconds": round(dt, 1), "s_per_Mpoint": round(dt / (npts / 1e6), 2),
                     "peak_GiB": round(peak_gib, 2), "GiB_per_Mpoint": round(peak_gib / (npts / 1e6), 3),
                     "faces": d["faces"], "cell_m": d["cell_m"], "blocks": d["blocks"]["count"],
                     "rms_mm": round(1000 * float(np.sqrt(np.mean(dist ** 2))), 2),
                     "within_2cm": round(float(np.mean(dist < 0.02)), 4)})
        print(json.dumps(rows[-1]), flush=True)
    print("| points | s | s / M points | peak GiB | GiB / M points | faces | cell m | RMS mm | within 2 cm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r_ in rows:
        print(f"| {r_['points']:,} | {r_['seconds']} | {r_['s_per_Mpoint']} | {r_['peak_GiB']} | {r_['GiB_per_Mpoint']} | "
              f"{r_['faces']:,} | {r_['cell_m']} | {r_['rms_mm']} | {100 * r_['within_2cm']:.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
