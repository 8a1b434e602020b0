"""Camera positions and image footprints as an OGC GeoPackage (``cameras.gpkg``) for QGIS and GDAL.

Two layers in the survey's CRS: ``cameras`` (3D points: each oriented image's projection centre, with its name,
height, standard deviations and viewing direction) and ``footprints`` (polygons: the image's four corners
intersected with the horizontal plane at the sparse cloud's median height; an image whose corner ray does not
meet that plane below the camera has no footprint). Written with the standard library's sqlite3 following the
GeoPackage 1.3 encoding (OGC 12-128r18: the ``gpkg_spatial_ref_sys``, ``gpkg_contents`` and
``gpkg_geometry_columns`` tables; geometries as the GeoPackage binary header + ISO WKB), so no GDAL vector driver
is needed to write it.
"""

from __future__ import annotations

import os
import sqlite3
import struct
import tempfile

import numpy as np

__all__ = ["footprint", "cameras_gpkg_bytes"]


def footprint(cam, R, center, ground_z: float) -> np.ndarray | None:
    """(4, 2) x, y of an image's corners on the plane ``z = ground_z`` (m), or None when a corner ray misses it.

    ``R``: world → camera rotation; ``center``: (3,) projection centre."""
    w, h = cam.image_size
    rays = np.asarray(cam.unproject(np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)), float)
    d = rays @ np.asarray(R, float)  # camera → world directions (rows)
    C = np.asarray(center, float)
    if not np.all(d[:, 2] < -1e-9):
        return None
    s = (ground_z - C[2]) / d[:, 2]
    if not np.all(s > 0):
        return None
    return C[:2] + s[:, None] * d[:, :2]


def _srs(crs) -> tuple[int, str, str]:
    """(srs_id, name, WKT1) of a CRS for gpkg_spatial_ref_sys; (0, 'undefined', 'undefined') without a CRS."""
    if not crs:
        return 0, "undefined", "undefined"
    from pyproj import CRS
    from pyproj.enums import WktVersion

    c = CRS.from_user_input(crs)
    h = c.sub_crs_list[0] if c.is_compound else c
    code = h.to_epsg() or 100000
    return int(code), h.name, h.to_wkt(WktVersion.WKT1_GDAL)


def _gpb(srs_id: int, wkb: bytes, env) -> bytes:
    """GeoPackage binary geometry: magic 'GP', version 0, flags (little-endian, envelope xy), srs id, envelope, WKB."""
    flags = 0b00000011  # envelope [minx, maxx, miny, maxy], little-endian
    return b"GP" + bytes([0, flags]) + struct.pack("<i", srs_id) + struct.pack("<4d", *env) + wkb


def _point_z(x, y, z) -> bytes:
    return struct.pack("<BIddd", 1, 1001, x, y, z)  # ISO WKB Point Z


def _polygon(xy) -> bytes:
    ring = np.vstack([xy, xy[:1]])
    return struct.pack("<BII", 1, 3, 1) + struct.pack("<I", len(ring)) + ring.astype("<f8").tobytes()


def cameras_gpkg_bytes(oc, ground_z: float | None) -> bytes:
    """The GeoPackage of an :class:`~thermogrammetry.io.oriented.OrientedCameras` (see the module docstring).

    ``ground_z``: height (m) of the footprints' plane (the sparse cloud's median); None: no footprints."""
    srs_id, srs_name, wkt = _srs(oc.crs)
    fd, tmp = tempfile.mkstemp(suffix=".gpkg")
    os.close(fd)
    try:
        db = sqlite3.connect(tmp)
        db.execute("PRAGMA application_id = 1196444487")  # 'GPKG'
        db.execute("PRAGMA user_version = 10300")
        db.executescript("""
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY, organization TEXT NOT NULL,
            organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT UNIQUE,
            description TEXT DEFAULT '', last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
            min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER);
        CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
            geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
            CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name));
        CREATE TABLE cameras (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom POINT, name TEXT, camera_id TEXT, x DOUBLE,
            y DOUBLE, z DOUBLE, sx DOUBLE, sy DOUBLE, sz DOUBLE, view_azimuth_deg DOUBLE, view_off_nadir_deg DOUBLE);
        CREATE TABLE footprints (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom POLYGON, name TEXT, ground_z DOUBLE,
            area_m2 DOUBLE);
        """)
        rows = [("Undefined cartesian SRS", -1, "NONE", -1, "undefined", None),
                ("Undefined geographic SRS", 0, "NONE", 0, "undefined", None),
                ("WGS 84 geodetic", 4326, "EPSG", 4326, _srs("EPSG:4326")[2], None)]
        if srs_id not in (-1, 0, 4326):
            rows.append((srs_name, srs_id, "EPSG" if srs_id != 100000 else "NONE", srs_id, wkt, None))
        db.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?,?,?,?,?,?)", rows)
        cams, feet = [], []
        for im in oc.images:
            C = np.asarray(im.center, float)
            view = np.asarray(im.R, float)[2]  # the optical axis in the world frame
            az = float(np.degrees(np.arctan2(view[0], view[1])) % 360.0)
            off = float(np.degrees(np.arccos(np.clip(-view[2], -1.0, 1.0))))
            sd = [None] * 3 if im.center_std is None else [float(v) for v in np.asarray(im.center_std, float)]
            cams.append((_gpb(srs_id, _point_z(*C), (C[0], C[0], C[1], C[1])), im.name, im.camera_id, *map(float, C),
                         *sd, az, off))
            if ground_z is not None:
                q = footprint(oc.camera_of(im), im.R, C, float(ground_z))
                if q is not None:
                    area = 0.5 * abs(float(np.dot(q[:, 0], np.roll(q[:, 1], -1)) - np.dot(q[:, 1], np.roll(q[:, 0], -1))))
                    env = (q[:, 0].min(), q[:, 0].max(), q[:, 1].min(), q[:, 1].max())
                    feet.append((_gpb(srs_id, _polygon(q), env), im.name, float(ground_z), area))
        db.executemany("INSERT INTO cameras (geom, name, camera_id, x, y, z, sx, sy, sz, view_azimuth_deg, "
                       "view_off_nadir_deg) VALUES (?,?,?,?,?,?,?,?,?,?,?)", cams)
        db.executemany("INSERT INTO footprints (geom, name, ground_z, area_m2) VALUES (?,?,?,?)", feet)
        for table, kind, gtype, z, n in (("cameras", "camera projection centres", "POINT", 1, len(cams)),
                                         ("footprints", "image footprints on the sparse cloud's median height", "POLYGON",
                                          0, len(feet))):
            xs = [struct.unpack_from("<4d", r[0], 8) for r in (cams if table == "cameras" else feet)]
            box = (min(e[0] for e in xs), min(e[2] for e in xs), max(e[1] for e in xs), max(e[3] for e in xs)) if xs \
                else (None,) * 4
            db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, description, min_x, min_y, max_x, "
                       "max_y, srs_id) VALUES (?,?,?,?,?,?,?,?,?)", (table, "features", table, kind, *box, srs_id))
            db.execute("INSERT INTO gpkg_geometry_columns VALUES (?,?,?,?,?,?)", (table, "geom", gtype, srs_id, z, 0))
        db.commit()
        db.close()
        with open(tmp, "rb") as fh:
            return fh.read()
    finally:
        os.unlink(tmp)
