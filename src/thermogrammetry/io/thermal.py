"""The thermal image object and the reader registry.

:class:`ThermalImage` keeps the raw sensor signal (``raw_counts``), the temperatures derived from it
(``temperature_k``, float32 kelvin, or ``None`` when no documented conversion exists) and the metadata that
produced them, so every temperature can be traced and recomputed with other parameters
(:meth:`ThermalImage.recompute`, per image or per pixel).  Raw counts are never presented as degrees:
``signal_unit`` says what :meth:`ThermalImage.signal` returns.

Readers register themselves with a *sniffing* function that looks at the first bytes of a file (and its
name); :func:`read_thermal` picks the first reader, by priority, whose sniffer accepts the file.  No vendor
if/elif chain: adding a format is one :func:`register_reader` call in its own module.
"""

from __future__ import annotations

import dataclasses
import mmap
import struct
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ..enums import StrChoice
from ..errors import (ConfigError, CorruptFileError, DataFileError, ImageTooLargeError, InvalidInputError, ShapeError,
                      UnsupportedFormatError)
from ..radiometry.measurement import MeasurementParams, object_temperature_from_raw
from ..radiometry.planck import PlanckConstants

__all__ = [
    "SignalUnit",
    "Geotag",
    "ThermalMetadata",
    "ThermalImage",
    "ReadOptions",
    "ReaderSpec",
    "register_reader",
    "registered_readers",
    "sniff_reader",
    "read_thermal",
    "iter_thermal",
]


class SignalUnit(StrChoice):
    """What :meth:`ThermalImage.signal` holds."""

    KELVIN = "K"
    COUNTS = "counts"


def _f(v) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


@dataclass(frozen=True)
class Geotag:
    """Position and attitude at exposure (all optional).

    Angles in degrees as the vendors write them (DJI XMP: gimbal/flight roll, pitch, yaw; pitch -90 = nadir).
    ``rtk_flag``: DJI's RtkFlag (50 = fixed, 34 = float, 16 = single); ``rtk_std_m``: (lon, lat, height) σ.
    """

    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_m: float | None = None
    relative_altitude_m: float | None = None
    gimbal_roll_deg: float | None = None
    gimbal_pitch_deg: float | None = None
    gimbal_yaw_deg: float | None = None
    flight_roll_deg: float | None = None
    flight_pitch_deg: float | None = None
    flight_yaw_deg: float | None = None
    rtk_flag: int | None = None
    rtk_std_m: tuple[float, float, float] | None = None

    @property
    def has_position(self) -> bool:
        return self.latitude_deg is not None and self.longitude_deg is not None

    @classmethod
    def from_sources(cls, exif: dict, xmp: dict, fff_gps: dict | None = None) -> "Geotag":
        """Combine EXIF GPS, DJI XMP (``drone-dji``) and a FLIR FFF GPS record (EXIF wins for position)."""
        fff_gps = fff_gps or {}
        lat = exif.get("latitude_deg", fff_gps.get("latitude_deg"))
        lon = exif.get("longitude_deg", fff_gps.get("longitude_deg"))
        alt = _f(xmp.get("AbsoluteAltitude"))
        if alt is None:
            alt = exif.get("altitude_m", fff_gps.get("altitude_m"))
        if lat is None and _f(xmp.get("GpsLatitude")) is not None:
            lat, lon = _f(xmp.get("GpsLatitude")), _f(xmp.get("GpsLongitude") or xmp.get("GpsLongtitude"))
        rtk = None
        if xmp.get("RtkFlag") is not None:
            try:
                rtk = int(float(xmp["RtkFlag"]))
            except ValueError:
                rtk = None
        std = None
        if all(_f(xmp.get(k)) is not None for k in ("RtkStdLon", "RtkStdLat", "RtkStdHgt")):
            std = (_f(xmp["RtkStdLon"]), _f(xmp["RtkStdLat"]), _f(xmp["RtkStdHgt"]))
        return cls(
            latitude_deg=lat,
            longitude_deg=lon,
            altitude_m=alt,
            relative_altitude_m=_f(xmp.get("RelativeAltitude")),
            gimbal_roll_deg=_f(xmp.get("GimbalRollDegree")),
            gimbal_pitch_deg=_f(xmp.get("GimbalPitchDegree")),
            gimbal_yaw_deg=_f(xmp.get("GimbalYawDegree")),
            flight_roll_deg=_f(xmp.get("FlightRollDegree")),
            flight_pitch_deg=_f(xmp.get("FlightPitchDegree")),
            flight_yaw_deg=_f(xmp.get("FlightYawDegree")),
            rtk_flag=rtk,
            rtk_std_m=std,
        )


