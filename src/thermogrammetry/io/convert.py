"""Batch conversion of radiometric thermal files to temperature TIFFs (the library side of
``thermogrammetry convert``).

One output TIFF per image or sequence frame (``<stem>.tif``, ``<stem>_f00003.tif`` for frames), float32 in
K or °C or 16-bit with GDAL scale/offset, with EXIF/GPS/XMP kept (:func:`~.tiff.write_temperature_tiff`).
A file that cannot be converted (unknown format, truncated, raw counts only) is recorded as a failure with
its reason and the batch goes on; each output is written atomically, so a failure never leaves a partial
file behind (a sequence that breaks part-way keeps its complete frames and is still reported as failed).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..errors import ConfigError, ThermogrammetryError
from ..radiometry.encoding import Encoding, TemperatureUnit
from .thermal import iter_thermal
from .tiff import write_temperature_tiff

__all__ = ["ConvertOptions", "FileResult", "ConvertReport", "convert_files"]


@dataclass(frozen=True)
class ConvertOptions:
    """Typed options of :func:`convert_files`.

    ``overrides``: measurement parameters replacing the files' (``emissivity``, ``distance_m``,
    ``relative_humidity`` fraction, ``reflected_temperature_k``, ``atmospheric_temperature_k``).
    ``dji_sdk``: path of DJI's Thermal SDK library for DJI R-JPEGs.  ``input_unit``: "K" or "C", the unit
    of CSV/NPY temperature matrices (which carry none).
    """

    unit: TemperatureUnit = TemperatureUnit.K
    encoding: Encoding = Encoding.FLOAT32
    overrides: dict = field(default_factory=dict)
    dji_sdk: str | None = None
    input_unit: str | None = None  # declared unit of CSV/NPY matrices and float TIFFs without a unit tag

    def __post_init__(self) -> None:
        from ..radiometry.measurement import MeasurementParams

        object.__setattr__(self, "unit", TemperatureUnit(self.unit))
        object.__setattr__(self, "encoding", Encoding(self.encoding))
        unknown = sorted(set(self.overrides) - set(MeasurementParams.field_names()))
        if unknown:
            raise ConfigError(f"unknown override(s) {unknown}; valid: {sorted(MeasurementParams.field_names())}")
        if self.input_unit is not None and str(self.input_unit).upper() not in ("K", "C"):
            raise ConfigError(f"input_unit={self.input_unit!r}: expected 'K' or 'C'")


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


@dataclass
class ConvertReport:
    results: list[FileResult] = field(default_factory=list)

    @property
    def failures(self) -> list[FileResult]:
        return [r for r in self.results if not r.ok]

    @property
    def n_outputs(self) -> int:
        return sum(len(r.outputs) for r in self.results)


def _convert_one(p: Path, stem: str, out: Path, opts: ConvertOptions,
                 on_frame_done: Callable[[str, int], None] | None) -> FileResult:
    t0 = time.perf_counter()
    res = FileResult(str(p), ok=False)
    written: list[Path] = []
    lo, hi = np.inf, -np.inf
    try:
        frames = iter_thermal(p, dji_sdk=opts.dji_sdk, unit=opts.input_unit, **opts.overrides)
        first = next(frames)
        second = next(frames, None)
        multi = second is not None
        pending = [first] + ([second] if multi else [])

        def all_frames():
            yield from pending
            if multi:
                yield from frames

        for i, img in enumerate(all_frames()):
            t = img.require_temperature()
            idx = img.metadata.frame_index if img.metadata.frame_index is not None else i
            target = out / (f"{stem}_f{idx:05d}.tif" if multi else f"{stem}.tif")
            write_temperature_tiff(target, t, unit=opts.unit, encoding=opts.encoding, metadata=img.metadata)
            written.append(target)
            if on_frame_done is not None:
                on_frame_done(str(p), idx)
            if np.any(np.isfinite(t)):
                lo, hi = min(lo, float(np.nanmin(t))), max(hi, float(np.nanmax(t)))
            res.reader, res.shape = img.metadata.reader or "", img.shape
        res.ok = True
        res.message = f"{len(written)} frame(s)"
    except (ThermogrammetryError, OSError, ValueError, StopIteration) as exc:
        # keep the batch going.  Frames already written are complete files (atomic writes); a sequence
        # that breaks part-way keeps them and says so.
        msg = str(exc) or type(exc).__name__
        if isinstance(exc, StopIteration):
            msg = f"{p}: no frame"
        if written:
            msg = f"{msg} (the {len(written)} frame(s) before it were converted)"
        res.message = msg
    res.outputs = [str(w) for w in written]
    res.t_min_k, res.t_max_k = (lo, hi) if np.isfinite(lo) else (None, None)
    res.seconds = time.perf_counter() - t0
    return res


def convert_files(
    inputs: Sequence[str | Path],
    out_dir: str | Path,
    options: ConvertOptions | None = None,
    *,
    jobs: int = 1,
    on_file_done: Callable[[FileResult], None] | None = None,
    on_frame_done: Callable[[str, int], None] | None = None,
) -> ConvertReport:
    """Convert every input file; never stops at a bad file (see module docstring).

    ``jobs`` > 1 converts that many files at once in threads (decoding, the exp/log of the Planck curve
    and deflate release the GIL for most of the time).  ``on_file_done(result)`` is called after each
    file (from the worker thread), ``on_frame_done(path, frame_index)`` after each written frame.

    Returns
    -------
    ConvertReport with one :class:`FileResult` per input, in input order.
    """
    opts = options or ConvertOptions()
    if int(jobs) < 1:
        raise ConfigError(f"jobs={jobs!r}: expected an integer >= 1")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # output names are fixed up front (same stem twice -> _2, _3 ...), so threads never race for a name
    used: set[str] = set()
    tasks: list[tuple[Path, str]] = []
    for src in inputs:
        p = Path(src)
        stem, k = p.stem, 2
        while stem in used:
            stem, k = f"{p.stem}_{k}", k + 1
        used.add(stem)
        tasks.append((p, stem))

    def run(task):
        res = _convert_one(task[0], task[1], out, opts, on_frame_done)
        if on_file_done is not None:
            on_file_done(res)
        return res

    if int(jobs) == 1 or len(tasks) < 2:
        results = [run(t) for t in tasks]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=int(jobs)) as pool:
            results = list(pool.map(run, tasks))
    return ConvertReport(results=results)
