"""The user's control inputs: GNSS positions (files' EXIF/XMP or a gnss.csv), GCPs, check points, manual ties."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .inputs import _name_list
from .options import SurveyOptions


def _gnss_xyz(inputs: dict, opt: SurveyOptions, crs_out: str | None):
    """(n, 3) positions in the output CRS and (n, 3) σ, from EXIF/XMP (``auto``) or a gnss.csv."""
    n = len(inputs["images"])
    xyz = np.full((n, 3), np.nan)
    sig = np.full((n, 3), np.nan)
    notes = []
    mode = opt.gnss
    if str(mode).lower() == "none":
        return xyz, sig, crs_out, ["GNSS not used (--gnss none)"]
    if str(mode).lower() == "auto":
        lat = np.array([im["geotag"].get("lat", np.nan) if im["geotag"] else np.nan for im in inputs["images"]], float)
        lon = np.array([im["geotag"].get("lon", np.nan) if im["geotag"] else np.nan for im in inputs["images"]], float)
        alt = np.array([(im["geotag"].get("alt") if im["geotag"] and im["geotag"].get("alt") is not None else np.nan)
                        for im in inputs["images"]], float)
        have = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
        if not have.any():
            return xyz, sig, crs_out, ["no GNSS positions in the files"]
        from pyproj import CRS, Transformer

        if crs_out is None:
            from ...sfm.plan import utm_epsg

            crs_out = f"EPSG:{utm_epsg(float(np.nanmean(lon[have])), float(np.nanmean(lat[have])))}"
            notes.append(f"no --crs given: positions in the UTM zone of the flight, {crs_out}")
        tf = Transformer.from_crs(CRS.from_epsg(4979), CRS.from_user_input(crs_out), always_xy=True)
        x, y, z = tf.transform(lon[have], lat[have], alt[have])
        xyz[have] = np.column_stack([x, y, z])
        for k in np.nonzero(have)[0]:
            g = inputs["images"][k]["geotag"]
            flag, std = g.get("rtk_flag"), g.get("rtk_std_m")
            if flag == 50 and std:
                s = np.maximum(np.array([std[0], std[1], std[2]], float), [0.01, 0.01, 0.02])
            elif flag == 50:
                s = np.array([0.03, 0.03, 0.05])
            elif flag == 34:
                s = np.array([0.5, 0.5, 1.0])
            elif flag == 16:
                s = np.array([2.0, 2.0, 4.0])
            else:
                s = np.array([3.0, 3.0, 5.0])
            sig[k] = s
        miss = [inputs["images"][k]["name"] for k in np.nonzero(~have)[0]]
        if miss:
            notes.append(f"{len(miss)} image(s) without GNSS: {_name_list(miss, 5)}")
        notes.append("GNSS heights used as written in the files (no geoid/ellipsoid conversion)")
    else:
        from ...io.testfield_csv import read_gnss_csv

        g = read_gnss_csv(mode)
        index = {}
        for k, im in enumerate(inputs["images"]):
            index[im["name"]] = k
            index.setdefault(Path(im["source"]).name, k)
            index.setdefault(Path(im["source"]).stem, k)
        unknown = []
        for r, name in enumerate(g.image):
            k = index.get(name, index.get(Path(name).stem))
            if k is None:
                unknown.append(name)
                continue
            xyz[k] = g.xyz[r]
            sig[k] = g.std[r] if g.std is not None else np.array([0.05, 0.05, 0.10])
        if g.std is None:
            notes.append(f"{g.source}: no sX,sY,sZ columns: σ 0.05 m horizontal, 0.10 m vertical assumed")
        miss = [im["name"] for k, im in enumerate(inputs["images"]) if not np.isfinite(xyz[k]).all()]
        if miss:
            notes.append(f"{len(miss)} image(s) without a GNSS position in {g.source}: {_name_list(miss, 5)}")
        if unknown:
            notes.append(f"{g.source}: {len(unknown)} image name(s) not among the inputs, ignored: {', '.join(unknown[:5])}")
    if opt.gnss_sigma_m is not None:
        sig[np.isfinite(sig).all(1)] = np.asarray(opt.gnss_sigma_m, float)
    return xyz, sig, crs_out, notes


def _read_manual_ties(path_meas, names, exclude_ids, default_sigma_px):
    """Rows of the GCP measurement file whose id is neither a GCP nor a check point: manual tie points.

    Returns (tie ids, observations [(image index, tie index, xy, sigma)], notes).
    """
    from ...io.testfield_csv import read_measurements_csv

    if path_meas is None:
        return [], [], []
    meas = read_measurements_csv(path_meas)
    index = {n: k for k, n in enumerate(names)}
    ids: dict[str, int] = {}
    obs = []
    for r in range(len(meas.id)):
        pid = meas.id[r]
        if pid in exclude_ids:
            continue
        k = index.get(meas.image[r], index.get(Path(meas.image[r]).stem))
        if k is None:
            continue  # named by _read_markers' note on images that are not inputs
        s = meas.std[r] if meas.std is not None else np.array([default_sigma_px, default_sigma_px])
        obs.append((k, ids.setdefault(pid, len(ids)), meas.xy[r], s))
    notes = [f"{meas.source}: {len(ids)} id(s) in neither the GCP nor the check-point file used as manual tie points "
             f"(unknown 3D points): {_name_list(list(ids), 5)}"] if ids else []
    return list(ids), obs, notes


def _read_markers(path_pts, path_meas, names, default_sigma_m, default_sigma_px, what, *, unknown_ids_note=True):
    """Control/check CSVs -> ids, xyz, sigma, observations [(image index, point index, xy, sigma)], notes."""
    from ...io.testfield_csv import read_control_csv, read_measurements_csv

    if path_pts is None:
        return [], np.zeros((0, 3)), np.zeros((0, 3)), [], []
    ctrl = read_control_csv(path_pts)
    sig = ctrl.std if ctrl.std is not None else np.full((len(ctrl.ids), 3), default_sigma_m)
    obs, notes = [], []
    if path_meas is None:
        notes.append(f"{what}: no image measurements given ({path_pts} alone cannot be used)")
        return list(ctrl.ids), ctrl.xyz, sig, obs, notes
    meas = read_measurements_csv(path_meas)
    index = {}
    for k, n in enumerate(names):
        index[n] = k
    idmap = {pid: k for k, pid in enumerate(ctrl.ids)}
    unknown_img, unknown_id = set(), set()
    for r in range(len(meas.id)):
        im = meas.image[r]
        k = index.get(im, index.get(Path(im).stem))
        if k is None:
            unknown_img.add(im)
            continue
        g = idmap.get(meas.id[r])
        if g is None:
            unknown_id.add(meas.id[r])
            continue
        s = meas.std[r] if meas.std is not None else np.array([default_sigma_px, default_sigma_px])
        obs.append((k, g, meas.xy[r], s))
    if unknown_img:
        notes.append(f"{meas.source}: measurements in {len(unknown_img)} image(s) that are not inputs, ignored: {', '.join(sorted(unknown_img)[:5])}")
    if unknown_id and unknown_ids_note:
        notes.append(f"{meas.source}: {len(unknown_id)} id(s) not in {ctrl.source}, ignored: {', '.join(sorted(unknown_id)[:5])}")
    return list(ctrl.ids), ctrl.xyz, sig, obs, notes
