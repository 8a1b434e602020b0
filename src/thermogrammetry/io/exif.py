"""JPEG segment walking, EXIF (via Pillow) and XMP (DJI ``drone-dji`` namespace) metadata.

Only what thermal readers need: the list of APPn segments (so vendor readers can collect their raw blocks),
the standard EXIF/GPS tags, and the DJI XMP pose/RTK fields.  Byte-level details are documented where they
are parsed.
"""

from __future__ import annotations

import io
import math
import re
import struct
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from ..errors import CorruptFileError, UnsupportedFormatError

__all__ = ["JpegSegment", "jpeg_segments", "read_exif", "parse_xmp", "app_payload"]

_SOI = b"\xff\xd8"


@dataclass(frozen=True)
class JpegSegment:
    """One marker segment: ``marker`` (e.g. 0xE1 for APP1), file ``offset`` of the 0xFF byte, ``payload``."""

    marker: int
    offset: int
    payload: bytes


def jpeg_segments(data: bytes, path: str | Path = "<bytes>") -> list[JpegSegment]:
    """Marker segments of a JPEG up to the first start-of-scan.

    Raises
    ------
    UnsupportedFormatError
        ``data`` does not start with the JPEG SOI marker.
    CorruptFileError
        A segment runs past the end of the file (truncated header).
    """
    if data[:2] != _SOI:
        raise UnsupportedFormatError(f"{path}: not a JPEG file (no FF D8 start-of-image marker)")
    out: list[JpegSegment] = []
    i = 2
    n = len(data)
    while i < n:
        if data[i] != 0xFF:
            raise CorruptFileError(f"{path}: JPEG marker expected at byte {i}, found 0x{data[i]:02X}")
        m = data[i + 1] if i + 1 < n else None
        if m is None:
            break
        if m == 0xFF:  # fill byte
            i += 1
            continue
        if m in (0xD8, 0x01) or 0xD0 <= m <= 0xD7:
            i += 2
            continue
        if m in (0xDA, 0xD9):
            out.append(JpegSegment(m, i, b""))
            break
        if i + 4 > n:
            raise CorruptFileError(f"{path}: truncated JPEG segment header at byte {i} (file has {n} bytes)")
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        end = i + 2 + length
        if length < 2 or end > n:
            raise CorruptFileError(
                f"{path}: JPEG segment 0x{m:02X} at byte {i} declares {length} bytes but the file ends at {n} "
                "(truncated file)"
            )
        out.append(JpegSegment(m, i, data[i + 4 : end]))
        i = end
    return out


def app_payload(segments: list[JpegSegment], marker: int, prefix: bytes | None = None) -> list[bytes]:
    """Payloads of all segments with ``marker`` (and whose payload starts with ``prefix`` if given)."""
    return [s.payload for s in segments if s.marker == marker and (prefix is None or s.payload.startswith(prefix))]


