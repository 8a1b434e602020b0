"""Bundle Adjustment in the Large: our LM/Schur engine vs Ceres (pycolmap) vs scipy least_squares.

Usage::

    /work/venv/bin/python benchmarks/bal.py [--repeats 3] [--problems 49-7776 21-11315 16-22106]
                                            [--data ../shared/data/bal] [--scipy-max-nfev 20]

One invocation runs every solver on every problem from the same BAL start. Each solve runs in a
fresh subprocess (``--worker``) so that its peak memory can be read from ``ru_maxrss``: the table
reports the peak resident set during the solve minus the resident set just before it (memory the
solver needed on top of the loaded problem), and the wall time of the solve call only (problem
set-up excluded for every solver). Timings on a shared machine are noisy: every solve is repeated
``--repeats`` times and the median is reported.

Every final state is scored by the same plain BAL cost, ``1/2 sum r^2`` over all observations
(points behind a camera included; COLMAP's own cost drops them).

Solvers and settings (identical stopping rules where the solver has them):

- ``ours``: :func:`thermogrammetry.adjustment.solve_bal`, Ceres-style LM, Schur complement,
  dense Cholesky on the reduced camera system, 2 threads.
- ``ceres``: pycolmap's Ceres bundle adjuster, camera model RADIAL (f, cx, cy, k1, k2) with the
  principal point fixed at 0 -- identical to BAL's model after flipping the camera frame
  (``R_colmap = diag(1,-1,-1) R_bal``, ``t_colmap = diag(1,-1,-1) t_bal``, ``y_colmap = -y_bal``);
  ``SPARSE_SCHUR``, trust-region LM, no gauge fixing (like BAL), 2 threads.
- ``scipy``: ``scipy.optimize.least_squares(method='trf', x_scale='jac')`` with our analytic sparse
  Jacobian (axis-angle parameterisation) and ``max_nfev`` bounded so the run ends in minutes.

Stopping rules: function_tolerance 1e-6, gradient_tolerance 1e-10, parameter_tolerance 1e-8,
at most 100 iterations (scipy: ftol=1e-6, xtol=1e-8, gtol=1e-10, max_nfev as given).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "bal"
PROBLEMS = {
    "49-7776": "problem-49-7776-pre.txt.bz2",
    "21-11315": "problem-21-11315-pre.txt.bz2",
    "16-22106": "problem-16-22106-pre.txt.bz2",
}
FTOL, GTOL, PTOL, MAXIT, THREADS = 1e-6, 1e-10, 1e-8, 100, 2


def _rss_kb() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


# ------------------------------------------------------------------------------------------
# workers (run in a fresh process each)
# ------------------------------------------------------------------------------------------
def _run_ours(problem):
    from thermogrammetry.adjustment.bal import BALSolverOptions, solve_bal

    opt = BALSolverOptions(
        max_iterations=MAXIT,
        function_tolerance=FTOL,
        gradient_tolerance=GTOL,
        parameter_tolerance=PTOL,
        num_threads=THREADS,
    )
    before = _rss_kb()
    t0 = time.perf_counter()
    res = solve_bal(problem, opt)
    wall = time.perf_counter() - t0
    return res.problem, res.iterations, wall, before, str(res.termination)


def _run_ceres(problem):
    import pycolmap

    from thermogrammetry.adjustment.bal import rotation_matrices

    flip = np.array([1.0, -1.0, -1.0])
    rec = pycolmap.Reconstruction()
    cams = problem.cameras
    R = rotation_matrices(cams[:, :3]) * flip[None, :, None]
    t = cams[:, 3:6] * flip
    span = float(np.max(np.abs(problem.observations))) * 2 + 2
    obs_by_cam = [[] for _ in range(problem.num_cameras)]
    for k, c in enumerate(problem.camera_index):
        obs_by_cam[c].append(k)
    local = np.empty(problem.num_observations, dtype=np.int64)
    for c in range(problem.num_cameras):
        cam = pycolmap.Camera(
            model="RADIAL",
            width=int(span),
            height=int(span),
            params=[cams[c, 6], 0.0, 0.0, cams[c, 7], cams[c, 8]],
            camera_id=c + 1,
        )
        rec.add_camera_with_trivial_rig(cam)
        ks = obs_by_cam[c]
        local[ks] = np.arange(len(ks))
        xy = problem.observations[ks] * np.array([1.0, -1.0])
        pts2d = pycolmap.Point2DList([pycolmap.Point2D(p) for p in xy])
        img = pycolmap.Image(name=f"{c}", points2D=pts2d, camera_id=c + 1, image_id=c + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R[c]), t[c]))
    order = np.argsort(problem.point_index, kind="stable")
    bounds = np.searchsorted(problem.point_index[order], np.arange(problem.num_points + 1))
    pid = np.zeros(problem.num_points, dtype=np.int64)
    for p in range(problem.num_points):
        ks = order[bounds[p] : bounds[p + 1]]
        track = pycolmap.Track([pycolmap.TrackElement(int(problem.camera_index[k]) + 1, int(local[k])) for k in ks])
        pid[p] = rec.add_point3D(problem.points[p], track)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = True
    opts.refine_principal_point = False
    opts.refine_extra_params = True
    opts.print_summary = False
    opts.ceres.auto_select_solver_type = False
    opts.ceres.min_num_residuals_for_cpu_multi_threading = 0
    so = opts.ceres.solver_options
    so.linear_solver_type = pycolmap.ceres.LinearSolverType.SPARSE_SCHUR if hasattr(pycolmap, "ceres") else so.linear_solver_type
    so.function_tolerance = FTOL
    so.gradient_tolerance = GTOL
    so.parameter_tolerance = PTOL
    so.max_num_iterations = MAXIT
    so.num_threads = THREADS
    so.minimizer_progress_to_stdout = False
    _set_sparse_schur(so)
    opts.ceres.solver_options = so
    config = pycolmap.BundleAdjustmentConfig()
    for c in range(problem.num_cameras):
        config.add_image(c + 1)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    adjuster = pycolmap.create_default_bundle_adjuster(opts, config, rec)
    before = _rss_kb()
    t0 = time.perf_counter()
    summary = adjuster.solve()
    wall = time.perf_counter() - t0
    d = summary.todict() if hasattr(summary, "todict") else {}
    iters = _ceres_iterations(summary, d)
    if os.environ.get("BAL_BENCH_DEBUG"):
        print(summary.brief_report(), file=sys.stderr)
    out = problem.copy()
    from thermogrammetry.adjustment._so3 import axis_angles

    for c in range(problem.num_cameras):
        img = rec.image(c + 1)
        pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        Rc = np.asarray(pose.rotation.matrix())
        out.cameras[c, :3] = axis_angles(Rc * flip[:, None])
        out.cameras[c, 3:6] = np.asarray(pose.translation) * flip
        prm = np.asarray(rec.camera(c + 1).params)
        out.cameras[c, 6:9] = prm[[0, 3, 4]]
    for p in range(problem.num_points):
        out.points[p] = rec.point3D(int(pid[p])).xyz
    return out, iters, wall, before, str(getattr(summary, "termination_type", ""))


def _set_sparse_schur(so):
    import pycolmap

    for mod in (getattr(pycolmap, "ceres", None), getattr(pycolmap, "pyceres", None)):
        if mod is not None and hasattr(mod, "LinearSolverType"):
            so.linear_solver_type = mod.LinearSolverType.SPARSE_SCHUR
            return
    so.linear_solver_type = type(so.linear_solver_type).SPARSE_SCHUR


def _ceres_iterations(summary, d):
    # pycolmap's summary wraps ceres::Solver::Summary; iterations = successful + unsuccessful steps
    inner = getattr(summary, "summary", None)
    for obj in (inner, summary):
        if obj is None:
            continue
        s = getattr(obj, "num_successful_steps", None)
        u = getattr(obj, "num_unsuccessful_steps", None)
        if s is not None and u is not None:
            return int(s) + int(u)
    import re

    text = str(getattr(summary, "brief_report", lambda: "")())
    m = re.search(r"Iterations:\s*(\d+)", text)
    if m:
        return int(m.group(1))
    return -1


def _run_scipy(problem, max_nfev):
    import scipy.sparse
    from scipy.optimize import least_squares

    from thermogrammetry.adjustment.bal import bal_project, bal_project_jacobian

    nc, npt, m = problem.num_cameras, problem.num_points, problem.num_observations
    ci, pi, obs = problem.camera_index, problem.point_index, problem.observations
    rows = np.repeat(np.arange(2 * m), 12)
    cols_c = ci[:, None] * 9 + np.arange(9)
    cols_p = 9 * nc + pi[:, None] * 3 + np.arange(3)
    cols1 = np.concatenate([cols_c, cols_p], axis=1)  # (m, 12)
    cols = np.repeat(cols1, 2, axis=0).ravel()

    def unpack(x):
        return x[: 9 * nc].reshape(nc, 9), x[9 * nc :].reshape(npt, 3)

    def fun(x):
        c, p = unpack(x)
        return (bal_project(c[ci], p[pi]) - obs).ravel()

    def jac(x):
        c, p = unpack(x)
        _, Jc, Jp = bal_project_jacobian(c[ci], p[pi])
        data = np.concatenate([Jc, Jp], axis=2).reshape(-1)
        return scipy.sparse.csr_matrix((data, (rows, cols)), shape=(2 * m, 9 * nc + 3 * npt))

    x0 = np.concatenate([problem.cameras.ravel(), problem.points.ravel()])
    before = _rss_kb()
    t0 = time.perf_counter()
    res = least_squares(
        fun, x0, jac=jac, method="trf", x_scale="jac", ftol=FTOL, xtol=PTOL, gtol=GTOL, max_nfev=max_nfev
    )
    wall = time.perf_counter() - t0
    out = problem.copy()
    out.cameras, out.points = (a.copy() for a in unpack(res.x))
    return out, int(res.nfev), wall, before, f"status {res.status}"


def worker(solver: str, path: str, out_json: str, max_nfev: int) -> None:
    from thermogrammetry.adjustment.bal import bal_cost
    from thermogrammetry.io import read_bal

    # warm-up on a tiny problem: libraries, thread pools and BLAS buffers are loaded before the
    # memory baseline is taken, for every solver alike
    tiny = Path(path).with_name("gtsam_dubrovnik-3-7-pre.txt")
    if tiny.exists():
        runner = {"ours": _run_ours, "ceres": _run_ceres}.get(solver, lambda p: _run_scipy(p, 5))
        runner(read_bal(tiny))
    problem = read_bal(path)
    init = bal_cost(problem)
    if solver == "ours":
        final, iters, wall, before, term = _run_ours(problem)
    elif solver == "ceres":
        final, iters, wall, before, term = _run_ceres(problem)
    else:
        final, iters, wall, before, term = _run_scipy(problem, max_nfev)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux
    rec = dict(
        solver=solver,
        initial_cost=init,
        final_cost=bal_cost(final),
        iterations=iters,
        wall_s=wall,
        peak_rss_mb=peak / 1024,
        solve_mem_mb=max(0, peak - before) / 1024,
        termination=term,
    )
    tmp = out_json + ".tmp"
    with open(tmp, "w") as f:
        json.dump(rec, f)
    os.replace(tmp, out_json)


# ------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--problems", nargs="*", default=list(PROBLEMS))
    ap.add_argument("--solvers", nargs="*", default=["ours", "ceres", "scipy"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scipy-repeats", type=int, default=1)
    ap.add_argument("--scipy-max-nfev", type=int, default=20)
    ap.add_argument("--worker", nargs=3, metavar=("SOLVER", "PATH", "OUT"))
    a = ap.parse_args(argv)
    if a.worker:
        worker(*a.worker, a.scipy_max_nfev)
        return 0
    import tempfile

    rows = []
    for prob in a.problems:
        path = Path(a.data) / PROBLEMS.get(prob, prob)
        if not path.exists():
            print(f"skip {prob}: {path} is absent")
            continue
        runs = {s: [] for s in a.solvers}
        failed = set()
        # interleave the solvers (ours, ceres, scipy, ours, ceres, ...) so that load from other
        # processes on a shared machine hits all of them alike
        for rep in range(a.repeats):
            for solver in a.solvers:
                if solver in failed or (solver == "scipy" and rep >= a.scipy_repeats):
                    continue
                with tempfile.TemporaryDirectory() as td:
                    out = os.path.join(td, "r.json")
                    cmd = [sys.executable, __file__, "--worker", solver, str(path), out,
                           "--scipy-max-nfev", str(a.scipy_max_nfev)]
                    p = subprocess.run(cmd, capture_output=True, text=True)
                    if p.returncode != 0 or not os.path.exists(out):
                        print(f"{prob} {solver}: worker failed\n{p.stderr[-2000:]}")
                        failed.add(solver)
                        continue
                    with open(out) as f:
                        runs[solver].append(json.load(f))
        res = {}
        for solver, rr in runs.items():
            if not rr:
                continue
            med = dict(rr[0])
            for k in ("wall_s", "peak_rss_mb", "solve_mem_mb", "final_cost"):
                med[k] = statistics.median(r[k] for r in rr)
            med["walls"] = [r["wall_s"] for r in rr]
            res[solver] = med
        rows.append((prob, res))
        _print_rows([(prob, res)])
        sys.stdout.flush()
    print()
    print("SUMMARY")
    _print_rows(rows)
    return 0


def _print_rows(rows):
    hdr = f"{'problem':<10} {'solver':<6} {'initial cost':>14} {'final cost':>14} {'vs ceres':>9} {'iters':>5} {'wall s':>8} {'solve MB':>9} {'peak MB':>8} {'t/t_ceres':>9}  termination"
    print(hdr)
    print("-" * len(hdr))
    for prob, res in rows:
        ce = res.get("ceres")
        for s, r in res.items():
            rel = f"{(r['final_cost'] / ce['final_cost'] - 1) * 100:+.3f}%" if ce else "-"
            ratio = f"{r['wall_s'] / ce['wall_s']:.2f}" if ce else "-"
            print(
                f"{prob:<10} {s:<6} {r['initial_cost']:>14.6e} {r['final_cost']:>14.6e} {rel:>9} {r['iterations']:>5d} "
                f"{r['wall_s']:>8.3f} {r['solve_mem_mb']:>9.1f} {r['peak_rss_mb']:>8.1f} {ratio:>9}  {r['termination']}"
            )
        if "ours" in res and "scipy" in res:
            print(f"{'':<10} scipy/ours wall-time ratio: {res['scipy']['wall_s'] / res['ours']['wall_s']:.1f}x")
        if "ours" in res and "ceres" in res:
            ratios = [o / c for o, c in zip(res["ours"]["walls"], res["ceres"]["walls"])]
            print(
                f"{'':<10} wall times ours {['%.2f' % w for w in res['ours']['walls']]}, ceres "
                f"{['%.2f' % w for w in res['ceres']['walls']]}; per-pair ratio median {statistics.median(ratios):.2f}"
            )
            print(
                f"{'':<10} peak memory ours/ceres: solve delta {res['ours']['solve_mem_mb'] / max(res['ceres']['solve_mem_mb'], 1e-9):.2f}, "
                f"process peak {res['ours']['peak_rss_mb'] / res['ceres']['peak_rss_mb']:.2f}"
            )


if __name__ == "__main__":
    sys.exit(main())
