"""How well a block determines its camera's interior orientation and its height datum, from the covariance of its
final adjustment.

A self-calibrated focal length is only as good as the block's geometry lets it be. Over flat ground, a focal
length ``s f`` with every camera at ``s`` times its height above the ground leaves every image point in place
(Kraus 2007, §4.4): the focal length and the flying height are then one unknown, and their correlation in the
adjustment's covariance goes to ±1. Relief, oblique views, GCPs at several heights or GNSS heights of the cameras
separate them. Radial
distortion that the block determines poorly bends a flat block into a dome or a bowl. Three figures per camera say
this in the units users think in:

- ``focal_sigma_rel``: σ(f) / f;
- ``focal_height_correlation``: the correlation of f with the block's mean camera height
  ``Z̄ = (1/n) Σ Z0_j`` — ``cov(f, Z̄) / (σ(f) σ(Z̄))`` with ``cov(f, Z̄) = (1/n) Σ_j cov(f, Z0_j)`` and
  ``σ²(Z̄) = (1/n²) Σ_jk cov(Z0_j, Z0_k)``;
- ``distortion_corner_sigma_px``: the σ of the radial displacement ``f r (k1 r² + k2 r⁴ + k3 r⁶)`` at the frame's
  corner (``r`` its normalised radius), from the covariance of the estimated k's.

Besides: ``mean_height_sigma_m``, σ(Z̄), the height datum's own uncertainty.

References
----------
Kraus, K. (2007). Photogrammetry: Geometry from Images and Laser Scans, 2nd ed., §4.4 (self-calibration,
determinability of the interior orientation).
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §15.4 (self-calibrating bundle adjustment).
"""

from __future__ import annotations

import numpy as np

__all__ = ["block_determinability"]

#: parameter names that stand for the focal length, by camera model
_FOCAL = ("fx", "f", "c_mm")
_RADIAL = ("k1", "k2", "k3")


def block_determinability(covariance, param_names, cameras: dict) -> dict:
    """Determinability figures per self-calibrated camera of one adjusted block (see the module docstring).

    Parameters
    ----------
    covariance : (P, P) array or None
        A-posteriori covariance of the adjustment's parameters (poses as rotation and projection centre).
    param_names : list of str, (P,)
        ``"<camera name>.<parameter>"`` for intrinsics, ``"<pose name>.X0"`` … for the projection centres.
    cameras : dict
        ``{camera name in param_names: (id to report, Camera)}``.

    Returns
    -------
    dict
        ``{camera id: {"focal_sigma_rel", "focal_height_correlation", "distortion_corner_sigma_px",
        "mean_height_sigma_m"}}`` (a figure is None where its parameters were not estimated); empty without a
        covariance.
    """
    if covariance is None or not len(param_names):
        return {}
    cov = np.asarray(covariance, float)
    names = list(param_names)
    if cov.shape != (len(names), len(names)):
        return {}
    index = {n: k for k, n in enumerate(names)}
    z = np.array([k for k, n in enumerate(names) if n.endswith(".Z0")], int)
    var_zbar = float(np.sum(cov[np.ix_(z, z)])) / len(z) ** 2 if len(z) else float("nan")
    out = {}
    for prefix, (cid, cam) in cameras.items():
        values = dict(zip(cam.param_names, np.asarray(cam.params, float)))
        fcol = next(((index[f"{prefix}.{p}"], p) for p in _FOCAL if f"{prefix}.{p}" in index), None)
        kcols = [(index[f"{prefix}.{p}"], p) for p in _RADIAL if f"{prefix}.{p}" in index]
        if fcol is None and not kcols:
            continue  # held: nothing estimated
        rec = {"focal_sigma_rel": None, "focal_height_correlation": None, "distortion_corner_sigma_px": None,
               "mean_height_sigma_m": float(np.sqrt(var_zbar)) if var_zbar >= 0 else None}
        if fcol is not None:
            col, p = fcol
            sf = float(np.sqrt(max(cov[col, col], 0.0)))
            rec["focal_sigma_rel"] = sf / abs(values[p]) if values.get(p) else None
            if len(z) and sf > 0 and var_zbar > 0:
                c = float(np.mean(cov[col, z])) / (sf * np.sqrt(var_zbar))
                rec["focal_height_correlation"] = float(np.clip(c, -1.0, 1.0))
        if kcols and "fx" in values and "fy" in values:
            w, h = cam.image_size
            r2 = (0.5 * w / values["fx"]) ** 2 + (0.5 * h / values["fy"]) ** 2
            r = np.sqrt(r2)
            powers = {"k1": r2, "k2": r2**2, "k3": r2**3}
            cols = np.array([c for c, _ in kcols])
            g = values["fx"] * r * np.array([powers[p] for _, p in kcols])
            rec["distortion_corner_sigma_px"] = float(np.sqrt(max(g @ cov[np.ix_(cols, cols)] @ g, 0.0)))
        out[str(cid)] = rec
    return out