@dataclass
class ThermalMetadata:
    """Everything known about how an image's values were produced (all fields optional).

    ``planck`` + ``measurement`` are what turn ``raw_counts`` into ``temperature_k``; ``notes`` says in
    plain words what the reader did (e.g. "raw counts only: no documented conversion").
    """

    make: str | None = None
    model: str | None = None
    serial: str | None = None
    planck: PlanckConstants | None = None
    measurement: MeasurementParams | None = None
    geotag: Geotag = field(default_factory=Geotag)
    timestamp: datetime | None = None
    focal_length_mm: float | None = None
    pixel_pitch_um: tuple[float, float] | None = None
    source_path: str | None = None
    reader: str | None = None
    frame_index: int | None = None
    notes: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    exif: dict[str, Any] = field(default_factory=dict, repr=False)

    # convenience views of the measurement parameters (names of the issue / FLIR tags)
    @property
    def emissivity(self):
        return None if self.measurement is None else self.measurement.emissivity

    @property
    def object_distance_m(self):
        return None if self.measurement is None else self.measurement.distance_m

    @property
    def relative_humidity(self):
        return None if self.measurement is None else self.measurement.relative_humidity

    @property
    def reflected_temperature_k(self):
        return None if self.measurement is None else self.measurement.reflected_temperature_k

    @property
    def atmospheric_temperature_k(self):
        return None if self.measurement is None else self.measurement.atmospheric_temperature_k

    def describe(self) -> str:
        who = " ".join(x for x in (self.make, self.model) if x) or "unknown camera"
        src = self.source_path or "<memory>"
        fr = f" frame {self.frame_index}" if self.frame_index is not None else ""
        return f"{src}{fr} ({who}, reader {self.reader})"


@dataclass(frozen=True)
class ReadOptions:
    """Options every reader receives (unknown keys are refused by :func:`read_thermal`).

    Attributes
    ----------
    overrides : dict
        Measurement-parameter overrides (names of :class:`MeasurementParams`: ``emissivity``,
        ``distance_m``, ``relative_humidity``, ``reflected_temperature_k``, ``atmospheric_temperature_k``, ...);
        scalars or per-pixel arrays.
    frames : set of int or None
        Frame indices to read from a sequence (None: all).
    unit : "K" | "C" | None
        Declared unit of a temperature matrix (CSV/NPY) or float TIFF without its own unit tag.
    scale, offset : float or None
        Declared linear mapping ``value = counts * scale + offset`` (in ``unit``) for 16-bit TIFFs
        that do not carry one.
    dji_sdk : str or None
        Path of DJI's Thermal SDK library ``libdirp.so``/``libdirp.dll`` (or env ``THERMOGRAMMETRY_DJI_TSDK``).
    on_damaged : callable or None
        ``on_damaged(frame_index, message)`` for a damaged frame of a sequence, which is then skipped (the
        following frames keep their own indices); None: a damaged frame raises :class:`CorruptFileError`.
    """

    overrides: dict = field(default_factory=dict)
    frames: frozenset[int] | None = None
    unit: str | None = None
    scale: float | None = None
    offset: float | None = None
    dji_sdk: str | None = None
    on_damaged: Callable[[int, str], None] | None = None


