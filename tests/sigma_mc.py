"""Test helper: Monte Carlo of the ortho's σ model (``ortho_sigma.tif``) on a survey folder from the TRUE poses.

Each run perturbs every pose by draws of the σ it states in ``cameras.json`` (centre, m; rotation, the left
increment about the camera axes, deg) and adds white sensor noise of a known NETD to the noise-free frames, then
runs ``ortho`` (the NETD estimated from the frames, the DSM exact: ``dsm_sigma_m=0``). Per cell, the scatter
of the ortho value around the noise-free truth (ortho of the true poses and noise-free frames) is compared with
the σ the runs predicted.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import rasterio
import tifffile

from survey_truth import write_true_dsm, write_true_survey


def _rot(w):
    from thermogrammetry.products.ortho_sigma import _rot as r

    return r(w)


def monte_carlo(root, runs: int, *, frames, netd=0.05, center_std=0.005, rotation_std_deg=0.005, sampling="nearest",
                dsm_gsd=0.1, seed=0, given_netd: bool = False) -> dict:
    """``given_netd``: the model is told the NETD (isolates the geometry part) instead of estimating it.

    Returns per-cell arrays (``truth``, ``values`` (runs, h, w), ``sigma`` (runs, 4, h, w)) and the NETDs
    estimated per run."""
    from thermogrammetry.io.oriented import OrientedCameras
    from thermogrammetry.pipeline.ortho import run_ortho
    from thermogrammetry.products.ortho import OrthoConfig
    from thermogrammetry.products.ortho_sigma import SigmaConfig

    root = Path(root)
    base = root / "base"
    if not (base / "cameras.json").exists():
        sc, _ = write_true_survey(base, frames=frames, sensor=False)
        write_true_dsm(root / "dsm.tif", sc, dsm_gsd)
    cfg = OrthoConfig(sampling=sampling)
    sig = SigmaConfig(dsm_sigma_m=0.0, netd=netd if given_netd else None)
    run_ortho(base, root / "dsm.tif", root / "truth", workers=0, config=cfg, sigma=False)
    with rasterio.open(root / "truth" / "ortho.tif") as s:
        truth = s.read(1)
    remember_truth(base)
    oc = OrientedCameras.load(base)
    rng = np.random.default_rng(seed)
    vals, sigs, netds = [], [], []
    for k in range(runs):
        run = root / f"run{k}"
        shutil.rmtree(run, ignore_errors=True)
        (run / "frames").mkdir(parents=True)
        for im in oc.images:
            fr = tifffile.imread(base / im.frame).astype(np.float64)
            fr = fr + rng.normal(0.0, netd, fr.shape)
            tifffile.imwrite(run / im.frame, fr.astype(np.float32))
            C = im.center + rng.normal(0.0, center_std, 3)
            im.R = _rot(np.radians(rng.normal(0.0, rotation_std_deg, 3))) @ oc_R[im.name]
            im.t = -im.R @ C
            im.center_std = np.full(3, center_std)
            im.rotation_std_deg = np.full(3, rotation_std_deg)
        oc.save(run / "cameras.json")
        o = root / f"o{k}"  # beside the survey folder, not inside it (an OUT inside an input folder is refused)
        rep = run_ortho(run, root / "dsm.tif", o, workers=0, config=cfg, sigma=sig)
        with rasterio.open(o / "ortho.tif") as s:
            vals.append(s.read(1))
        with rasterio.open(o / "ortho_sigma.tif") as s:
            sigs.append(s.read())
        netds.append(rep["sigma"]["netd"])
        shutil.rmtree(run)
        shutil.rmtree(o)
        for im in oc.images:  # back to the truth for the next draw
            im.R, im.t = oc_R[im.name], oc_t[im.name]
    return {"truth": truth, "values": np.array(vals), "sigma": np.array(sigs), "netd": np.array(netds)}


oc_R: dict = {}
oc_t: dict = {}


def remember_truth(base):
    from thermogrammetry.io.oriented import OrientedCameras

    for im in OrientedCameras.load(base).images:
        oc_R[im.name], oc_t[im.name] = im.R.copy(), im.t.copy()


def mc_table(mc: dict) -> dict:
    """Per-cell figures: the ratio RMS(value − truth) / RMS(predicted σ), its median, the share within 2σ."""
    v, s, t = mc["values"], mc["sigma"][:, 0], mc["truth"]
    ok = np.isfinite(v).all(axis=0) & np.isfinite(s).all(axis=0) & np.isfinite(t)
    err = v[:, ok] - t[ok]
    scat = np.sqrt(np.mean(err ** 2, axis=0))
    pred = np.sqrt(np.mean(s[:, ok] ** 2, axis=0))
    ratio = scat / pred
    return {"runs": int(len(v)), "cells": int(ok.sum()), "median_ratio": float(np.median(ratio)),
            "rms_ratio": float(np.sqrt(np.mean(scat ** 2) / np.mean(pred ** 2))),
            "within_2sigma": float(np.mean(np.abs(err) <= 2 * s[:, ok])),
            "pred_median": float(np.median(pred)), "pred_p95": float(np.quantile(pred, 0.95)),
            "scatter_median": float(np.median(scat)), "scatter_p95": float(np.quantile(scat, 0.95)),
            "netd_estimated": [float(x) for x in mc["netd"]],
            "share_pred_le_0.05": float(np.mean(pred <= 0.05)),
            "within_0.05_of_those": float(np.mean(np.abs(err[:, pred <= 0.05]) <= 0.05)) if (pred <= 0.05).any() else None,
            "median_ratio_by_geometry_tercile": [float(np.median(ratio[q])) for q in np.array_split(
                np.argsort(np.median(mc["sigma"][:, 2][:, ok], axis=0)), 3)]}
