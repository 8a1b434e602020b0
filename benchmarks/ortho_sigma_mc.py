"""Benchmark: Monte Carlo check of the ortho's σ raster (``ortho_sigma.tif``) against the scatter of the ortho.

A synthetic survey (tests/survey_truth.py: true poses, noise-free rendered frames, 2 lines × 5 frames, true
DSM at 0.1 m); each run draws the poses from the σ stated in cameras.json and adds white sensor noise of a
known NETD (the model estimates the NETD from the frames), runs ``ortho``; per cell, RMS(value − truth) over
the runs against the RMS of the predicted σ (tests/sigma_mc.py).

Usage::

    python benchmarks/ortho_sigma_mc.py [--runs 30] [--sampling nearest|bilinear] [--center-std 0.005]
                                        [--rotation-std 0.005] [--netd 0.05] [--given-netd] [--dir DIR]

Measured 2026-12-02, 30 runs, 83 k cells (median ratio scatter / predicted σ; cells within 2σ; NETD estimated):
nearest, pose σ 5 mm / 0.005°: 0.89, 97.9 %, 0.053 K; bilinear, pose σ 20 mm / 0.02°: 0.81, 95.8 %, 0.056 K.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from sigma_mc import mc_table, monte_carlo  # noqa: E402

FRAMES = [k for line in (1, 2) for k in range(14 * line + 4, 14 * line + 9)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--sampling", default="nearest")
    ap.add_argument("--center-std", type=float, default=0.005)
    ap.add_argument("--rotation-std", type=float, default=0.005)
    ap.add_argument("--netd", type=float, default=0.05)
    ap.add_argument("--dir", default=None)
    ap.add_argument("--given-netd", action="store_true", help="tell the model the NETD (else estimated from the frames)")
    a = ap.parse_args(argv)
    root = Path(a.dir or tempfile.mkdtemp(prefix="sigma_mc_"))
    mc = monte_carlo(root, a.runs, frames=FRAMES, netd=a.netd, center_std=a.center_std,
                     rotation_std_deg=a.rotation_std, sampling=a.sampling, given_netd=a.given_netd)
    tab = mc_table(mc)
    tab["netd_estimated"] = {"median": sorted(tab["netd_estimated"])[len(tab["netd_estimated"]) // 2],
                             "true": a.netd}
    print(json.dumps({"sampling": a.sampling, "center_std_m": a.center_std, "rotation_std_deg": a.rotation_std, **tab},
                     indent=1))


if __name__ == "__main__":
    main()