def _ratio(v) -> float | None:
    try:
        return float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def _dms(v, ref) -> float | None:
    try:
        d, m, s = (float(x) for x in v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    val = d + m / 60.0 + s / 3600.0
    if isinstance(ref, bytes):
        ref = ref.decode("ascii", "ignore")
    if isinstance(ref, str) and ref.strip().upper()[:1] in ("S", "W"):
        val = -val
    return val


def _text(v) -> str | None:
    if v is None:
        return None
    if isinstance(v, bytes):
        v = v.decode("utf-8", "ignore")
    v = str(v).strip().strip("\x00").strip()
    return v or None


def read_exif(data: bytes) -> dict[str, Any]:
    """Standard EXIF/GPS tags of an image file's bytes (JPEG or TIFF) as plain Python values.

    Keys (present only when the file has them): ``make``, ``model``, ``serial``, ``software``,
    ``timestamp`` (naive datetime from DateTimeOriginal), ``focal_length_mm``, ``pixel_pitch_um``
    (from FocalPlaneX/YResolution), ``latitude_deg``, ``longitude_deg``, ``altitude_m``,
    ``image_description``, and ``raw_exif`` / ``raw_gps`` (tag-id -> value dicts, for re-writing).
    """
    out: dict[str, Any] = {}
    try:
        _read_exif(data, out)
    except Exception as exc:  # damaged EXIF must not make the image unreadable; say what was lost
        out["exif_error"] = f"EXIF unreadable, camera/GPS tags ignored ({type(exc).__name__}: {str(exc)[:120]})"
    return out


def _read_exif(data: bytes, out: dict[str, Any]) -> None:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as img:
            exif = img.getexif()
    except Exception:  # not an image Pillow knows (e.g. only a JPEG header): there is no EXIF to read
        return
    base = dict(exif.items())
    try:
        sub = dict(exif.get_ifd(0x8769).items())
    except Exception as exc:
        sub = {}
        out["exif_error"] = f"EXIF sub-IFD unreadable ({type(exc).__name__}): focal length, serial, time ignored"
    try:
        gps = dict(exif.get_ifd(0x8825).items())
    except Exception as exc:
        gps = {}
        out["exif_error"] = f"EXIF GPS IFD unreadable ({type(exc).__name__}): position ignored"
    out["raw_exif"] = {**base, **sub}
    out["raw_gps"] = gps
    for key, tag in (("make", 271), ("model", 272), ("software", 305), ("image_description", 270)):
        t = _text(base.get(tag))
        if t:
            out[key] = t
    serial = _text(sub.get(0xA431)) or _text(base.get(0xA431))
    if serial:
        out["serial"] = serial
    dt = _text(sub.get(36867)) or _text(base.get(306))
    if dt:
        try:
            out["timestamp"] = datetime.strptime(dt[:19], "%Y:%m:%d %H:%M:%S")
        except ValueError:
            pass
    fl = _ratio(sub.get(37386))
    if fl and math.isfinite(fl) and fl > 0:
        out["focal_length_mm"] = fl
    # FocalPlaneXResolution (pixels per unit) + unit (2 inch, 3 cm, 4 mm, 5 um)
    fx, fy, unit = _ratio(sub.get(41486)), _ratio(sub.get(41487)), sub.get(41488)
    try:
        unit_um = {2: 25400.0, 3: 10000.0, 4: 1000.0, 5: 1.0}.get(int(unit) if unit is not None else 2)
    except (TypeError, ValueError, OverflowError):
        unit_um = None
    if fx and fx > 0 and unit_um and fx > 1.5:  # DJI writes 1 px/unit placeholders; ignore those
        px = unit_um / fx
        py = unit_um / fy if fy and fy > 0 else px
        if 1.0 <= px <= 100.0:
            out["pixel_pitch_um"] = (px, py)
    lat = _dms(gps.get(2), gps.get(1))
    lon = _dms(gps.get(4), gps.get(3))
    if lat is not None and lon is not None and not (math.isfinite(lat) and math.isfinite(lon)
                                                     and abs(lat) <= 90 and abs(lon) <= 180):
        out["exif_error"] = f"EXIF GPS position {lat}, {lon} out of range: ignored"
        lat = lon = None
    if lat is not None and lon is not None and not (lat == 0 and lon == 0):
        out["latitude_deg"], out["longitude_deg"] = lat, lon
        alt = _ratio(gps.get(6))
        if alt is not None:
            ref = gps.get(5)
            if isinstance(ref, bytes):
                ref = ref[:1] == b"\x01"
            if math.isfinite(alt):
                out["altitude_m"] = -alt if ref in (1, True) else alt


_XMP_START = b"<x:xmpmeta"
_XMP_END = b"</x:xmpmeta>"


def parse_xmp(data: bytes) -> dict[str, str]:
    """Flat ``{local-name: value}`` of the XMP packet in ``data`` (attributes and simple elements).

    DJI writes e.g. ``drone-dji:GimbalYawDegree="-78.10"``, ``drone-dji:RtkFlag="50"``; both attribute
    and element syntax are read.  Namespaces are dropped (first occurrence wins).
    """
    i = data.find(_XMP_START)
    if i < 0:
        return {}
    j = data.find(_XMP_END, i)
    packet = data[i : (j + len(_XMP_END)) if j > 0 else i + 65536].decode("utf-8", "ignore")
    out: dict[str, str] = {}
    for m in re.finditer(r'([A-Za-z][\w\-]*):([A-Za-z][\w]*)\s*=\s*"([^"]*)"', packet):
        out.setdefault(m.group(2), m.group(3).strip())
    for m in re.finditer(r"<([A-Za-z][\w\-]*):([A-Za-z][\w]*)>([^<]*)</\1:\2>", packet):
        out.setdefault(m.group(2), m.group(3).strip())
    return out


def utc(ts: datetime | None) -> datetime | None:  # pragma: no cover - tiny helper
    return ts.replace(tzinfo=timezone.utc) if ts is not None and ts.tzinfo is None else ts
