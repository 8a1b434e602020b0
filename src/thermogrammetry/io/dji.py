"""DJI radiometric JPEGs (H20T, H20N, M2EA, M30T, M3T, M3TD, M4T, H30T, XT S): raw block + metadata.

What is in the file (observed on the rjpeg_samples set and consistent with ExifTool's DJI module):

* the raw thermal image, ``width x height`` little-endian uint16, split over consecutive APP3 segments
  (APP4 on the Zenmuse XT S, whose APP3 holds a 32 KiB calibration block instead);
* measurement parameters in APP4, three layouts:
  ``AA 55 12 06`` (H20T): int16 at 0x44 distance (m), 0x46 humidity (%), 0x48 emissivity (%),
  0x4a reflected temperature (0.1 °C), 0x4c ambient temperature (°C);
  ``FF D2 D1 FF "iirp"`` (M3T, M30T, H20N, M4T, H30T): float32 at 0x20 ambient (°C), 0x24 distance (m),
  0x28 emissivity, 0x2c humidity (fraction), 0x30 reflected temperature (°C);
  no magic (M2EA, ExifTool "ThermalParams2"): the same five floats at 0x00;
  other layouts (M3TD ``"hirp"``) are not decoded and say so;
* geotags and gimbal/flight attitude, RTK flag and σ in the ``drone-dji`` XMP namespace.

Temperatures.  DJI publishes no conversion from these counts to temperature (it ships a closed library, the
DJI Thermal SDK, ``libdirp``).  Without it the image is loaded as **raw counts** -- ``temperature_k`` is
``None``, ``signal_unit`` is ``"counts"`` and a note says why; geometry workflows work on the counts.  If the
user points to the SDK (``dji_sdk=`` / ``--dji-sdk`` or the environment variable
``THERMOGRAMMETRY_DJI_TSDK``), it is called through ``ctypes`` (``dirp_create_from_rjpeg``,
``dirp_set_measurement_params``, ``dirp_measure_ex``) and its °C output becomes ``temperature_k``; nothing
of the SDK is vendored.  The binding follows the SDK's public header ``dirp_api.h`` (v1.x); CI tests it
against a stand-in library with the same C interface, not against DJI's binary (not redistributable).

References
----------
.. [1] P. Harvey, ExifTool ``Image::ExifTool::DJI`` (ThermalParams, ThermalParams2), https://exiftool.org/TagNames/DJI.html
.. [2] DJI Thermal SDK v1.x, ``dirp_api.h`` (function names and structures used by :func:`_sdk_measure`).
"""

from __future__ import annotations

import ctypes
import struct
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import ConfigError, CorruptFileError, InvalidInputError, UnsupportedFormatError
from ..radiometry.measurement import MeasurementParams
from .dji_sdk import INSTALL_HINT, SDK_ENV, sdk_path
from .exif import jpeg_segments, parse_xmp, read_exif
from .thermal import Geotag, ReadOptions, ThermalImage, ThermalMetadata, register_reader

__all__ = ["parse_dji_params", "SDK_ENV"]

NO_CONVERSION_NOTE = (
    "DJI R-JPEG: raw counts only -- DJI documents no conversion of these counts to temperature; for "
    f"temperatures {INSTALL_HINT}; or keep the raw counts (--raw, products labelled as counts)"
)


def _frame_size(segments) -> tuple[int, int] | None:
    for s in segments:
        if s.marker in (0xC0, 0xC1, 0xC2) and len(s.payload) >= 5:
            h, w = struct.unpack(">HH", s.payload[1:5])
            return w, h
    return None


