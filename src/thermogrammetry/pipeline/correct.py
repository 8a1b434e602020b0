"""The ``correct`` verb's driver: per-pixel angle, distance and corrected temperature of an oriented thermal image.

Surfaces: planes (``--plane A,B,C,D`` or a ``planes.csv`` with ``normal_x,normal_y,normal_z,d_m`` as
written by ``closerange``), a triangle mesh (``--mesh`` OBJ/PLY/STL, read by trimesh) or a DSM GeoTIFF
(``--dsm``, read by rasterio; triangulated between pixel centres). The mesh/DSM must be in the same
object frame as the camera pose. The correction itself (:func:`thermogrammetry.products.correction.correct_oriented_image`)
takes arrays; this module reads the files and writes OUT as one output set.

References
----------
P. Sawicki, R. Stein, B. Więcek, "Directional emissivity correction by photogrammetric 3D object reconstruction"
(eq. 6-8: the directional emissivity and the corrected temperature).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["run_correct"]


def _finite(v, n: int, where: str) -> np.ndarray:
    """``n`` finite numbers from a JSON/CSV value, or ConfigError naming ``where`` and the value."""
    from ..errors import ConfigError

    try:
        a = np.asarray(v, dtype=float).ravel()
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected {n} numbers, got {str(v)[:80]!r}") from None
    if a.size != n:
        raise ConfigError(f"{where}: expected {n} numbers, got {a.size} ({str(v)[:80]})")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{where}: expected finite numbers, got {a.tolist()}")
    return a


def _rotation(v, where: str) -> np.ndarray:
    from ..errors import ConfigError

    R = _finite(v, 9, where).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ConfigError(f"{where}: not a rotation matrix (expected 3x3 with R R^T = I and det R = +1)")
    return R


def _read_json(path: Path, what: str):
    from ..errors import CorruptFileError
    from ..pipeline.closerange import read_text

    text = read_text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise CorruptFileError(f"{what} {path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None


def _pose_from_json(d, source: str):
    from ..errors import ConfigError
    from ..geometry import Pose

    if not isinstance(d, dict):
        raise ConfigError(f"{source}: expected a JSON object with a pose, got {type(d).__name__}")
    if "R" in d and "t" in d:
        return _rotation(d["R"], f"{source}: R"), _finite(d["t"], 3, f"{source}: t")
    if "R_cam_from_world" in d and "center_m" in d:
        R = _rotation(d["R_cam_from_world"], f"{source}: R_cam_from_world")
        return R, -R @ _finite(d["center_m"], 3, f"{source}: center_m")
    keys = ("omega_deg", "phi_deg", "kappa_deg", "X0", "Y0", "Z0")
    if set(keys) <= set(d):
        v = _finite([d[k] for k in keys], 6, f"{source}: {', '.join(keys)}")
        p = Pose.from_opk(*np.radians(v[:3]), v[3:])
        return p.R, p.t
    raise ConfigError(f"{source}: expected a pose with R and t (cam_from_world), or R_cam_from_world and center_m, "
                      f"or omega_deg, phi_deg, kappa_deg, X0, Y0, Z0; got keys {sorted(d)}")


def _plane(normal, d, where: str):
    from ..errors import ConfigError

    n = _finite(normal, 3, f"{where}: normal")
    dd = _finite([d], 1, f"{where}: d")[0]
    norm = float(np.linalg.norm(n))
    if norm < 1e-12:
        raise ConfigError(f"{where}: the plane normal is zero; expected A,B,C not all 0")
    return n.tolist(), float(dd)


def _csv_rows(text: str, source: str) -> list[dict]:
    from ..errors import CorruptFileError

    try:
        return list(csv.DictReader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise CorruptFileError(f"{source}: not a readable CSV ({exc})") from None


def _planes_csv(text: str, source: str):
    from ..errors import DataFileError

    rows = _csv_rows(text, source)
    need = {"normal_x", "normal_y", "normal_z", "d_m"}
    if not rows or not need <= set(rows[0]):
        raise DataFileError(f"{source}: expected columns name,normal_x,normal_y,normal_z,d_m (closerange planes.csv)")
    out = []
    for i, r in enumerate(rows):
        where = f"{source}, line {i + 2}"
        try:
            vals = [float(r[k]) for k in ("normal_x", "normal_y", "normal_z", "d_m")]
        except (TypeError, ValueError):
            raise DataFileError(f"{where}: normal_x,normal_y,normal_z,d_m must be numbers, got "
                                f"{[r.get(k) for k in ('normal_x', 'normal_y', 'normal_z', 'd_m')]}") from None
        n, d = _plane(vals[:3], vals[3], where)
        out.append((r.get("name") or f"plane{i}", n, d, (r.get("ids") or "").split()))
    return out


def _points_csv(text: str, source: str) -> dict:
    from ..errors import DataFileError

    rows = _csv_rows(text, source)
    if not rows or not {"id", "X", "Y", "Z"} <= set(rows[0]):
        raise DataFileError(f"{source}: expected columns id,X,Y,Z (closerange points.csv)")
    pts = {}
    for i, r in enumerate(rows):
        try:
            xyz = [float(r[k]) for k in ("X", "Y", "Z")]
        except (TypeError, ValueError):
            raise DataFileError(f"{source}, line {i + 2}: X,Y,Z of point {r.get('id')!r} must be numbers, got "
                                f"{[r.get(k) for k in 'XYZ']}") from None
        pts[r["id"]] = _finite(xyz, 3, f"{source}, line {i + 2} (point {r['id']!r}) X,Y,Z").tolist()
    return pts


def _orientation_from_cameras(path: Path, name: str):
    """(camera, R, t) of image ``name`` from a cameras.json: the oriented-cameras schema
    (:class:`thermogrammetry.io.oriented.OrientedCameras`, written by survey and closerange) or the format
    closerange wrote before (``thermogrammetry.closerange.cameras/1``, now its ``orientation.json``)."""
    from ..errors import ConfigError, UnsupportedFormatError
    from ..io.oriented import CAMERAS_FORMAT, OrientedCameras

    d = _read_json(path, "cameras file")
    fmt = d.get("format") if isinstance(d, dict) else None
    if fmt == CAMERAS_FORMAT:
        # correct reads no frame from the file (the thermal image is given): texture's cameras_fitted.json, whose
        # frame paths are absolute, is accepted here
        oc = OrientedCameras.from_dict(d, source=str(path), root=path.parent, confine_frames=False)
        if name not in oc.names():
            raise ConfigError(f"{path}: no image {name!r}; images: {', '.join(oc.names()[:10])}"
                              + (" ..." if len(oc) > 10 else ""))
        im = oc.image(name)
        return oc.camera_of(im), im.R, im.t
    if fmt == "thermogrammetry.closerange.cameras/1":
        from ..closerange import network as nw

        cams = d.get("cameras")
        if not isinstance(cams, dict) or name not in cams:
            raise ConfigError(f"{path}: no camera {name!r}; cameras: {sorted(cams) if isinstance(cams, dict) else []}")
        c = cams[name]
        if not isinstance(c, dict):
            raise ConfigError(f"{path}: camera {name!r} is not an object")
        if "camera" in c:  # positioned with a known interior orientation: keep its distortion
            from ..camera import Camera

            cam = Camera.from_dict(c["camera"], source=f"{path}: {name}")
            R = _rotation(c.get("R_cam_from_world"), f"{path}: {name}.R_cam_from_world")
            return cam, R, -R @ _finite(c.get("center_m"), 3, f"{path}: {name}.center_m")
        L = _finite(c.get("dlt_L_world"), 11, f"{path}: {name}.dlt_L_world")
        P = nw.dlt_matrix(L)
        if np.linalg.matrix_rank(P[:, :3]) < 3:
            raise ConfigError(f"{path}: {name}.dlt_L_world is degenerate (the 3x3 part of P is singular)")
        K, R, C = nw.decompose_projection(P)
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(C))):
            raise ConfigError(f"{path}: {name}.dlt_L_world does not decompose into a camera")
        return K, R, -R @ C
    raise UnsupportedFormatError(
        f"{path}: not an oriented-cameras file: key 'format' is {fmt!r}; expected {CAMERAS_FORMAT!r} (written by "
        "survey and closerange, see thermogrammetry.io.oriented) or closerange's former 'thermogrammetry.closerange.cameras/1'")


def run_correct(thermal_image, out, *, cameras=None, thermal: str | None = None, camera=None, pose=None, planes=None,
                points=None, plane=(), mesh=None, dsm=None, ambient_c: float = 22.0, emissivity: str = "cosine",
                refractive_index: float = 1.5, transmission: bool = False, humidity: float = 50.0,
                thermal_unit: str | None = None, max_angle_deg: float = 75.0,
                sigma_angle_deg: float | None = None) -> dict:
    """Correct ``thermal_image`` and write ``corrected.tif``, ``angle_deg.tif``, ``distance_m.tif``, ``valid.tif``
    (and ``sigma_k.tif`` with ``sigma_angle_deg``) into ``out``; returns ``pixels_corrected`` and ``unit``.

    Bad input raises a :class:`~thermogrammetry.errors.ThermogrammetryError` naming the file, before anything is
    written.
    """
    from .._atomic import OutputSet
    from ..closerange.workflow import CloseRangeConfig
    from ..errors import ConfigError
    from ..io import read_thermal
    from ..products.correction import correct_oriented_image
    from .closerange import _unit_of, read_text

    cam_file = None
    if cameras is not None:
        if not thermal:
            raise ConfigError("--cameras needs --thermal NAME (the image to correct)")
        cam, R, t = _orientation_from_cameras(cameras, thermal)
    elif camera is not None and pose is not None:
        from ..io.camera_file import open_camera_file

        cam_file = open_camera_file(camera)  # camera.json, Metashape XML, OpenCV YAML/XML or COLMAP cameras.txt
        cam = cam_file.camera
        R, t = _pose_from_json(_read_json(pose, "pose file"), str(pose))
    else:
        raise ConfigError("give the orientation: --cameras cameras.json --thermal NAME, or --camera camera.json --pose pose.json")
    for name, v, ok in (("--ambient-c", ambient_c, ambient_c > -273.15), ("--humidity", humidity, 0 <= humidity <= 100),
                        ("--max-angle-deg", max_angle_deg, 0 < max_angle_deg < 90),
                        ("--refractive-index", refractive_index, refractive_index > 1),
                        ("--sigma-angle-deg", sigma_angle_deg, sigma_angle_deg is None or sigma_angle_deg >= 0)):
        if v is not None and (not math.isfinite(v) or not ok):
            raise ConfigError(f"{name} {v}: out of range (ambient above absolute zero, humidity 0-100 %, "
                              "max angle in (0, 90) deg, refractive index > 1, sigma >= 0; all finite)")
    pl = []
    outlines = None
    if planes is not None:
        rows = _planes_csv(read_text(planes, "planes file"), str(planes))
        pl += [(n, dd) for _, n, dd, _ in rows]
        if points is not None:
            pts = _points_csv(read_text(points, "points file"), str(points))
            outlines = []
            for name, _, _, ids in rows:
                missing = [i for i in ids if i not in pts]
                if len(ids) < 3 or missing:
                    raise ConfigError(f"plane {name!r} in {planes}: ids {ids} not all in {points} (missing {missing})")
                outlines.append(np.array([pts[i] for i in ids]))
    if plane and outlines is not None:
        raise ConfigError("--plane has no outline: use it without --points, or put the plane in planes.csv")
    for spec in plane:
        try:
            a, b, cc, dd = (float(x) for x in spec.split(","))
        except ValueError:
            raise ConfigError(f"--plane {spec!r}: expected A,B,C,D") from None
        pl.append(_plane([a, b, cc], dd, f"--plane {spec!r}"))
    surf = None
    if mesh is not None:
        import trimesh

        from ..errors import DataFileError

        if not mesh.is_file():
            raise DataFileError(f"mesh {mesh}: no such file")
        try:
            m = trimesh.load(mesh, force="mesh", process=False)
            surf = (np.asarray(m.vertices, float), np.asarray(m.faces, int))
        except Exception as exc:  # trimesh raises many kinds
            raise DataFileError(f"mesh {mesh}: cannot be read ({type(exc).__name__}: {exc})") from None
        if surf[1].size == 0 or surf[1].ndim != 2 or not np.all(np.isfinite(surf[0])):
            raise DataFileError(f"mesh {mesh}: expected triangles with finite vertices, got {len(surf[1])} faces")
    if dsm is not None:
        surf = _read_dsm(dsm)
    if sum(x is not None for x in (mesh, dsm)) + bool(pl) != 1:
        raise ConfigError("give exactly one kind of surface: --planes/--plane, --mesh or --dsm")
    img = read_thermal(thermal_image, unit=thermal_unit)
    T0 = img.require_temperature()
    unit = (thermal_unit or _unit_of(img)).upper().lstrip("°")
    cfg = CloseRangeConfig(ambient_c=ambient_c, emissivity=emissivity, refractive_index=refractive_index,
                           transmission=transmission, relative_humidity=humidity / 100.0,
                           max_angle_deg=max_angle_deg)
    image_size = (T0.shape[1], T0.shape[0])
    if hasattr(cam, "image_size") and tuple(cam.image_size) != image_size:
        raise ConfigError(f"camera image size {cam.image_size} differs from the thermal image's {image_size}")
    cr = correct_oriented_image(T0, cam, R, t, pl or None, cfg, mesh=surf, polygons_world=outlines,
                                sigma_angle_rad=None if sigma_angle_deg is None else np.radians(sigma_angle_deg))
    n_ok = int(np.count_nonzero(cr.valid))
    if n_ok == 0:
        raise ConfigError(
            f"no pixel of {thermal_image} could be corrected: the surface is not seen by the camera (behind it, "
            f"outside the image, or viewed beyond --max-angle-deg {max_angle_deg:g}); check the pose and the surface")
    from ..io.tiff import encode_raster_tiff, encode_temperature_tiff

    with OutputSet(out, "correct") as stage:
        def put(name, data):
            stage.path(name).write_bytes(data)

        put("corrected.tif", encode_temperature_tiff(cr.corrected_k.astype(np.float32), unit=unit, encoding="float32",
                                                    metadata=img.metadata)[0])
        put("angle_deg.tif", encode_raster_tiff(np.degrees(cr.angle_rad), unit="deg", quantity="viewing_angle",
                                                description="viewing angle from the surface normal (deg)"))
        put("distance_m.tif", encode_raster_tiff(cr.distance_m, unit="m", quantity="distance",
                                                 description="camera-to-surface distance along the ray (m)"))
        put("valid.tif", encode_raster_tiff(cr.valid.astype(np.uint8), unit="1", quantity="valid",
                                            description="1 = corrected pixel, 0 = not corrected"))
        if sigma_angle_deg is not None:
            put("sigma_k.tif", encode_raster_tiff(cr.sigma_k, unit="K", quantity="sigma_temperature",
                                                  description="σ of the corrected temperature from the angle σ (K)"))
        summary = {"thermal_image": str(thermal_image), "unit": unit, "pixels_corrected": n_ok}
        if cam_file is not None:
            summary["camera_file"] = cam_file.to_dict()
        stage.commit(summary)
    out_summary = {"pixels_corrected": n_ok, "unit": unit}
    if cam_file is not None:
        out_summary["camera_file"] = cam_file.to_dict()
    return out_summary


def _read_dsm(dsm: Path):
    """DSM GeoTIFF -> triangle mesh; unreadable or empty files raise DataFileError naming the file."""
    from ..errors import CorruptFileError, DataFileError
    from ..products.surfaces import dsm_to_mesh

    if not dsm.is_file():
        raise DataFileError(f"DSM {dsm}: no such file")
    try:
        import rasterio

        with rasterio.open(dsm) as src:
            z = src.read(1, masked=True).astype(float).filled(np.nan)
            tr = src.transform
    except Exception as exc:  # rasterio raises RasterioIOError and others on damaged files
        raise CorruptFileError(f"DSM {dsm}: cannot be read as a GeoTIFF ({type(exc).__name__}: {exc})") from None
    if not np.any(np.isfinite(z)):
        raise CorruptFileError(f"DSM {dsm}: holds no valid height")
    vals = (tr.a, tr.b, tr.c, tr.d, tr.e, tr.f)
    if not all(math.isfinite(v) for v in vals) or tr.a * tr.e - tr.b * tr.d == 0:
        raise CorruptFileError(f"DSM {dsm}: degenerate or missing geotransform {vals}")
    return dsm_to_mesh(z, vals)
