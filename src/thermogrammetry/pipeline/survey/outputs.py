"""What ``survey`` writes: ``cameras.json``, ``survey.json``, the COLMAP text model, ``sparse.ply`` / ``sparse.las``,
``cameras.gpkg`` (camera centres and image footprints for QGIS, :mod:`thermogrammetry.products.gpkg`)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from ...sfm.block_gates import ATTITUDE_FLAG_DEG, GNSS_FLAG_SIGMA
from ...sfm.block_gates import attitude_check
from .store import (CAMERAS_KEY, COLMAP_CAMERAS_KEY, COLMAP_IMAGES_KEY, COLMAP_POINTS_KEY, SPARSE_LAS_KEY,
                    SPARSE_PLY_KEY, SurveyStore, _read_frame, _tie_xy, _write_lines, frame_key)


def _point_values(project, inputs, rec, names, images_used, obs_mask):
    """Mean frame value at the observations of each point (bilinear), and whether it is a temperature."""
    tr = rec.tracks
    units = {inputs["images"][i]["unit"] for i in images_used}
    unit = units.pop() if len(units) == 1 else "mixed"
    vals = np.zeros(len(rec.points))
    cnt = np.zeros(len(rec.points))
    if unit not in ("K", "counts"):
        return None, unit
    for i in images_used:
        o = np.nonzero(obs_mask & (tr.image == i))[0]
        if len(o) == 0:
            continue
        img = _read_frame(project, names[i]).astype(np.float64)
        xy = _tie_xy(project, names[i])[tr.feature[o]]
        import cv2

        v = cv2.remap(img.astype(np.float32), xy[:, 0].astype(np.float32).reshape(-1, 1), xy[:, 1].astype(np.float32).reshape(-1, 1),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
        ok = np.isfinite(v)
        np.add.at(vals, tr.track[o][ok], v[ok])
        np.add.at(cnt, tr.track[o][ok], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return vals / cnt, unit


def _centre_covariances(fa_all) -> dict:
    """{image index: (3, 3) a-posteriori covariance of its projection centre (m²)} from the final adjustments'
    covariance (rows ``<pose>.X0/Y0/Z0``); images of a block without one, and rig views, are absent."""
    out = {}
    for ci, images, fa, datum, geo in fa_all:
        cov, names = fa.covariance, fa.param_names
        if cov is None or not names:
            continue
        p = fa.result.problem
        col = {n: k for k, n in enumerate(names)}
        for i, v in fa.view_of_image.items():
            if p.view_rig[v] >= 0:
                continue
            k = [col.get(f"{p.pose_names[p.view_pose[v]]}.{a}") for a in ("X0", "Y0", "Z0")]
            if None not in k:
                C = np.asarray(cov[np.ix_(k, k)], float)
                if np.isfinite(C).all():
                    out[int(i)] = C
    return out


def _write_outputs(project, inputs, rec, fa_all, names, crs, ctrl, checks, gcp_errors, gcp_rejected, notes, results, extra=None,
                   rig_only=None):
    from ...io.oriented import OrientedCameras, OrientedImage
    from ...sfm.georef import axis_statistics, gnss_misfit

    cam_ids = SurveyStore(project).load_reconstruction_meta()["camera_ids"]
    images_out = []
    per_image = []
    rms_all = []
    tie_by_image: dict[int, np.ndarray] = {}
    oriented_idx = []
    for ci, images, fa, datum, geo in fa_all:
        for i in images:
            oriented_idx.append(int(i))
        v = fa.tie_residuals
        for i in images:
            tie_by_image[int(i)] = v[fa.tie_obs_image == i]
        rms_all.append(v)
        for i in images:
            im = inputs["images"][i]
            images_out.append(OrientedImage(names[i], cam_ids[rec.image_camera[i]], rec.R[i], rec.t[i],
                                            center_std=fa.center_std[i], rotation_std_deg=fa.rotation_std_deg[i],
                                            frame=frame_key(names[i]), source=im["source"], unit=im["unit"],
                                            sensor=im["sensor"]))
    cams = {cid: rec.cameras[k] for k, cid in enumerate(cam_ids) if any(o.camera_id == cid for o in images_out)}
    # the camera's standard deviations from the last solve of the largest block
    if fa_all:
        fa0 = fa_all[0][2]
        if fa0.result.camera_std:
            for b, (cid) in enumerate(sorted({o.camera_id for o in images_out if True}, key=cam_ids.index)):
                k = cam_ids.index(cid)
                pb_cams = fa0.result.problem.cameras
                # cameras in the problem are added in sorted camera index order
                order = sorted({int(rec.image_camera[i]) for i in fa_all[0][1]})
                if k in order:
                    std = fa0.result.camera_std[order.index(k)]
                    cams[cid] = rec.cameras[k].replace(param_std=np.where(np.isfinite(std), std, np.nan))
    oc = OrientedCameras(cams, images_out, crs=crs,
                         notes="" if crs else "local frame (no GNSS/GCP datum): arbitrary origin, orientation and scale") if images_out else None
    V = np.concatenate(rms_all) if rms_all else np.zeros((0, 2))
    rms = float(np.sqrt(np.mean(np.sum(V**2, axis=1)))) if len(V) else None
    n_total = len(names) + len(inputs["failed"])
    centre_cov = _centre_covariances(fa_all)
    status = []
    for i, n in enumerate(names):
        s = rec.status[i]
        ok = i in set(oriented_idx)
        v = tie_by_image.get(i)
        status.append({"name": n, "oriented": ok, "block": int(rec.component[i]) + 1 if ok else None,
                       "reason": ((rig_only or {}).get(i, "") if ok else (s.reason or "not oriented")),
                       "tie_points": int(len(v)) if v is not None else 0,
                       "rms_px": float(np.sqrt(np.mean(np.sum(v**2, 1)))) if v is not None and len(v) else None,
                       "unit": inputs["images"][i]["unit"], "sensor": inputs["images"][i]["sensor"],
                       **({"rig_only": True} if ok and i in (rig_only or {}) else {}),
                       **({"center_cov_m2": centre_cov[i].tolist()} if ok and i in centre_cov else {})})
    # GNSS misfit per image: adjusted antenna position − given GNSS position (a surveyor's check of every centre)
    gnss_d, flagged = [], []
    for ci, images, fa, datum, geo in fa_all:
        if not geo:
            continue
        for i, (d, z) in sorted(gnss_misfit(rec, images, ctrl).items()):
            st = status[i]
            st["gnss_residual_m"] = [float(x) for x in d]
            st["gnss_residual_sigma"] = float(np.max(z))
            used = i not in fa.gnss_rejected
            if used:
                gnss_d.append(d)
            else:
                st["gnss_used"] = False
            if np.max(z) > GNSS_FLAG_SIGMA:
                flagged.append((i, d, float(np.max(z)), used))
    if flagged:
        if len(flagged) > max(3, 0.1 * len(gnss_d)):
            notes = notes + [f"{len(flagged)} of {len(gnss_d)} adjusted camera centres are more than {GNSS_FLAG_SIGMA:g} σ "
                             "from their GNSS positions (gnss_flagged): the GNSS σ given is too optimistic for this "
                             "flight, or the GNSS and the images do not belong together"]
        else:
            notes = notes + [f"{names[i]}: adjusted camera centre {np.linalg.norm(d):.3f} m from its GNSS position "
                             f"({z:.1f} σ{'' if used else '; that GNSS position was left out of the final adjustment'}): "
                             "its orientation (e.g. tie points on occluding edges or repeated structure) or its GNSS tag "
                             "is wrong; check it before using its products" for i, d, z, used in flagged]
    att_summary = attitude_check(rec, fa_all, ctrl, names, status)
    if att_summary.get("median_deg", 0.0) > ATTITUDE_FLAG_DEG:
        notes = notes + [f"the camera attitudes in the files differ from the adjusted rotations by {att_summary['median_deg']:.1f}° "
                         "(median over the images): a convention or camera mounting the files do not describe, not a "
                         "fault of the orientation"]
    if att_summary.get("flagged"):
        notes = notes + [f"{f['image']}: adjusted rotation {f['from_common_deg']:.1f}° from the camera attitude in its file "
                         "beyond the block's common difference: its orientation (a wrong resection) or its attitude tag is "
                         "wrong; check it before using its products" for f in att_summary["flagged"]]
    for f in inputs["failed"]:
        status.append({"name": Path(f["file"]).name, "oriented": False, "block": None, "reason": f["reason"], "tie_points": 0,
                       "rms_px": None, "unit": None, "sensor": None})
    # sparse cloud of the exported blocks
    tr = rec.tracks
    used = np.zeros(len(names), bool)
    used[oriented_idx] = True
    obs_mask = rec.obs_valid & used[tr.image] & np.isfinite(rec.points[tr.track]).all(1)
    cnt = np.bincount(tr.track[obs_mask], minlength=len(rec.points))
    pts_ok = (cnt >= 2) & np.isfinite(rec.points).all(1)
    if oriented_idx and pts_ok.any():
        # points run away to near infinity (nearly parallel rays left after outlier removal) are not exported
        d = np.linalg.norm(rec.points[pts_ok] - rec.centers()[oriented_idx].mean(axis=0), axis=1)
        far = np.zeros(len(pts_ok), bool)
        far[np.nonzero(pts_ok)[0]] = d > 50.0 * max(float(np.median(d)), 1e-9)
        pts_ok &= ~far
    values, unit = _point_values(project, inputs, rec, names, oriented_idx, obs_mask)
    mult = cnt[pts_ok]
    units = sorted({inputs["images"][i]["unit"] for i in oriented_idx})
    summary = {
        "images_total": n_total,
        "images_oriented": int(len(oriented_idx)),
        "components": [int(len(images)) for ci, images, fa, datum, geo in fa_all],
        "reprojection_rms_px": rms,
        "gcps": axis_statistics(gcp_errors),
        "checkpoints": axis_statistics([c["error"] for c in checks if c.get("error") is not None]),
        "gnss": axis_statistics(gnss_d),
        "gnss_flagged": [{"image": names[i], "dx": float(d[0]), "dy": float(d[1]), "dz": float(d[2]), "sigma": z,
                          "used": used} for i, d, z, used in flagged],
        "attitude": att_summary,
        "crs": crs,
        "seconds": None,
        "georeferenced": bool(crs),
        "frame_units": units,
        "temperatures": units == ["K"],
        "points": int(pts_ok.sum()),
        "tie_point_multiplicity": {"mean": float(mult.mean()) if len(mult) else None,
                                   "histogram": np.bincount(mult).tolist() if len(mult) else []},
        "blocks": results,
        "images": status,
        "cameras": {cid: {"params": c.param_dict, "std": dict(zip(c.param_names, [None if not np.isfinite(x) else float(x)
                                                                                   for x in (c.param_std if c.param_std is not None else [np.nan] * len(c.param_names))]))}
                    for cid, c in cams.items()},
        "gcp_residuals": [{"id": ctrl.gcp_ids[g], "dx": float(e[0]), "dy": float(e[1]), "dz": float(e[2]),
                           "x": float(ctrl.gcp_xyz[g][0]), "y": float(ctrl.gcp_xyz[g][1]), "z": float(ctrl.gcp_xyz[g][2]),
                           "sigma_given": [float(v) for v in ctrl.gcp_sigma[g]]}
                          for g, e in zip([g for *_, fa, datum, geo in fa_all for g in np.nonzero(fa.gcp_used)[0]], gcp_errors)],
        "gcp_rejected_measurements": gcp_rejected,
        "checkpoint_errors": [{"id": c["id"], "n_images": c["n_images"], "reason": c.get("reason", ""),
                               **_given_xyz(ctrl, c["id"]),
                               **({"dx": float(c["error"][0]), "dy": float(c["error"][1]), "dz": float(c["error"][2]),
                                   **({"sx": float(c["std"][0]), "sy": float(c["std"][1]), "sz": float(c["std"][2])}
                                      if c.get("std") is not None else {"sx": None, "sy": None, "sz": None,
                                                                        "sigma_refused": c.get("sigma_refused", "")})}
                                  if c.get("error") is not None else {})} for c in checks],
        "failed_inputs": inputs["failed"],
        "notes": inputs.get("notes", []) + notes + sorted({im["note"] for im in inputs["images"] if im.get("note")}),
        **(extra or {}),
    }
    if oc is not None:
        project.write_text(CAMERAS_KEY, json.dumps(oc.to_dict(), indent=1) + "\n")
        _write_colmap(project, oc, rec, names, oriented_idx, obs_mask, pts_ok, values)
        _write_clouds(project, rec.points[pts_ok], None if values is None else values[pts_ok], unit, mult, crs)
        from ...products.gpkg import cameras_gpkg_bytes

        zs = rec.points[pts_ok][:, 2]
        project.write_bytes("cameras.gpkg", cameras_gpkg_bytes(oc, float(np.median(zs)) if len(zs) else None))
    SurveyStore(project).save_survey(summary)
    return {"images_oriented": summary["images_oriented"], "components": summary["components"], "rms_px": rms, "crs": crs}


def _given_xyz(ctrl, cid) -> dict:
    """``x``, ``y``, ``z``: the given coordinates of check point ``cid`` (its map position in the report)."""
    if cid not in ctrl.check_ids:
        return {}
    X = ctrl.check_xyz[ctrl.check_ids.index(cid)]
    return {"x": float(X[0]), "y": float(X[1]), "z": float(X[2])}


def _write_colmap(project, oc, rec, names, oriented_idx, obs_mask, pts_ok, values):
    from ...io.colmap import ColmapImage, ColmapPoints3D, colmap_camera_line
    from ...geometry.rotations import quaternion_from_matrix

    cam_keys = list(oc.cameras)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for k, cid in enumerate(cam_keys):
        cam = oc.cameras[cid]
        if cam.model.value == "photogrammetric":
            from ...camera import convert_camera

            cam = convert_camera(cam, "opencv").camera
        lines.append(colmap_camera_line(k + 1, cam))
    project.write_text(COLMAP_CAMERAS_KEY, "\n".join(lines) + "\n")
    tr = rec.tracks
    pid = np.full(len(rec.points), -1, np.int64)
    pid[pts_ok] = np.arange(1, int(pts_ok.sum()) + 1)
    name_to_idx = {n: i for i, n in enumerate(names)}
    # the tracks of points3D.txt as arrays (point id, image id, index in the image's POINTS2D), in the order the
    # images are written (12 B per observation instead of a string each)
    t_pid, t_img, t_n2d = [], [], []

    def image_lines():
        yield "# Image list with two lines of data per image:"
        yield "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
        yield "#   POINTS2D[] as (X, Y, POINT3D_ID)"
        # COLMAP text models hold coordinates as written: large CRS coordinates keep their precision in %.17g
        for k, o in enumerate(oc.images):
            i = name_to_idx[o.name]
            q = quaternion_from_matrix(o.R)
            sel = np.nonzero(obs_mask & (tr.image == i) & pts_ok[tr.track])[0]
            xy = _tie_xy(project, names[i])[tr.feature[sel]]
            yield " ".join([str(k + 1)] + [repr(float(v)) for v in q] + [repr(float(v)) for v in o.t]
                           + [str(cam_keys.index(o.camera_id) + 1), f"{o.name}.tif"])
            ps = pid[tr.track[sel]]
            yield " ".join(f"{x + 0.5!r} {y + 0.5!r} {int(t)}" for (x, y), t in zip(xy.tolist(), ps.tolist()))
            t_pid.append(ps.astype(np.int32))
            t_img.append(np.full(len(sel), k + 1, np.int32))
            t_n2d.append(np.arange(len(sel), dtype=np.int32))

    _write_lines(project, COLMAP_IMAGES_KEY, image_lines())
    P = rec.points[pts_ok]
    if values is not None:
        v = values[pts_ok]
        lo, hi = np.nanpercentile(v, [1, 99]) if np.isfinite(v).any() else (0.0, 1.0)
        g = np.clip((np.nan_to_num(v, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(int)
    else:
        g = np.full(len(P), 128)
    cat = (lambda a: np.concatenate(a) if a else np.zeros(0, np.int32))  # noqa: E731
    t_pid, t_img, t_n2d = cat(t_pid), cat(t_img), cat(t_n2d)
    order = np.argsort(t_pid, kind="stable")  # per point, its elements in the order they were written
    t_img, t_n2d = t_img[order], t_n2d[order]
    bounds = np.searchsorted(t_pid[order], np.arange(1, len(P) + 2))
    del order, t_pid

    def point_lines():
        yield "# 3D point list with one line of data per point:"
        yield "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
        for k in range(len(P)):
            a, b = bounds[k], bounds[k + 1]
            yield (f"{k + 1} {float(P[k, 0])!r} {float(P[k, 1])!r} {float(P[k, 2])!r} {int(g[k])} {int(g[k])} {int(g[k])} 0 "
                   + " ".join(f"{im} {n2d}" for im, n2d in zip(t_img[a:b].tolist(), t_n2d[a:b].tolist())))

    _write_lines(project, COLMAP_POINTS_KEY, point_lines())


def _write_clouds(project, P, values, unit, mult, crs):
    """sparse.ply (plyfile) and sparse.las (laspy) with the mean frame value of each point."""
    import laspy
    from plyfile import PlyData, PlyElement

    name = "temperature_k" if unit == "K" else ("raw_counts" if unit == "counts" else None)
    dt = [("x", "f8"), ("y", "f8"), ("z", "f8"), ("views", "u2")] + ([(name, "f4")] if name and values is not None else [])
    arr = np.empty(len(P), dtype=dt)
    arr["x"], arr["y"], arr["z"] = P[:, 0], P[:, 1], P[:, 2]
    arr["views"] = np.minimum(mult, 65535)
    if name and values is not None:
        arr[name] = values.astype(np.float32)
    buf = io.BytesIO()
    PlyData([PlyElement.describe(arr, "vertex")], text=False,
            comments=[f"crs {crs or 'local'}", f"value {name or 'none'}"]).write(buf)
    project.write_bytes(SPARSE_PLY_KEY, buf.getvalue())
    header = laspy.LasHeader(point_format=6, version="1.4")
    if name and values is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.float32,
                                                    description="kelvin" if unit == "K" else "raw sensor counts"))
    header.add_extra_dim(laspy.ExtraBytesParams(name="views", type=np.uint16, description="images observing the point"))
    if len(P):
        header.offsets = np.floor(P.min(axis=0))
    header.scales = np.array([0.001, 0.001, 0.001])
    if crs:
        from pyproj import CRS

        try:
            header.add_crs(CRS.from_user_input(crs))
        except Exception:  # noqa: BLE001 - a CRS laspy cannot encode is recorded in the report instead
            pass
    las = laspy.LasData(header)
    las.x, las.y, las.z = P[:, 0], P[:, 1], P[:, 2]
    if name and values is not None:
        setattr(las, name, values.astype(np.float32))
    las.views = np.minimum(mult, 65535).astype(np.uint16)
    buf = io.BytesIO()
    las.write(buf)
    project.write_bytes(SPARSE_LAS_KEY, buf.getvalue())
