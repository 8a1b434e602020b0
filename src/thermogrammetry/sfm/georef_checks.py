"""Check points of a georeferenced block and its accuracy statistics.

Check points never enter the adjustment: each is intersected afterwards from its image measurements with
the adjusted cameras (:func:`intersect_check_points`), and its covariance is the propagation of both the
measurement noise and the a-posteriori covariance of the poses and intrinsics involved::

    Σ_X = N⁻¹ + G Σ_θ Gᵀ,   N = J_Xᵀ W J_X,   G = N⁻¹ J_Xᵀ W J_θ

(J by central differences in the engine's parameterisation: left rotation increment about the camera
axes, projection centre, camera parameters). :func:`axis_statistics` gives the per-axis accuracy table.

References
----------
Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
thermal imagery (check points, Table 3 accuracy layout).
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §4.2.4 (propagation).
"""

from __future__ import annotations

import numpy as np

from ..geometry.rotations import matrix_from_axis_angle
from .georef_adjustment import FinalAdjustment
from .georef_control import ControlInputs

__all__ = ["intersect_check_points", "axis_statistics", "gcp_measurement_report"]


def _project(cam, R, t, X):
    return cam.project((R @ X + t)[None, :])[0]


def intersect_check_points(rec, fa: FinalAdjustment, ctrl: ControlInputs, *, eps: float = 1e-6):
    """Intersect each check point from its measurements in the adjusted block (never adjusted with it).

    Returns
    -------
    list of dict: ``id``, ``xyz`` (3,), ``std`` (3,) m (measurement + pose/camera covariance), ``error`` (3,)
    (estimate - given), ``n_images``, ``measurement_sigma_px`` (the measurements' σ used: the given one scaled by
    the GCP measurements' estimated over given σ, ``fa.marker_sigma``); check points seen in fewer than 2 oriented images are listed with
    ``xyz`` None and a ``reason``.
    """
    from .reconstruction import triangulate_tracks

    out = []
    block = set(fa.images.tolist())
    # measured like the GCPs: the check points' measurements are taken to scatter as the GCPs' residuals show theirs
    # to (a variance component of the marker measurements, more or less than the σ given or the default)
    ms = fa.marker_sigma
    scale = float(np.clip(ms["estimated_px"] / ms["given_px"], 0.1, 10.0)) if ms and ms["given_px"] > 0 else 1.0
    names = fa.param_names
    index = {nm: k for k, nm in enumerate(names)}
    for ci, cid in enumerate(ctrl.check_ids):
        obs = [(i, np.asarray(xy, float), float(np.max(s))) for (i, gi, xy, s) in ctrl.check_obs if gi == ci and i in block]
        if len(obs) < 2:
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs),
                        "reason": f"measured in {len(obs)} oriented image(s); 2 needed"})
            continue
        ii = np.array([o[0] for o in obs])
        xy = np.array([o[1] for o in obs])
        sig = np.array([o[2] for o in obs]) * scale
        rays = np.concatenate([rec.cameras[rec.image_camera[i]].unproject(xy[k:k + 1])[:, :2] for k, i in enumerate(ii)])
        X, _ = triangulate_tracks(np.array([0]), np.zeros(len(ii), int), rec.R[ii], rec.t[ii], rays)
        X = X[0]
        if not np.isfinite(X).all():
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs), "reason": "rays do not intersect"})
            continue
        w = np.repeat(1.0 / sig**2, 2)

        def f(X, Rs, ts, cams):
            return np.concatenate([_project(cams[k], Rs[k], ts[k], X) for k in range(len(ii))])

        # work about a local origin: CRS coordinates (1e6 m) would eat the finite-difference steps
        origin = X.copy()
        Rs = [rec.R[i].copy() for i in ii]
        ts = [rec.t[i] + rec.R[i] @ origin for i in ii]
        cams = [rec.cameras[rec.image_camera[i]] for i in ii]
        X = np.zeros(3)
        for _ in range(10):  # Gauss-Newton on X
            r = xy.ravel() - f(X, Rs, ts, cams)
            J = np.empty((2 * len(ii), 3))
            h = 1e-4
            for a in range(3):
                d = np.zeros(3)
                d[a] = h
                J[:, a] = (f(X + d, Rs, ts, cams) - f(X - d, Rs, ts, cams)) / (2 * h)
            N = J.T @ (w[:, None] * J)
            if not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e12:
                break
            dx = np.linalg.solve(N, J.T @ (w * r))
            X = X + dx
            if np.linalg.norm(dx) < 1e-9 * max(1.0, np.linalg.norm(X)):
                break
        if not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e12:
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs),
                        "reason": "intersection undetermined (rays nearly parallel or projections invalid)"})
            continue
        Ninv = np.linalg.inv(N)
        cov = Ninv.copy()
        # propagation of the a-posteriori covariance of the camera-side parameters involved
        if fa.covariance is not None:
            cols, Jt = [], []
            for k, i in enumerate(ii):
                C = -Rs[k].T @ ts[k]
                base = f"image{i}"
                for a, nm in enumerate(("wx", "wy", "wz", "X0", "Y0", "Z0")):
                    key = f"{base}.{nm}"
                    if key not in index:
                        continue
                    col = np.zeros(2 * len(ii))
                    h = 1e-7 if a < 3 else 1e-4
                    vals = []
                    for sgn in (1, -1):
                        Rk, Ck = Rs[k], C.copy()
                        if a < 3:
                            dw = np.zeros(3)
                            dw[a] = sgn * h
                            Rk = matrix_from_axis_angle(dw) @ Rs[k]
                        else:
                            Ck[a - 3] += sgn * h
                        vals.append(_project(cams[k], Rk, -Rk @ Ck, X))
                    col[2 * k:2 * k + 2] = (vals[0] - vals[1]) / (2 * h)
                    cols.append(index[key])
                    Jt.append(col)
            for c in sorted({int(rec.image_camera[i]) for i in ii}):
                cam = rec.cameras[c]
                for pn in cam.param_names:
                    key = f"camera{c}.{pn}"
                    if key not in index:
                        continue
                    h = 1e-6 * max(1.0, abs(cam[pn]))
                    col = np.zeros(2 * len(ii))
                    for k, i in enumerate(ii):
                        if rec.image_camera[i] != c:
                            continue
                        cp = cam.replace(**{pn: cam[pn] + h})
                        cm = cam.replace(**{pn: cam[pn] - h})
                        col[2 * k:2 * k + 2] = (_project(cp, Rs[k], ts[k], X) - _project(cm, Rs[k], ts[k], X)) / (2 * h)
                    cols.append(index[key])
                    Jt.append(col)
            if cols:
                Jt = np.array(Jt).T  # (2k, p): d(projection)/d(theta)
                G = Ninv @ J.T @ (w[:, None] * Jt)  # dX/d(observation shift) applied to -J_theta
                S = fa.covariance[np.ix_(cols, cols)]
                cov = cov + G @ S @ G.T
        std = np.sqrt(np.diag(cov))
        X = X + origin
        out.append({"id": cid, "xyz": X, "std": std, "cov": cov, "error": X - ctrl.check_xyz[ci], "n_images": len(obs),
                    "reason": "", "measurement_sigma_px": float(np.median(sig))})
    return out


