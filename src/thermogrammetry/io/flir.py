"""FLIR radiometric files: R-JPEG (FFF in APP1), single FFF frames, SEQ and CSQ sequences.

Own parser of FLIR's FFF container (layout as documented by ExifTool's FLIR module; flyr reads only part
of it and only little-endian records, which is why it fails on the DJI XT2/XTR FLIR cores):

FFF header (0x40 bytes)
    ``0x00`` "FFF\\0" (or "AFF\\0"), ``0x04`` creator string[16], ``0x14`` int32 format version (100..299;
    its byte order decides the header's byte order), ``0x18`` int32 offset of the record directory,
    ``0x1c`` int32 number of directory entries.
Directory entry (0x20 bytes)
    ``0x00`` int16 record type (1 RawData, 0x20 CameraInfo, 0x2b GPSInfo, 0x0e EmbeddedImage ...),
    ``0x02`` subtype, ``0x04`` version, ``0x08`` index id, ``0x0c`` int32 offset (from the FFF start),
    ``0x10`` int32 length.
RawData record
    ``0x00`` int16 = 2 in the record's byte order (decides it), ``0x02`` width, ``0x04`` height,
    ``0x20`` image: PNG (16-bit, byte-swapped), TIFF, JPEG-LS (CSQ) or plain uint16 in record order.
CameraInfo record
    same byte-order test; floats at ``0x20`` emissivity, ``0x24`` object distance (m), ``0x28`` reflected
    apparent temperature (K), ``0x2c`` atmospheric temperature (K), ``0x30`` IR window temperature (K),
    ``0x34`` IR window transmission, ``0x3c`` relative humidity (fraction; > 2 means percent), ``0x58``
    PlanckR1, ``0x5c`` PlanckB, ``0x60`` PlanckF, ``0x70..0x80`` alpha1, alpha2, beta1, beta2, X;
    strings ``0xd4`` model[32], ``0xf4`` part number[16], ``0x104`` serial[16], ``0x170`` lens[32];
    ``0x1b4`` float field of view (deg); ``0x308`` int32 PlanckO, ``0x30c`` float PlanckR2;
    ``0x384`` int32 unix time, ``0x388`` int32 ms (low 16 bits), ``0x38c`` int16 time-zone minutes.
GPSInfo record
    ``0x00`` int32 valid flag, ``0x08``/``0x0a`` latitude/longitude ref, ``0x10``/``0x18`` float64
    latitude/longitude (deg), ``0x20`` float32 altitude (m).

SEQ files are FFF frames back to back; CSQ files the same with JPEG-LS compressed raw data
(decoded with ``imagecodecs.jpegls_decode``).

References
----------
.. [1] P. Harvey, ExifTool ``Image::ExifTool::FLIR`` (FLIR.pm), https://exiftool.org/TagNames/FLIR.html
.. [2] G. J. Tattersall, Thermimage R package v4.1.3 (SEQ/CSQ frame layout notes).
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..errors import CorruptFileError, InvalidInputError, UnsupportedFormatError
from ..radiometry.atmosphere import AtmosphericCoefficients
from ..radiometry.measurement import MeasurementParams
from ..radiometry.planck import PlanckConstants
from .exif import app_payload, jpeg_segments, parse_xmp, read_exif
from .thermal import Geotag, ReadOptions, ThermalImage, ThermalMetadata, register_reader

__all__ = ["FFFFrame", "parse_fff", "iter_fff_frames", "flir_app1_fff"]

REC_RAW = 0x01
REC_CAMERA_INFO = 0x20
REC_GPS = 0x2B


@dataclass
class FFFFrame:
    """Decoded content of one FFF frame."""

    raw_counts: np.ndarray  # (H, W) uint16
    camera_info: dict
    gps: dict
    raw_format: str  # "png", "tiff", "jpeg-ls", "uint16"
    offset: int  # byte offset of the frame in its container
    length: int  # bytes used by the frame
    index: int = 0  # position in the sequence (damaged frames counted)


def _endian_of_header(buf: bytes) -> str | None:
    if len(buf) < 0x20 or buf[:4] not in (b"FFF\x00", b"AFF\x00"):
        return None
    for e in (">", "<"):
        ver = struct.unpack(e + "I", buf[0x14:0x18])[0]
        if 100 <= ver < 300:  # FLIR: 100..1xx; Workswell WIRIS writes 211
            return e
    return None


def _record_endian(rec: bytes) -> str:
    # the first int16 of RawData/CameraInfo records is 2 in the record's own byte order
    return ">" if rec[:2] == b"\x00\x02" else "<"


def _fff_records(buf: bytes, base: int, where: str) -> tuple[dict[int, tuple[int, int]], int]:
    e = _endian_of_header(buf[base : base + 0x40])
    if e is None:
        raise UnsupportedFormatError(f"{where}: no FLIR FFF header at byte {base}")
    dir_off, n = struct.unpack(e + "II", buf[base + 0x18 : base + 0x20])
    if n == 0 or n > 4096:
        raise CorruptFileError(f"{where}: FFF header at byte {base} lists {n} records; expected 1..4096")
    end_dir = base + dir_off + 32 * n
    if end_dir > len(buf):
        raise CorruptFileError(
            f"{where}: FFF record directory at byte {base + dir_off} ({n} entries) runs past the end of the data "
            f"({len(buf)} bytes): truncated file"
        )
    recs: dict[int, tuple[int, int]] = {}
    frame_end = end_dir
    for k in range(n):
        p = base + dir_off + 32 * k
        rtype = struct.unpack(e + "H", buf[p : p + 2])[0]
        if rtype == 0:
            continue
        off, length = struct.unpack(e + "II", buf[p + 0x0C : p + 0x14])
        recs.setdefault(rtype, (base + off, length))
        frame_end = max(frame_end, base + off + length)
    return recs, frame_end


def _cstr(b: bytes) -> str | None:
    s = b.split(b"\x00", 1)[0].decode("latin-1", "ignore").strip()
    return s or None


def _parse_camera_info(rec: bytes) -> dict:
    e = _record_endian(rec)
    if len(rec) < 0x310:
        raise CorruptFileError(f"CameraInfo record has {len(rec)} bytes, expected >= 0x310")

    def f(o):
        return struct.unpack(e + "f", rec[o : o + 4])[0]

    rh = f(0x3C)
    info = {
        "emissivity": f(0x20),
        "object_distance_m": f(0x24),
        "reflected_temperature_k": f(0x28),
        "atmospheric_temperature_k": f(0x2C),
        "window_temperature_k": f(0x30),
        "window_transmission": f(0x34),
        "relative_humidity": rh / 100.0 if rh > 2 else rh,
        "planck_r1": f(0x58),
        "planck_b": f(0x5C),
        "planck_f": f(0x60),
        "alpha1": f(0x70),
        "alpha2": f(0x74),
        "beta1": f(0x78),
        "beta2": f(0x7C),
        "x": f(0x80),
        "range_max_k": f(0x90),
        "range_min_k": f(0x94),
        "model": _cstr(rec[0xD4:0xF4]),
        "part_number": _cstr(rec[0xF4:0x104]),
        "serial": _cstr(rec[0x104:0x114]),
        "software": _cstr(rec[0x114:0x124]),
        "lens": _cstr(rec[0x170:0x190]),
        "field_of_view_deg": f(0x1B4) if len(rec) >= 0x1B8 else None,
        "planck_o": struct.unpack(e + "i", rec[0x308:0x30C])[0],
        "planck_r2": f(0x30C),
    }
    if len(rec) >= 0x38E:
        secs, ms = struct.unpack(e + "II", rec[0x384:0x38C])
        tz = struct.unpack(e + "h", rec[0x38C:0x38E])[0]
        if 0 < secs < 4e9:
            # unix seconds are UTC; the int16 is the camera's time-zone offset in minutes (kept aside)
            info["timestamp"] = datetime.fromtimestamp(secs, tz=timezone.utc) + timedelta(milliseconds=ms & 0xFFFF)
            info["timezone_minutes"] = int(tz)
    return info


def _parse_gps(rec: bytes) -> dict:
    """GPSInfo record; its byte order is not flagged, so take the one giving a valid flag and sane angles."""
    if len(rec) < 0x24:
        return {}
    for e in ("<", ">"):
        valid = struct.unpack(e + "I", rec[0:4])[0]
        lat, lon = struct.unpack(e + "dd", rec[0x10:0x20])
        alt = struct.unpack(e + "f", rec[0x20:0x24])[0]
        if valid == 1 and np.isfinite(lat) and np.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180:
            break
    else:
        return {}
    if lat == 0 and lon == 0:
        return {}
    if rec[0x08:0x09] == b"S":
        lat = -abs(lat)
    if rec[0x0A:0x0B] == b"W":
        lon = -abs(lon)
    return {"latitude_deg": float(lat), "longitude_deg": float(lon),
            "altitude_m": float(alt) if np.isfinite(alt) and abs(alt) < 1e5 else None}


def _jpegls_near(stream: bytes) -> int | None:
    """NEAR parameter of a JPEG-LS stream's first scan: 0 = lossless, k = every sample within +-k counts."""
    i = 2
    while i + 4 <= len(stream) and stream[i] == 0xFF:
        marker = stream[i + 1]
        length = struct.unpack(">H", stream[i + 2 : i + 4])[0]
        if marker == 0xDA:
            ns = stream[i + 4]
            k = i + 5 + 2 * ns
            return int(stream[k]) if k < len(stream) else None
        i += 2 + length
    return None