@dataclass
class ThermalImage:
    """One thermal frame: raw signal, temperatures (kelvin) and the metadata that links them.

    Attributes
    ----------
    raw_counts : ndarray (H, W) uint16 or None
        The sensor's raw signal, when the file has it.
    temperature_k : ndarray (H, W) float32 or None
        Object temperatures in kelvin; ``None`` when only counts are known (then ``signal_unit`` is
        ``"counts"``).  NaN marks pixels without a valid temperature.
    metadata : ThermalMetadata
    """

    raw_counts: np.ndarray | None
    temperature_k: np.ndarray | None
    metadata: ThermalMetadata

    def __post_init__(self) -> None:
        if self.raw_counts is None and self.temperature_k is None:
            raise ConfigError("ThermalImage needs raw_counts or temperature_k (both are None)")
        if self.temperature_k is not None:
            self.temperature_k = np.asarray(self.temperature_k, dtype=np.float32)
        if self.raw_counts is not None and self.temperature_k is not None and self.raw_counts.shape != self.temperature_k.shape:
            raise ConfigError(
                f"raw_counts shape {self.raw_counts.shape} differs from temperature_k shape {self.temperature_k.shape}"
            )

    def __repr__(self) -> str:
        md = self.metadata
        rng = ""
        if self.temperature_k is not None and np.any(np.isfinite(self.temperature_k)):
            rng = f", {float(np.nanmin(self.temperature_k)):.2f}..{float(np.nanmax(self.temperature_k)):.2f} K"
        elif self.raw_counts is not None:
            rng = f", counts {int(self.raw_counts.min())}..{int(self.raw_counts.max())}"
        return f"ThermalImage({self.width}x{self.height}, {self.signal_unit.value}{rng}, {md.describe()})"

    @property
    def is_temperature(self) -> bool:
        """True when ``temperature_k`` is available."""
        return self.temperature_k is not None

    @property
    def signal_unit(self) -> SignalUnit:
        return SignalUnit.KELVIN if self.is_temperature else SignalUnit.COUNTS

    @property
    def shape(self) -> tuple[int, int]:
        a = self.temperature_k if self.temperature_k is not None else self.raw_counts
        return tuple(int(s) for s in a.shape)  # type: ignore[return-value]

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def height(self) -> int:
        return self.shape[0]

    def signal(self) -> np.ndarray:
        """Temperatures in kelvin when known, else the raw counts (check :attr:`signal_unit`).

        Geometry workflows (features, matching) use this: they work on either."""
        return self.temperature_k if self.temperature_k is not None else self.raw_counts  # type: ignore[return-value]

    @property
    def temperature_c(self) -> np.ndarray:
        """°C view (edge use only); raises when only raw counts are known."""
        return self.require_temperature() - np.float32(273.15)

    def require_temperature(self) -> np.ndarray:
        if self.temperature_k is None:
            why = "; ".join(self.metadata.notes) or "no conversion to temperature"
            raise UnsupportedFormatError(f"{self.metadata.describe()}: raw counts only, no temperatures ({why})")
        return self.temperature_k

    def recompute(self, **overrides) -> "ThermalImage":
        """Temperatures recomputed from ``raw_counts`` with measurement parameters overridden.

        Keyword arguments are :class:`MeasurementParams` fields (``emissivity``, ``distance_m``,
        ``relative_humidity``, ``reflected_temperature_k``, ``atmospheric_temperature_k``,
        ``window_temperature_k``, ``window_transmission``, ``coefficients``); each a scalar or an (H, W)
        per-pixel map.  ``None`` values keep the file's value.  Returns a new image; metadata records the
        parameters used.
        """
        md = self.metadata
        if self.raw_counts is None or md.planck is None:
            raise UnsupportedFormatError(
                f"{md.describe()}: cannot recompute temperatures: "
                + ("no raw counts" if self.raw_counts is None else "no Planck calibration in the file")
            )
        for k, v in overrides.items():
            a = np.asarray(v) if v is not None and not hasattr(v, "alpha1") else None
            if a is not None and a.ndim > 0:
                try:
                    np.broadcast_shapes(a.shape, self.raw_counts.shape)
                except ValueError:
                    raise ShapeError(
                        f"{k}: per-pixel map of shape {a.shape} does not fit the image {self.raw_counts.shape} "
                        f"({md.describe()}); expected a scalar or an (H, W) array"
                    ) from None
        params = (md.measurement or MeasurementParams()).override(**overrides)
        t = object_temperature_from_raw(self.raw_counts, md.planck, params).astype(np.float32)
        new_md = dataclasses.replace(md, measurement=params, notes=list(md.notes))
        if any(v is not None for v in overrides.values()):
            new_md.notes.append("measurement parameters overridden: " + ", ".join(sorted(k for k, v in overrides.items() if v is not None)))
        return ThermalImage(self.raw_counts, t, new_md)

    def correct_directional(self, angle_rad, emissivity_model, *, distance_m=None, max_angle_deg: float | None = None,
                            **overrides) -> "ThermalImage":
        """Per-pixel viewing-angle correction: temperatures with ``emissivity = emissivity_model(angle)``.

        Parameters
        ----------
        angle_rad : (H, W) array or scalar
            Angle between surface normal and viewing ray (radians); NaN where no surface is known.
        emissivity_model : callable
            e.g. :class:`~thermogrammetry.radiometry.FresnelEmissivity`,
            :class:`~thermogrammetry.radiometry.TabulatedEmissivity`, :class:`~thermogrammetry.radiometry.CosineEmissivity`.
        distance_m : (H, W) array or scalar, optional
            Camera-to-surface distance per pixel (atmospheric transmission over the real path).
        max_angle_deg : float, optional
            Refuse angles beyond this (default :data:`~thermogrammetry.radiometry.DEFAULT_MAX_ANGLE_DEG`).
        **overrides
            Other measurement parameters (reflected/atmospheric temperature, humidity, ...).
        """
        from ..radiometry.directional import DEFAULT_MAX_ANGLE_DEG, corrected_temperature

        md = self.metadata
        if self.raw_counts is None or md.planck is None:
            raise UnsupportedFormatError(
                f"{md.describe()}: directional correction needs raw counts and a Planck calibration; for a temperature "
                "image use radiometry.corrected_temperature_from_apparent with a signal model"
            )
        params = (md.measurement or MeasurementParams()).override(**overrides)
        t = corrected_temperature(self.raw_counts, md.planck, params, angle_rad, emissivity_model, distance_m=distance_m,
                                  max_angle_deg=DEFAULT_MAX_ANGLE_DEG if max_angle_deg is None else max_angle_deg)
        new_md = dataclasses.replace(md, measurement=params, notes=list(md.notes) + [
            f"directional correction: emissivity from {type(emissivity_model).__name__} per pixel"
            + (", per-pixel distance" if distance_m is not None else "")])
        return ThermalImage(self.raw_counts, t.astype(np.float32), new_md)

    @classmethod
    def from_raw(cls, raw_counts: np.ndarray, metadata: ThermalMetadata, opts: ReadOptions | None = None) -> "ThermalImage":
        """Build an image from raw counts; temperatures computed when the metadata has a calibration."""
        img = cls(raw_counts, None, metadata)
        if metadata.planck is not None:
            img = img.recompute(**((opts.overrides if opts else None) or {}))
        return img


