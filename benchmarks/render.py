"""Render speed of the synthetic UAV survey: 100 thermal frames of 640x512 (target: < 60 s on 2 cores).

Usage::

    /work/venv/bin/python benchmarks/render.py [--frames 100] [--threads 2] [--reference-frames 5]

Scene: :class:`thermogrammetry.synthetic.survey.SurveyConfig` defaults (seed 003's set-up: 640x512,
25 mm, 17 um, 100 m above ground, 80 % overlap / 60 % sidelap, 200 x 120 m terrain with buildings and
trees, DSM cell 0.2 m), one sample per pixel, full sensor model (PSF, vignetting, FPN, NETD). Scene
generation and the one-off camera-ray cache are timed separately from the frame rendering.

Reference, same run: the same rays cast with Embree (``trimesh`` + ``embreex``) against the DSM
triangulated as two triangles per cell -- the usual fast way to ray-cast a DSM. It only casts (no
radiometry, no sensor), and intersects a triangulated surface rather than the bilinear one, so the
table also reports how far its hits lie from ours (the difference of the two surface interpolants,
not an error of either). The machine is shared: the load average and the CPU time are printed so
that wall times can be judged.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2, help="parallel workers")
    ap.add_argument("--mode", choices=("process", "thread"), default="process")
    ap.add_argument("--reference-frames", type=int, default=5)
    args = ap.parse_args(argv)

    from thermogrammetry.synthetic.survey import SurveyConfig, make_survey, render_frames
    from thermogrammetry.synthetic.terrain import raycast_heightfield

    t0 = time.perf_counter()
    scene = make_survey(SurveyConfig(max_frames=args.frames))
    t_scene = time.perf_counter() - t0
    n = len(scene.frames)
    t0 = time.perf_counter()
    scene.rays_cam()
    t_rays = time.perf_counter() - t0

    import resource

    def cpu_now():
        a = resource.getrusage(resource.RUSAGE_SELF)
        b = resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    load0 = os.getloadavg()[0]
    c0 = cpu_now()
    t0 = time.perf_counter()
    checksum = 0.0
    for _, img in render_frames(scene, threads=args.threads, mode=args.mode):
        checksum += float(img[::64, ::64].sum())
    t_render = time.perf_counter() - t0
    cpu_render = cpu_now() - c0
    load1 = os.getloadavg()[0]

    rows = [
        ("scene generation (terrain, plan, markers)", f"{t_scene:.2f} s", ""),
        ("camera ray cache (once per camera)", f"{t_rays:.2f} s", ""),
        (f"render {n} frames 640x512, {args.threads} {args.mode} worker(s)", f"{t_render:.2f} s",
         f"{t_render / n * 1000:.0f} ms/frame; CPU {cpu_render:.1f} s = {cpu_render / n * 1000:.0f} ms/frame"),
        ("target", "< 60 s", "PASS" if t_render < 60 else "FAIL"),
        ("load average (start / end, 1 min)", f"{load0:.1f} / {load1:.1f}", f"{os.cpu_count()} CPUs"),
    ]

    # reference: Embree on the triangulated DSM
    try:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: F401

        have_embree = True
    except Exception as exc:  # pragma: no cover - optional dependency
        have_embree = False
        rows.append(("reference Embree", "unavailable", f"{type(exc).__name__}: {exc}"))
    if have_embree and args.reference_frames > 0:
        ter = scene.terrain
        h, w = ter.dsm.shape
        cell = ter.dsm_cell_m
        xs = (np.arange(w) + 0.5) * cell
        ys = ter.height_m - (np.arange(h) + 0.5) * cell
        X, Y = np.meshgrid(xs, ys)
        V = np.c_[X.ravel(), Y.ravel(), ter.dsm.ravel()]
        idx = np.arange(h * w).reshape(h, w)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        F = np.r_[np.c_[a, c, b], np.c_[b, c, d]]
        t0 = time.perf_counter()
        mesh = trimesh.Trimesh(V, F, process=False)
        inter = trimesh.ray.ray_pyembree.RayMeshIntersector(mesh)
        inter.intersects_first(np.zeros((1, 3)) + [10, 10, 500], np.array([[0, 0, -1.0]]))  # build BVH
        t_build = time.perf_counter() - t0
        rays = scene.rays_cam()
        t_emb = 0.0
        t_ours = 0.0
        diffs = []
        for fr in scene.frames[: args.reference_frames]:
            C = ter.to_local(fr.pose.center)
            dw = rays @ fr.pose.R
            t0 = time.perf_counter()
            loc, ray_idx, _ = inter.intersects_location(np.broadcast_to(C, dw.shape), dw, multiple_hits=False)
            t_emb += time.perf_counter() - t0
            t0 = time.perf_counter()
            pts, hit = raycast_heightfield(ter, C, dw, caster=scene.caster)
            t_ours += time.perf_counter() - t0
            diffs.append(np.linalg.norm(loc - pts[ray_idx], axis=1))
        dd = np.concatenate(diffs)
        k = args.reference_frames
        rows += [
            ("Embree BVH build (triangulated DSM)", f"{t_build:.2f} s", f"{len(F)} triangles"),
            (f"cast only, {k} frames: ours (bilinear heightfield)", f"{t_ours:.2f} s", f"{t_ours / k * 1000:.0f} ms/frame"),
            (f"cast only, {k} frames: Embree via trimesh", f"{t_emb:.2f} s", f"{t_emb / k * 1000:.0f} ms/frame"),
            ("|hit(ours) - hit(Embree)| median / 99 % / max", f"{np.median(dd) * 1000:.2f} / {np.percentile(dd, 99) * 1000:.1f} / {dd.max() * 1000:.0f} mm",
             "bilinear vs triangulated surface"),
        ]
    try:
        from rich.console import Console
        from rich.table import Table

        tab = Table(title="synthetic UAV survey rendering")
        for col in ("what", "value", "note"):
            tab.add_column(col)
        for r in rows:
            tab.add_row(*r)
        Console().print(tab)
    except Exception:  # pragma: no cover
        for r in rows:
            print(" | ".join(r))
    print(f"checksum {checksum:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
