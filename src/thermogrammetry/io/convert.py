"""Batch conversion of radiometric thermal files to temperature TIFFs (the library side of
``thermogrammetry convert``).

One output TIFF per image or sequence frame (``<stem>.tif``, ``<stem>_f00003.tif`` for frames, the number
being the frame's own index even when an earlier frame is damaged), float32 in K or °C or 16-bit with GDAL
scale/offset, with EXIF/GPS/XMP kept (:func:`~.tiff.write_temperature_tiff`).

* A file that cannot be converted (unknown format, truncated, raw counts only, every pixel invalid) is
  recorded as a failure with its reason and the batch goes on; a damaged sequence frame is reported and the
  other frames are converted.
* The outputs are written as a set (:class:`~thermogrammetry._atomic.OutputSet`): into a staging folder
  beside OUT, moved into OUT at the end with ``convert-manifest.json`` written last; an interrupted run
  leaves OUT absent or as it was.
* 16-bit outputs share one scale/offset across the batch (from ``range_k`` or from all inputs, which then
  are decoded twice), so codes compare across a flight.
* ``raw=True`` writes the raw counts of every input that has them as uint16 TIFFs labelled as counts.
* ``references``: an empirical raw->temperature mapping from in-scene references
  (:mod:`thermogrammetry.radiometry.empirical`), applied to inputs with raw counts from the referenced
  camera model; the outputs say the temperatures are empirical.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .._atomic import OutputSet
from ..errors import ConfigError, InvalidInputError, ThermogrammetryError
from ..radiometry.encoding import Encoding, TemperatureUnit, Uint16Mapping
from .thermal import ThermalImage, iter_thermal
from .tiff import write_counts_tiff, write_temperature_tiff

__all__ = ["ConvertOptions", "FileResult", "ConvertReport", "convert_files", "convert_one"]


@dataclass(frozen=True)
class ConvertOptions:
    """Typed options of :func:`convert_files`.

    ``overrides``: measurement parameters replacing the files' (``emissivity``, ``distance_m``,
    ``relative_humidity`` fraction, ``reflected_temperature_k``, ``atmospheric_temperature_k``), finite.
    ``dji_sdk``: path of DJI's Thermal SDK library for DJI R-JPEGs.  ``input_unit``: "K" or "C", the unit
    of CSV/NPY temperature matrices and of ``scale``/``offset``.  ``scale``, ``offset``: count->temperature
    mapping ``value = counts * scale + offset`` (in ``input_unit``) for 16-bit TIFFs without one (Workswell
    WIRIS).  ``raw``: write raw counts instead of temperatures.  ``references``: path of a references CSV.
    ``range_k``: (min, max) kelvin of the shared 16-bit mapping (default: from all inputs).
    """

    unit: TemperatureUnit = TemperatureUnit.K
    encoding: Encoding = Encoding.FLOAT32
    overrides: dict = field(default_factory=dict)
    dji_sdk: str | None = None
    input_unit: str | None = None
    scale: float | None = None
    offset: float | None = None
    raw: bool = False
    references: str | None = None
    range_k: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        from ..radiometry.measurement import MeasurementParams

        object.__setattr__(self, "unit", TemperatureUnit(self.unit))
        object.__setattr__(self, "encoding", Encoding(self.encoding))
        unknown = sorted(set(self.overrides) - set(MeasurementParams.field_names()))
        if unknown:
            raise ConfigError(f"unknown override(s) {unknown}; valid: {sorted(MeasurementParams.field_names())}")
        for k, v in self.overrides.items():
            if v is not None and np.ndim(v) == 0 and not np.isfinite(float(v)):
                raise ConfigError(f"{k}={v!r}: expected a finite number")
        if self.input_unit is not None and str(self.input_unit).upper() not in ("K", "C"):
            raise ConfigError(f"input_unit={self.input_unit!r}: expected 'K' or 'C'")
        for k in ("scale", "offset"):
            v = getattr(self, k)
            if v is not None and not np.isfinite(float(v)):
                raise ConfigError(f"{k}={v!r}: expected a finite number")
        if self.scale is not None and float(self.scale) == 0:
            raise ConfigError("scale=0: expected a non-zero temperature step per count")
        if (self.scale is not None or self.offset is not None) and self.input_unit is None:
            raise ConfigError("scale/offset need the unit they are in: give input_unit 'K' or 'C' (--input-unit)")
        if self.range_k is not None:
            lo, hi = (float(v) for v in self.range_k)
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
                raise ConfigError(f"range {self.range_k!r}: expected finite MIN < MAX above absolute zero")
        if self.raw and self.references:
            raise ConfigError("raw counts and references exclude each other: --raw writes counts, --references temperatures")


@dataclass
class FileResult:
    path: str
    ok: bool
    reader: str = ""
    outputs: list[str] = field(default_factory=list)
    shape: tuple[int, int] | None = None
    t_min_k: float | None = None
    t_max_k: float | None = None
    message: str = ""
    seconds: float = 0.0
    invalid_pixels: int = 0
    damaged_frames: list[int] = field(default_factory=list)


@dataclass
class ConvertReport:
    results: list[FileResult] = field(default_factory=list)
    mapping: Uint16Mapping | None = None
    empirical: object | None = None
    manifest: str | None = None

    @property
    def failures(self) -> list[FileResult]:
        return [r for r in self.results if not r.ok]

    @property
    def n_outputs(self) -> int:
        return sum(len(r.outputs) for r in self.results)


def _frames(p: Path, opts: ConvertOptions, empirical, on_damaged) -> Iterator[ThermalImage]:
    unit = opts.input_unit
    for img in iter_thermal(p, dji_sdk=opts.dji_sdk, unit=unit, scale=opts.scale, offset=opts.offset,
                            on_damaged=on_damaged, **opts.overrides):
        if empirical is not None and img.raw_counts is not None and _same_camera(img, empirical):
            import dataclasses

            t = empirical.temperature_k(img.raw_counts).astype(np.float32)
            md = dataclasses.replace(img.metadata, notes=list(img.metadata.notes) + [empirical.describe()],
                                     extra={**img.metadata.extra, "tiff_metadata": empirical.metadata()})
            img = ThermalImage(img.raw_counts, t, md)
        yield img


def _same_camera(img: ThermalImage, empirical) -> bool:
    cams = getattr(empirical, "cameras", None)
    return not cams or (img.metadata.make, img.metadata.model) in cams


def convert_one(p: Path, stem: str, stage: OutputSet | None, opts: ConvertOptions, empirical, mapping,
                 on_frame_done: Callable[[str, int], None] | None) -> FileResult:
    t0 = time.perf_counter()
    res = FileResult(str(p), ok=False)
    written: list[str] = []
    frame_errors: list[str] = []
    damaged: list[tuple[int, str]] = []
    lo, hi = np.inf, -np.inf
    try:
        frames = _frames(p, opts, empirical, lambda i, msg: damaged.append((i, msg)))
        first = next(frames, None)
        if first is None:
            raise InvalidInputError(damaged[0][1] if damaged else f"{p}: no frame")
        second = next(frames, None)
        multi = second is not None or bool(damaged) or first.metadata.reader in ("flir_seq", "flir_csq")

        def all_frames():
            yield first
            if second is not None:
                yield second
                yield from frames

        for i, img in enumerate(all_frames()):
            idx = img.metadata.frame_index if img.metadata.frame_index is not None else i
            name = f"{stem}_f{idx:05d}.tif" if multi else f"{stem}.tif"
            res.reader, res.shape = img.metadata.reader or "", img.shape
            where = f"{p} frame {idx}" if multi else str(p)
            if opts.raw:
                if img.raw_counts is None:
                    raise InvalidInputError(f"{where}: the file holds temperatures, no raw counts (drop --raw)")
                if stage is not None:
                    write_counts_tiff(stage.path(name), np.asarray(img.raw_counts, dtype=np.uint16), metadata=img.metadata)
                    written.append(name)
                lo, hi = min(lo, float(img.raw_counts.min())), max(hi, float(img.raw_counts.max()))
            else:
                t = img.require_temperature()
                fin = np.isfinite(t)
                n_bad = int(t.size - np.count_nonzero(fin))
                if n_bad == t.size:
                    msg = (f"{where}: every pixel's temperature is invalid (NaN/inf) -- check the measurement "
                           "parameters (emissivity, distance) and the file's calibration record")
                    if not multi:
                        raise InvalidInputError(msg)
                    frame_errors.append(msg)
                    continue
                res.invalid_pixels += n_bad
                lo, hi = min(lo, float(t[fin].min())), max(hi, float(t[fin].max()))
                if stage is not None:
                    tt = np.where(fin, t, np.nan).astype(np.float32)
                    try:
                        write_temperature_tiff(stage.path(name), tt, unit=opts.unit, encoding=opts.encoding,
                                               metadata=img.metadata, mapping=mapping)
                    except InvalidInputError as exc:  # outside the shared 16-bit range
                        if not multi:
                            raise InvalidInputError(f"{where}: {exc}") from None
                        frame_errors.append(f"{where}: {exc}")
                        continue
                    written.append(name)
            if on_frame_done is not None:
                on_frame_done(str(p), idx)
        problems = [m for _, m in damaged] + frame_errors
        res.damaged_frames = [i for i, _ in damaged]
        res.ok = not problems
        res.message = f"{len(written)} frame(s)"
        if res.invalid_pixels:
            res.message += f", {res.invalid_pixels} invalid pixel(s) written as no-data"
        if problems:
            res.message = "; ".join(problems) + f" (the other {len(written)} frame(s) were converted)"
    except MemoryError:
        res.message = f"{p}: not enough memory to convert this file"
    except (ThermogrammetryError, OSError, ValueError) as exc:
        # keep the batch going.  Frames already written are complete files (atomic writes); a sequence
        # that breaks part-way keeps them and says so.
        msg = str(exc) or type(exc).__name__
        if written:
            msg = f"{msg} (the {len(written)} frame(s) before it were converted)"
        res.message = msg
    res.outputs = written
    res.t_min_k, res.t_max_k = (lo, hi) if np.isfinite(lo) else (None, None)
    res.seconds = time.perf_counter() - t0
    return res


def __getattr__(name):
    """``convert_files`` (the batch, its shared 16-bit mapping and the output set) moved to the verb's driver,
    :mod:`thermogrammetry.pipeline.convert`; this keeps ``from thermogrammetry.io.convert import convert_files``."""
    if name in ("convert_files", "_fit_references"):
        import importlib

        return getattr(importlib.import_module("thermogrammetry.pipeline.convert"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: the name :func:`convert_one` had before the batch driver moved out (kept for code that imports it)
_convert_one = convert_one