# ------------------------------------------------------------------------------------------------ registry

Sniffer = Callable[[bytes, Path], bool]
Reader = Callable[[Path, bytes, ReadOptions], Iterator[ThermalImage]]


@dataclass(frozen=True)
class ReaderSpec:
    name: str
    sniff: Sniffer
    read: Reader
    priority: int = 0
    description: str = ""


_READERS: dict[str, ReaderSpec] = {}
_SNIFF_BYTES = 1 << 18  # 256 KiB: enough to see every JPEG APPn marker header of the formats we know


def register_reader(name: str, sniff: Sniffer, read: Reader, *, priority: int = 0, description: str = "") -> None:
    """Register a reader; higher ``priority`` is asked first (ties: registration order)."""
    _READERS[name] = ReaderSpec(name, sniff, read, priority, description)


def _load_builtin() -> None:
    from . import dji, flir, matrix, tiff  # noqa: F401  (each registers its readers on import)


def registered_readers() -> list[ReaderSpec]:
    _load_builtin()
    return sorted(_READERS.values(), key=lambda r: -r.priority)


def sniff_reader(path: str | Path, head: bytes | None = None) -> ReaderSpec:
    """The reader that accepts ``path`` (first by priority), or :class:`UnsupportedFormatError`."""
    p = Path(path)
    if head is None:
        with open(p, "rb") as fh:
            head = fh.read(_SNIFF_BYTES)
    for spec in registered_readers():
        try:
            if spec.sniff(head, p):
                return spec
        except Exception:  # a sniffer must never make reading fail; treat as "not mine"
            continue
    kinds = ", ".join(r.name for r in registered_readers())
    if not head:
        what = "empty file"
    elif head.startswith(b"\xff\xd8"):
        if len(head) < _SNIFF_BYTES:  # the whole file is in ``head``: say so if it is a cut JPEG
            from .exif import jpeg_segments

            jpeg_segments(head, p)  # raises CorruptFileError naming the truncation
        what = ("a JPEG without radiometric data: no FLIR/Workswell FFF block in APP1, no DJI thermal block in "
                "APP3/APP4 -- an ordinary visible or palette-rendered image")
    elif head[:4] in (b"II*\x00", b"MM\x00*"):
        what = "a TIFF no reader accepts"
    else:
        what = f"unknown content, first bytes {head[:8]!r}"
    raise UnsupportedFormatError(f"{p}: not a radiometric thermal file: {what} (readers: {kinds})")


def _options(frames, unit, scale, offset, dji_sdk, overrides, on_damaged=None) -> ReadOptions:
    names = set(MeasurementParams.field_names())
    unknown = sorted(k for k in overrides if k not in names)
    if unknown:
        raise ConfigError(f"unknown option(s) {unknown}; measurement overrides are {sorted(names)}")
    if unit is not None and str(unit).upper() not in ("K", "C"):
        raise ConfigError(f"unit={unit!r}: expected 'K' or 'C'")
    for k, v in overrides.items():  # a scalar NaN/inf would silently give an all-NaN image
        if v is not None and not hasattr(v, "alpha1") and np.ndim(v) == 0 and not np.isfinite(float(v)):
            raise ConfigError(f"{k}={v!r}: expected a finite number")
    for k, v in (("scale", scale), ("offset", offset)):
        if v is not None and not np.isfinite(float(v)):
            raise ConfigError(f"{k}={v!r}: expected a finite number")
    if scale is not None and float(scale) == 0:
        raise ConfigError("scale=0: expected a non-zero count->temperature step")
    return ReadOptions(
        overrides={k: v for k, v in overrides.items() if v is not None},
        frames=None if frames is None else frozenset(int(f) for f in frames),
        unit=None if unit is None else str(unit).upper(),
        scale=scale,
        offset=offset,
        dji_sdk=dji_sdk,
        on_damaged=on_damaged,
    )