def _decode_raw(rec: bytes, where: str) -> tuple[np.ndarray, str]:
    e = _record_endian(rec)
    if len(rec) < 0x20:
        raise CorruptFileError(f"{where}: RawData record has {len(rec)} bytes, expected >= 32")
    w, h = struct.unpack(e + "HH", rec[2:6])
    img = rec[0x20:]
    if w == 0 or h == 0 or w > 16384 or h > 16384:
        raise CorruptFileError(f"{where}: RawData declares a {w}x{h} image")
    if img.startswith(b"\x89PNG"):
        from PIL import Image

        try:
            with Image.open(io.BytesIO(img)) as im:
                a = np.array(im).astype(np.uint16)
        except Exception as exc:
            raise CorruptFileError(f"{where}: embedded raw PNG cannot be decoded ({exc}): truncated file?") from None
        a = a.byteswap()  # FLIR stores the PNG's 16-bit samples little-endian
        fmt = "png"
    elif img[:4] in (b"II*\x00", b"MM\x00*"):
        import tifffile

        try:
            a = tifffile.imread(io.BytesIO(img))
        except Exception as exc:
            raise CorruptFileError(f"{where}: embedded raw TIFF cannot be decoded ({exc}): truncated file?") from None
        fmt = "tiff"
    elif img[:2] == b"\xff\xd8":
        import imagecodecs

        if not img.rstrip(b"\x00").endswith(b"\xff\xd9"):
            # checked before decoding: CharLS needs seconds to reject a cut stream
            raise CorruptFileError(f"{where}: embedded JPEG-LS raw frame has no end-of-image marker: truncated file")

        try:
            a = imagecodecs.jpegls_decode(img)
        except Exception as exc:
            raise CorruptFileError(f"{where}: embedded JPEG-LS raw frame cannot be decoded ({exc})") from None
        fmt = f"jpeg-ls, NEAR={_jpegls_near(img)}"
    else:
        need = 2 * w * h
        if len(img) < need:
            raise CorruptFileError(
                f"{where}: raw data holds {len(img)} bytes, {need} needed for {w}x{h} uint16: truncated file"
            )
        a = np.frombuffer(img[:need], dtype=e + "u2").reshape(h, w)
        fmt = "uint16"
    a = np.ascontiguousarray(a, dtype=np.uint16)
    if a.shape != (h, w):
        raise CorruptFileError(f"{where}: raw image decodes to {a.shape[::-1]} (w x h) but the record declares {w}x{h}")
    return a, fmt