def axis_statistics(errors) -> dict:
    """Khodaei et al. (2015) Table 3 layout: n, min, max, MAE, RMSE per axis (metres); nulls when n = 0."""
    E = np.asarray([e for e in errors if e is not None and np.all(np.isfinite(e))], float).reshape(-1, 3)
    d = {"n": int(len(E))}
    for k, ax in enumerate("xyz"):
        if len(E):
            v = E[:, k]
            d.update({f"rmse_{ax}": float(np.sqrt(np.mean(v**2))), f"mae_{ax}": float(np.mean(np.abs(v))),
                      f"min_{ax}": float(v.min()), f"max_{ax}": float(v.max())})
        else:
            d.update({f"rmse_{ax}": None, f"mae_{ax}": None, f"min_{ax}": None, f"max_{ax}": None})
    return d


def gcp_measurement_report(rec, fa_all, ctrl: ControlInputs, names) -> dict:
    """Every one of the user's GCP image measurements with its residual, whether it was used and, if not, why
    (``gcp_measurements``), and per GCP and per image the measurements, those used and the RMS and largest residual
    of the used ones (``gcp_measurements_by_gcp``, ``gcp_measurements_by_image``): no measurement is dropped
    silently. A measurement in an image that no georeferenced block holds is listed with that reason.

    Parameters
    ----------
    rec : Reconstruction (``registered``)
    fa_all : list of (block index, image indices, FinalAdjustment, datum, georeferenced)
    ctrl : ControlInputs
    names : list of str, image names by index

    Returns
    -------
    dict with the three lists (``survey.json`` keys; residuals ``projected − measured`` in px, see
    :func:`~thermogrammetry.sfm.georef_adjustment.gcp_measurement_table`)
    """
    rows, seen, georeferenced = [], set(), set()
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        georeferenced.update(int(i) for i in images)
        for r in fa.gcp_measurements:
            key = (r["image"], r["id"])
            if key not in seen:
                seen.add(key)
                rows.append({**r, "image": names[r["image"]], "block": int(ci) + 1})
    for i, gi, xy, sig in ctrl.gcp_obs:
        if (int(i), ctrl.gcp_ids[gi]) in seen:
            continue
        seen.add((int(i), ctrl.gcp_ids[gi]))
        why = "its image is in a block that is not georeferenced" if rec.registered[i] and int(i) not in georeferenced \
            else "its image is not oriented"
        rows.append({"image": names[i], "id": ctrl.gcp_ids[gi], "sigma_px": float(np.max(sig)), "dx_px": None,
                     "dy_px": None, "residual_px": None, "used": False, "reason": why, "block": None})

    def summary(key):
        out = {}
        for r in rows:
            e = out.setdefault(r[key], {key: r[key], "measurements": 0, "used": 0, "rms_px": None, "max_px": None, "_v": []})
            e["measurements"] += 1
            if r["used"] and r["residual_px"] is not None:
                e["used"] += 1
                e["_v"].append(r["residual_px"])
        for e in out.values():
            v = np.asarray(e.pop("_v"), float)
            if len(v):
                e["rms_px"], e["max_px"] = float(np.sqrt(np.mean(v**2))), float(np.max(v))
        return sorted(out.values(), key=lambda e: str(e[key]))

    return {"gcp_measurements": rows, "gcp_measurements_by_gcp": summary("id"), "gcp_measurements_by_image": summary("image")}