def iter_thermal(
    path: str | Path,
    *,
    frames: Sequence[int] | None = None,
    unit: str | None = None,
    scale: float | None = None,
    offset: float | None = None,
    dji_sdk: str | None = None,
    on_damaged: Callable[[int, str], None] | None = None,
    **overrides,
) -> Iterator[ThermalImage]:
    """Every frame of a thermal file (one for images, many for SEQ/CSQ), see :func:`read_thermal`.

    ``on_damaged(frame_index, message)``: report a damaged sequence frame and go on with the next (see
    :class:`ReadOptions`); without it a damaged frame raises :class:`CorruptFileError`."""
    p = Path(path)
    opts = _options(frames, unit, scale, offset, dji_sdk, overrides, on_damaged)
    # memory-mapped, so a multi-gigabyte SEQ/CSQ recording is paged in frame by frame, not loaded whole
    try:
        fh = open(p, "rb")
    except OSError as exc:
        raise DataFileError(f"{p}: cannot read file ({exc.strerror or exc})") from None
    with fh:
        try:
            data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except (ValueError, OSError):  # empty file (cannot be mapped) or a stream
            data = fh.read()
        try:
            spec = sniff_reader(p, data[:_SNIFF_BYTES])
            yield from read_with(spec, p, data, opts)
        finally:
            if isinstance(data, mmap.mmap):
                try:
                    data.close()
                except BufferError:  # a reader kept a view; the map is released with it
                    pass


def read_with(spec: ReaderSpec, p: Path, data, opts: ReadOptions) -> Iterator[ThermalImage]:
    """Frames of ``data`` (the bytes of ``p``) decoded by ``spec``, with decoder errors mapped to our exception
    tree (:class:`CorruptFileError`, :class:`ImageTooLargeError` for ``MemoryError``).  Used by
    :func:`iter_thermal` and by the fuzz harnesses (``fuzz/``)."""
    try:
        for k, img in enumerate(spec.read(p, data, opts)):
            idx = img.metadata.frame_index if img.metadata.frame_index is not None else k
            bad_exif = (img.metadata.exif or {}).get("exif_error")
            if bad_exif and bad_exif not in img.metadata.notes:
                img.metadata.notes.append(bad_exif)
            if opts.frames is None or idx in opts.frames:
                yield img
    except (DataFileError, InvalidInputError):  # our own errors (incl. ConfigError, ShapeError) pass unchanged
        raise
    except MemoryError:
        raise ImageTooLargeError(
            f"{p}: not enough memory to decode this {spec.name} file (declared sizes too large for this "
            "machine; a damaged header?)") from None
    except (ValueError, IndexError, KeyError, EOFError, OSError, TypeError, OverflowError, ZeroDivisionError,
            struct.error, RecursionError) as exc:  # decoding library errors on bad bytes
        raise CorruptFileError(f"{p}: {spec.name} reader failed: {type(exc).__name__}: {exc}") from None


def read_thermal(
    path: str | Path,
    *,
    frame: int = 0,
    unit: str | None = None,
    scale: float | None = None,
    offset: float | None = None,
    dji_sdk: str | None = None,
    **overrides,
) -> ThermalImage:
    """Read one thermal frame (``frame`` of a sequence) from any registered format.

    Parameters
    ----------
    path : str or Path
    frame : int
        Frame index for SEQ/CSQ sequences (0 for single images).
    unit, scale, offset, dji_sdk :
        See :class:`ReadOptions`.
    **overrides :
        Measurement parameters replacing the file's (``emissivity=0.98``, ``distance_m=dist_map``, ...).

    Raises
    ------
    UnsupportedFormatError
        No reader accepts the file, or it is not radiometric.
    CorruptFileError
        The file claims a known format but is truncated or inconsistent.
    """
    for img in iter_thermal(path, frames=[frame], unit=unit, scale=scale, offset=offset, dji_sdk=dji_sdk, **overrides):
        return img
    raise UnsupportedFormatError(f"{path}: has no frame {frame}")