def parse_fff(buf: bytes, base: int = 0, where: str = "<bytes>") -> FFFFrame:
    """Parse the FFF frame starting at byte ``base`` of ``buf``.

    Raises
    ------
    UnsupportedFormatError
        No FFF header, or no RawData / CameraInfo record (not radiometric).
    CorruptFileError
        Records run past the end of the data or do not decode.
    """
    recs, end = _fff_records(buf, base, where)
    if REC_RAW not in recs:
        raise UnsupportedFormatError(f"{where}: FFF frame at byte {base} has no RawData record (not radiometric)")
    if REC_CAMERA_INFO not in recs:
        raise UnsupportedFormatError(
            f"{where}: FFF frame at byte {base} has no CameraInfo record (no Planck constants: not radiometric)"
        )
    for rtype in (REC_RAW, REC_CAMERA_INFO):
        off, length = recs[rtype]
        # a record may declare a few padding bytes past the end of the last frame of a sequence (seen in
        # Thermimage's SampleCSQ.csq); the decoders below detect real truncation of the image data
        if off >= len(buf) or (rtype == REC_CAMERA_INFO and off + min(length, 0x310) > len(buf)):
            raise CorruptFileError(
                f"{where}: FFF record 0x{rtype:02x} at byte {off} ({length} bytes) runs past the end of the data "
                f"({len(buf)} bytes): truncated file"
            )
    off, length = recs[REC_RAW]
    raw, fmt = _decode_raw(buf[off : off + length], where)
    off, length = recs[REC_CAMERA_INFO]
    cam_rec = buf[off : off + length]
    info = _parse_camera_info(cam_rec)
    gps: dict = {}
    if REC_GPS in recs:
        off, length = recs[REC_GPS]
        if off + length <= len(buf):
            gps = _parse_gps(buf[off : off + length])
    return FFFFrame(raw, info, gps, fmt, base, end - base)


