"""The ``convert`` verb's driver: a batch of radiometric thermal files → one temperature TIFF per image or frame.

Each file is converted by :func:`thermogrammetry.io.convert.convert_one` (decoding, the radiometric model, the
TIFF with its metadata); this module runs the batch: output names fixed up front, files converted in threads,
one 16-bit scale/offset shared by the batch, an empirical mapping fitted from in-scene references, and OUT
written as one output set (:class:`~thermogrammetry._atomic.OutputSet`) with ``convert-manifest.json`` last.
A bad file is a failure with its reason and the batch goes on (see :mod:`thermogrammetry.io.convert`).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .._atomic import OutputSet
from ..errors import ConfigError, InvalidInputError
from ..io.convert import ConvertOptions, ConvertReport, FileResult, convert_one
from ..io.thermal import iter_thermal
from ..radiometry.encoding import Encoding, choose_uint16_mapping

__all__ = ["convert_files"]


def _fit_references(path: str, tasks, opts: ConvertOptions):
    """Fit the empirical mapping from the references' images (which must be among the inputs)."""
    from ..radiometry.empirical import fit_empirical_mapping, read_references_csv

    refs = read_references_csv(path)
    by_name: dict[str, Path] = {}
    for p, _ in tasks:
        by_name.setdefault(p.name, p)
        by_name.setdefault(str(p), p)
    counts, cams = {}, set()
    for r in refs:
        if r.image in counts:
            continue
        p = by_name.get(r.image) or by_name.get(Path(r.image).name)
        if p is None:
            raise ConfigError(f"references file {path}, line {r.row}: image {r.image!r} is not among the inputs")
        img = next(iter_thermal(p, dji_sdk=None, unit=opts.input_unit))
        if img.raw_counts is None:
            raise ConfigError(f"references file {path}, line {r.row}: {p} holds no raw counts to calibrate")
        counts[r.image] = img.raw_counts
        cams.add((img.metadata.make, img.metadata.model))
    emp = fit_empirical_mapping(refs, counts, source=f"references file {path}")
    emp.cameras = cams  # type: ignore[attr-defined]
    return emp


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
    ConvertReport with one :class:`FileResult` per input, in input order, the shared 16-bit mapping and the
    empirical mapping (if any).  Output paths in the results are the final ones in ``out_dir``.

    Raises
    ------
    ConfigError
        Bad options (``jobs`` < 1, unusable references file).
    DataFileError
        ``out_dir`` is a file or not writable (checked before any input is read).
    """
    opts = options or ConvertOptions()
    try:
        jobs = int(jobs)
    except (TypeError, ValueError):
        raise ConfigError(f"jobs={jobs!r}: expected an integer >= 1") from None
    if jobs < 1:
        raise ConfigError(f"jobs={jobs!r}: expected an integer >= 1")
    out = Path(out_dir)
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

    with OutputSet(out, "convert") as stage:
        empirical = _fit_references(opts.references, tasks, opts) if opts.references else None

        def pmap(fn):
            if jobs == 1 or len(tasks) < 2:
                return [fn(t) for t in tasks]
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(max_workers=jobs) as pool:
                return list(pool.map(fn, tasks))

        mapping = None
        if opts.encoding is Encoding.UINT16 and not opts.raw:
            if opts.range_k is not None:
                mapping = choose_uint16_mapping(np.asarray(opts.range_k, dtype=np.float64), opts.unit)
            else:  # first pass: the range of every input
                scan = pmap(lambda t: convert_one(t[0], t[1], None, opts, empirical, None, None))
                lo = [r.t_min_k for r in scan if r.t_min_k is not None]
                hi = [r.t_max_k for r in scan if r.t_max_k is not None]
                if lo:
                    try:
                        mapping = choose_uint16_mapping(np.asarray([min(lo), max(hi)]), opts.unit)
                    except InvalidInputError as exc:
                        raise ConfigError(f"one 16-bit mapping for the batch: {exc}; give --range MIN MAX "
                                          "or use float32") from None
        lock = threading.Lock()

        def run(task):
            res = convert_one(task[0], task[1], stage, opts, empirical, mapping, on_frame_done)
            res.outputs = [str(out / n) for n in res.outputs]
            if on_file_done is not None:
                with lock:
                    on_file_done(res)
            return res

        results = pmap(run)
        report = ConvertReport(results=results, mapping=mapping, empirical=empirical)
        if stage.files():
            manifest = {
                "unit": opts.unit.value, "encoding": "raw_counts" if opts.raw else opts.encoding.value,
                "uint16_mapping": None if mapping is None else {"scale": mapping.scale, "offset": mapping.offset,
                                                                 "unit": mapping.unit.value},
                "empirical": None if empirical is None else empirical.metadata(),
                "inputs": [{"path": r.path, "ok": r.ok, "outputs": [Path(o).name for o in r.outputs],
                            "message": r.message} for r in results],
            }
            stage.commit(manifest)
            report.manifest = str(out / stage.manifest_name)
    return report