def parse_dji_params(app4: bytes) -> dict | None:
    """Measurement parameters from the APP4 block (see module docstring); ``None`` for unknown layouts.

    Returns keys ``ambient_c``, ``distance_m``, ``emissivity``, ``humidity`` (fraction), ``reflected_c``.
    """
    if app4[:4] == b"\xaa\x55\x12\x06" and len(app4) >= 0x4E:
        dist, rh, emis, refl, amb = struct.unpack("<hhhhh", app4[0x44:0x4E])
        out = {"distance_m": float(dist), "humidity": rh / 100.0, "emissivity": emis / 100.0,
               "reflected_c": refl / 10.0, "ambient_c": float(amb)}
    elif app4[:8] == b"\xff\xd2\xd1\xffiirp" and len(app4) >= 0x34:
        amb, dist, emis, rh, refl = struct.unpack("<5f", app4[0x20:0x34])
        out = {"ambient_c": amb, "distance_m": dist, "emissivity": emis, "humidity": rh, "reflected_c": refl}
    elif len(app4) >= 0x14 and app4[:4] != b"\xff\xd2\xd1\xff":
        amb, dist, emis, rh, refl = struct.unpack("<5f", app4[0:0x14])
        out = {"ambient_c": amb, "distance_m": dist, "emissivity": emis, "humidity": rh, "reflected_c": refl}
    else:
        return None
    ok = (0 < out["emissivity"] <= 1 and 0 <= out["humidity"] <= 1 and 0 <= out["distance_m"] <= 1e4
          and -100 < out["ambient_c"] < 200 and -100 < out["reflected_c"] < 600)
    return {k: float(v) for k, v in out.items()} if ok else None


_CHECKED: set[str] = set()


def _sdk_measure(lib_path: str, data: bytes, params: dict | None, overrides: dict, shape: tuple[int, int]) -> np.ndarray:
    """Temperatures (K) from DJI's Thermal SDK (libdirp) via ctypes (loaded by :func:`.dji_sdk.load_dji_sdk`:
    its plugins first, no ``LD_LIBRARY_PATH`` needed; checked once per path by :func:`.dji_sdk.check_dji_sdk`)."""
    from .dji_sdk import check_dji_sdk, load_dji_sdk

    if lib_path not in _CHECKED:
        check_dji_sdk(lib_path)
        _CHECKED.add(lib_path)
    lib = load_dji_sdk(lib_path)

    class Params(ctypes.Structure):  # dirp_measurement_params_t (packed floats)
        # v1 ABI: distance (m), humidity (%), emissivity, reflection (°C); later SDKs append ambient_temp (°C).
        # The spare floats keep a newer library from writing past our struct; we read the library's values
        # first, so whatever it appends is sent back unchanged.
        _pack_ = 1
        _fields_ = [("distance", ctypes.c_float), ("humidity", ctypes.c_float),
                    ("emissivity", ctypes.c_float), ("reflection", ctypes.c_float),
                    ("spare", ctypes.c_float * 8)]

    if hasattr(lib, "dirp_register_app"):  # required by SDK 1.0-1.2, a no-op later
        lib.dirp_register_app(b"DJI_TSDK")
    handle = ctypes.c_void_p()
    buf = (ctypes.c_uint8 * len(data)).from_buffer_copy(data)
    rc = lib.dirp_create_from_rjpeg(buf, ctypes.c_int32(len(data)), ctypes.byref(handle))
    if rc != 0:
        raise UnsupportedFormatError(f"DJI Thermal SDK refused the file (dirp_create_from_rjpeg returned {rc})")
    try:
        p = Params()
        rc = lib.dirp_get_measurement_params(handle, ctypes.byref(p))
        if rc != 0:
            raise UnsupportedFormatError(f"DJI Thermal SDK: dirp_get_measurement_params returned {rc}")
        if "distance_m" in overrides:
            p.distance = float(overrides["distance_m"])
        if "relative_humidity" in overrides:
            p.humidity = float(overrides["relative_humidity"]) * 100.0
        if "emissivity" in overrides:
            p.emissivity = float(overrides["emissivity"])
        if "reflected_temperature_k" in overrides:
            p.reflection = float(overrides["reflected_temperature_k"]) - 273.15
        rc = lib.dirp_set_measurement_params(handle, ctypes.byref(p))
        if rc != 0:
            raise InvalidInputError(
                f"DJI Thermal SDK refused the measurement parameters (distance {p.distance:g} m, humidity {p.humidity:g} %, "
                f"emissivity {p.emissivity:g}, reflection {p.reflection:g} °C; SDK ranges 1-25 m, 20-100 %, 0.1-1, -40-500 °C): "
                f"dirp_set_measurement_params returned {rc}"
            )
        out = np.zeros(shape, dtype=np.float32)
        rc = lib.dirp_measure_ex(handle, out.ctypes.data_as(ctypes.POINTER(ctypes.c_float)), ctypes.c_int32(out.nbytes))
        if rc != 0:
            raise UnsupportedFormatError(f"DJI Thermal SDK could not measure the file (dirp_measure_ex returned {rc})")
    finally:
        lib.dirp_destroy(handle)
    return out + np.float32(273.15)