def iter_fff_frames(buf: bytes, where: str = "<bytes>", *,
                    on_damaged: Callable[[int, str], None] | None = None) -> Iterator[FFFFrame]:
    """Frames of a SEQ/CSQ/FFF byte string in file order (frames are found by following each frame's extent
    and then searching for the next valid FFF header).  Each frame's :attr:`FFFFrame.index` is its position
    in the sequence, counting damaged frames, so frame 4 keeps index 4 when frame 3 is damaged.

    A damaged frame in the middle of a sequence (its records do not decode, or its header is destroyed so
    that the next valid header is found past where the frame should start) raises :class:`CorruptFileError`,
    or -- with ``on_damaged(index, message)`` -- is reported there and skipped.  Frames of SEQ/CSQ files are
    contiguous; when a header is destroyed, the number of frames lost in the gap is estimated as the gap
    over the previous frame's length (at least 1).
    """
    pos = 0
    n = 0  # index of the next frame
    found = 0
    prev_len = 0

    def damaged(msg: str) -> None:
        if on_damaged is None:
            raise CorruptFileError(msg)
        on_damaged(n, msg)

    while pos < len(buf):
        k = buf.find(b"FFF\x00", pos)
        if k < 0:
            break
        if _endian_of_header(buf[k : k + 0x40]) is None:
            pos = k + 1
            continue
        try:
            recs, end = _fff_records(buf, k, where)
        except CorruptFileError as exc:
            if found == 0:
                raise
            if buf.find(b"FFF\x00", k + 4) < 0:  # the last frame: the file is cut
                raise CorruptFileError(f"{where}: frame {n} at byte {k} is truncated (file ends at {len(buf)})") from None
            damaged(f"{where}: frame {n} at byte {k} is damaged ({exc})")
            n += 1
            pos = k + 4
            continue
        if REC_RAW not in recs:
            pos = k + 4
            continue
        if found and prev_len and k - pos > 64:  # bytes where a frame should start were not a valid header
            lost = max(1, int(round((k - pos) / prev_len)))
            for _ in range(lost):
                damaged(f"{where}: frame {n} at byte {pos} is damaged (no valid FFF header where the frame should "
                        f"start; next valid frame at byte {k})")
                n += 1
        try:
            fr = parse_fff(buf, k, where)
        except (CorruptFileError, UnsupportedFormatError) as exc:
            if found == 0 and on_damaged is None:
                raise
            damaged(f"{where}: frame {n} at byte {k} is damaged ({exc})")
        else:
            fr.index = n
            yield fr
        found += 1
        n += 1
        prev_len = end - k
        pos = max(end, k + 4)
    if found == 0:
        raise UnsupportedFormatError(f"{where}: no FLIR FFF frame with raw data found")


def flir_app1_fff(segments, where: str, magic: bytes = b"FLIR\x00") -> bytes:
    """Reassemble the FFF blob split over the APP1 segments (``FLIR\\0`` + 0x01 + part + last; Workswell
    uses ``WORK\\0`` with the same layout)."""
    parts: dict[int, bytes] = {}
    last = None
    payloads = [p for p in app_payload(segments, 0xE1, magic) if len(p) >= 8]
    if len(payloads) > 1 and all(p[6] == 0 and p[7] == 0 for p in payloads):
        return b"".join(p[8:] for p in payloads)  # Workswell: no part numbers, segments in file order
    for p in payloads:
        idx, tot = p[6], p[7]
        last = tot if last is None else last
        parts.setdefault(idx, p[8:])
    if last is None:
        raise UnsupportedFormatError(f"{where}: JPEG without FLIR APP1 segments (not a FLIR radiometric JPEG)")
    missing = [i for i in range(last + 1) if i not in parts]
    if missing:
        raise CorruptFileError(f"{where}: FLIR APP1 segment(s) {missing} of 0..{last} missing: truncated file")
    return b"".join(parts[i] for i in range(last + 1))


# --------------------------------------------------------------------------------------------------------
# ThermalImage construction

def _metadata_from_frame(fr: FFFFrame, path: Path, reader: str, frame_index: int | None, exif: dict, xmp: dict) -> ThermalMetadata:
    ci = fr.camera_info
    notes = [f"FLIR FFF raw data ({fr.raw_format}); temperatures from the full FLIR measurement equation"]
    try:
        planck: PlanckConstants | None = PlanckConstants(ci["planck_r1"], ci["planck_r2"], ci["planck_b"], ci["planck_f"], ci["planck_o"])
    except InvalidInputError:
        planck = None
        notes = [f"FFF container without a Planck calibration (R1={ci['planck_r1']:g}, R2={ci['planck_r2']:g}, "
                 f"B={ci['planck_b']:g}): raw counts only -- the file does not say how to convert them to temperature"]
    try:
        coeffs = AtmosphericCoefficients(ci["alpha1"], ci["alpha2"], ci["beta1"], ci["beta2"], ci["x"])
    except InvalidInputError:
        coeffs = AtmosphericCoefficients()
    if ci["alpha1"] == 0 and ci["alpha2"] == 0 and ci["x"] == 0:
        coeffs = AtmosphericCoefficients()
    params = MeasurementParams(
        emissivity=float(ci["emissivity"]) if 0 < ci["emissivity"] <= 1 else 1.0,
        reflected_temperature_k=float(ci["reflected_temperature_k"]),
        atmospheric_temperature_k=float(ci["atmospheric_temperature_k"]),
        relative_humidity=float(min(max(ci["relative_humidity"], 0.0), 1.0)),
        distance_m=float(max(ci["object_distance_m"], 0.0)),
        window_temperature_k=float(ci["window_temperature_k"]),
        window_transmission=float(ci["window_transmission"]) if 0 < ci["window_transmission"] <= 1 else 1.0,
        coefficients=coeffs,
    )
    geotag = Geotag.from_sources(exif, xmp, fr.gps)
    make = exif.get("make") or "FLIR Systems"
    model = ci.get("model") or exif.get("model")
    return ThermalMetadata(
        make=make,
        model=model,
        serial=ci.get("serial") or exif.get("serial"),
        planck=planck,
        measurement=params,
        geotag=geotag,
        timestamp=exif.get("timestamp") or ci.get("timestamp"),
        focal_length_mm=exif.get("focal_length_mm"),
        pixel_pitch_um=exif.get("pixel_pitch_um"),
        source_path=str(path),
        reader=reader,
        frame_index=frame_index,
        notes=notes,
        extra={k: v for k, v in ci.items() if k in ("lens", "part_number", "software", "field_of_view_deg", "range_min_k", "range_max_k")},
        exif=exif,
    )