def _read_dji(path: Path, data: bytes, opts: ReadOptions) -> Iterator[ThermalImage]:
    segs = jpeg_segments(data, path)
    size = _frame_size(segs)
    if size is None:
        raise CorruptFileError(f"{path}: DJI JPEG without a frame header (SOF0): truncated file")
    app3 = b"".join(s.payload for s in segs if s.marker == 0xE3)
    app4 = b"".join(s.payload for s in segs if s.marker == 0xE4)
    # the visible JPEG may be an upscaled preview of the sensor (M30T: 1280x1024 preview of a 640x512 sensor)
    w, h = size
    for cand in ((w, h), (w // 2, h // 2)):
        if len(app3) == 2 * cand[0] * cand[1] or len(app4) == 2 * cand[0] * cand[1]:
            w, h = cand
            break
    need = 2 * w * h
    if len(app3) == need:
        raw_bytes, params_block = app3, app4
    elif len(app4) == need:  # Zenmuse XT S: raw in APP4
        raw_bytes, params_block = app4, b""
    elif not app3 and not app4:
        raise UnsupportedFormatError(
            f"{path}: DJI JPEG without a thermal data block (no APP3/APP4 segments): not a radiometric R-JPEG"
        )
    else:
        raise CorruptFileError(
            f"{path}: DJI thermal data segments hold {len(app3)} (APP3) / {len(app4)} (APP4) bytes; "
            f"{need} expected for a {w}x{h} uint16 image: truncated or unknown layout"
        )
    raw = np.frombuffer(raw_bytes, dtype="<u2").reshape(h, w).copy()
    exif = read_exif(data)
    xmp = parse_xmp(data[: segs[-1].offset])
    dji = parse_dji_params(params_block) if params_block else None
    notes = [NO_CONVERSION_NOTE]
    measurement = None
    if dji is not None:
        measurement = MeasurementParams(
            emissivity=dji["emissivity"], reflected_temperature_k=dji["reflected_c"] + 273.15,
            atmospheric_temperature_k=dji["ambient_c"] + 273.15, relative_humidity=dji["humidity"],
            distance_m=dji["distance_m"],
        ).override(**opts.overrides)
    else:
        notes.append("DJI measurement parameters: APP4 layout not decoded for this model")
    md = ThermalMetadata(
        make=exif.get("make", "DJI"), model=exif.get("model") or xmp.get("Model"),
        serial=exif.get("serial") or xmp.get("CameraSerialNumber"), planck=None, measurement=measurement,
        geotag=Geotag.from_sources(exif, xmp), timestamp=exif.get("timestamp"),
        focal_length_mm=exif.get("focal_length_mm"), pixel_pitch_um=exif.get("pixel_pitch_um"),
        source_path=str(path), reader="dji_rjpeg", frame_index=None, notes=notes,
        extra={"dji_params": dji, "xmp": xmp, "utc_at_exposure": xmp.get("UTCAtExposure")}, exif=exif,
    )
    sdk = sdk_path(opts.dji_sdk)
    temperature = None
    if sdk:
        temperature = _sdk_measure(sdk, data, dji, opts.overrides, (h, w))
        md.notes = [f"DJI R-JPEG: temperatures from DJI Thermal SDK {sdk}"]
    yield ThermalImage(raw, temperature, md)


def _sniff_dji(head: bytes, path: Path) -> bool:
    if not head.startswith(b"\xff\xd8") or b"FLIR\x00\x01" in head[:65536]:
        return False
    if b"DJI" not in head[:65536]:
        return False
    # at least one APP3 or APP4 segment among the leading markers
    i = 2
    while i + 4 <= len(head) and head[i] == 0xFF:
        m = head[i + 1]
        if m in (0xE3, 0xE4):
            return True
        if m in (0xDA, 0xD9):
            return False
        i += 2 + struct.unpack(">H", head[i + 2 : i + 4])[0]
    return False


register_reader("dji_rjpeg", _sniff_dji, _read_dji, priority=5,
                description="DJI R-JPEG (raw counts; temperatures with the DJI Thermal SDK)")