def _read_app1_fff(path: Path, data: bytes, opts: ReadOptions, magic: bytes, reader: str) -> Iterator[ThermalImage]:
    segs = jpeg_segments(data, path)
    fff = flir_app1_fff(segs, str(path), magic)
    fr = parse_fff(fff, 0, str(path))
    exif = read_exif(data)
    xmp = parse_xmp(data[: segs[-1].offset] if segs else data)
    md = _metadata_from_frame(fr, path, reader, None, exif, xmp)
    if exif.get("make"):
        md.make = exif["make"]
    yield ThermalImage.from_raw(fr.raw_counts, md, opts)


def _read_flir_jpeg(path: Path, data: bytes, opts: ReadOptions) -> Iterator[ThermalImage]:
    return _read_app1_fff(path, data, opts, b"FLIR\x00", "flir_rjpeg")


def _read_workswell_jpeg(path: Path, data: bytes, opts: ReadOptions) -> Iterator[ThermalImage]:
    return _read_app1_fff(path, data, opts, b"WORK\x00", "workswell_rjpeg")


def _read_fff(path: Path, data: bytes, opts: ReadOptions) -> Iterator[ThermalImage]:
    name = {".seq": "flir_seq", ".csq": "flir_csq"}.get(path.suffix.lower(), "flir_fff")
    def on_damaged(i: int, msg: str) -> None:
        if opts.frames is not None and i not in opts.frames:
            return  # a frame nobody asked for
        if opts.on_damaged is None:
            raise CorruptFileError(msg)
        opts.on_damaged(i, msg)

    for fr in iter_fff_frames(data, str(path), on_damaged=on_damaged):
        i = fr.index
        if opts.frames is not None and i not in opts.frames:
            continue
        md = _metadata_from_frame(fr, path, name, i, {}, {})
        yield ThermalImage.from_raw(fr.raw_counts, md, opts)


def _sniff_flir_jpeg(head: bytes, path: Path) -> bool:
    if not head.startswith(b"\xff\xd8"):
        return False
    k = head.find(b"FLIR\x00\x01")
    return k >= 4 and head[k - 4 : k - 2] == b"\xff\xe1"


def _sniff_workswell_jpeg(head: bytes, path: Path) -> bool:
    if not head.startswith(b"\xff\xd8"):
        return False
    k = head.find(b"WORK\x00\x01")
    return k >= 4 and head[k - 4 : k - 2] == b"\xff\xe1"


def _sniff_fff(head: bytes, path: Path) -> bool:
    return _endian_of_header(head[:0x40]) is not None


register_reader("flir_rjpeg", _sniff_flir_jpeg, _read_flir_jpeg, priority=10,
                description="FLIR radiometric JPEG (FFF in APP1), incl. DJI XT2/XTR FLIR cores")
register_reader("workswell_rjpeg", _sniff_workswell_jpeg, _read_workswell_jpeg, priority=10,
                description="Workswell WIRIS radiometric JPEG (FFF-like container in APP1; raw counts)")
register_reader("flir_fff", _sniff_fff, _read_fff, priority=10,
                description="FLIR FFF frame, SEQ sequence, CSQ sequence (JPEG-LS)")
