"""``thermogrammetry convert``: radiometric thermal files -> temperature TIFFs (float32 K/°C or 16-bit)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import List, Optional, Tuple

import typer

from .app import app, print_error

_TEMP = re.compile(r"^\s*([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(°?[cCkK])?\s*$")


def _temperature_k(text: Optional[str], unit: str, flag: str) -> Optional[float]:
    """'20C', '20 °C', '293.15K' or a bare number in the output unit -> kelvin."""
    if text is None:
        return None
    m = _TEMP.match(text)
    if not m:
        raise typer.BadParameter(f"{flag}={text!r}: expected a temperature like 20C or 293.15K")
    v = float(m.group(1))
    u = (m.group(2) or unit).lstrip("°").upper()
    k = v + 273.15 if u == "C" else v
    if k <= 0:
        raise typer.BadParameter(f"{flag}={text!r} is below absolute zero")
    return k


def _expand(inputs: List[Path], console) -> list[Path]:
    """Files given, and for each folder the thermal files directly inside it (sorted).  Files in a folder
    that no reader accepts (README, .txt notes, LICENSE) and subfolders are listed as skipped, not failed."""
    from ..io.thermal import _SNIFF_BYTES, sniff_reader

    files: list[Path] = []
    for item in inputs:
        if not item.is_dir():
            files.append(item)
            continue
        skipped, subdirs = [], []
        for q in sorted(item.iterdir()):
            if q.name.startswith("."):
                continue
            if q.is_dir():
                subdirs.append(q.name)
                continue
            try:
                with open(q, "rb") as fh:
                    sniff_reader(q, fh.read(_SNIFF_BYTES))
            except (OSError, ValueError):
                skipped.append(q.name)
                continue
            files.append(q)
        if skipped:
            console.print(f"{item}: skipped {len(skipped)} file(s) that are not thermal images: "
                          + ", ".join(skipped[:10]) + (" ..." if len(skipped) > 10 else ""), markup=False, highlight=False)
        if subdirs:
            console.print(f"{item}: subfolder(s) not searched (give them as inputs): " + ", ".join(subdirs[:10])
                          + (" ..." if len(subdirs) > 10 else ""), markup=False, highlight=False)
    return files


@app.command("convert")
def convert(
    inputs: List[Path] = typer.Argument(..., help="Thermal files (FLIR/DJI/Workswell R-JPEG, SEQ, CSQ, FFF, TIFF, CSV/NPY) or folders of them."),
    out_dir: Path = typer.Option(..., "-o", "--out", help="Output folder (created; written as a set, with convert-manifest.json last)."),
    unit: str = typer.Option("K", "--unit", help="Output unit: K or C."),
    encoding: str = typer.Option("float32", "--encoding", help="float32, or uint16 with GDAL scale/offset (<= 0.01 K step), one mapping for the whole batch."),
    emissivity: Optional[float] = typer.Option(None, "--emissivity", help="Override object emissivity (0-1]."),
    distance: Optional[float] = typer.Option(None, "--distance", help="Override object distance in metres."),
    humidity: Optional[float] = typer.Option(None, "--humidity", help="Override relative humidity in percent (0-100)."),
    reflected: Optional[str] = typer.Option(None, "--reflected", help="Override reflected apparent temperature, e.g. 20C or 293.15K (bare number: --unit)."),
    air_temperature: Optional[str] = typer.Option(None, "--air-temperature", help="Override air temperature, e.g. 20C or 293.15K (bare number: --unit)."),
    dji_sdk: Optional[Path] = typer.Option(None, "--dji-sdk", help="Path of DJI's Thermal SDK library (libdirp) for DJI R-JPEGs."),
    jobs: int = typer.Option(1, "--jobs", "-j", min=1, help="Files converted at once (threads), >= 1."),
    input_unit: Optional[str] = typer.Option(None, "--input-unit", help="Unit (K or C) of CSV/NPY temperature matrices, which carry none, and of --scale/--offset."),
    raw: bool = typer.Option(False, "--raw", help="Write the raw sensor counts (uint16 TIFF labelled as counts, not temperatures) of every input that has them, e.g. DJI R-JPEGs."),
    references: Optional[Path] = typer.Option(None, "--references", help="refs.csv: >= 2 in-scene references give an empirical counts->temperature line (see docs/verbs/convert.md)."),
    scale: Optional[float] = typer.Option(None, "--scale", help="Temperature per count for 16-bit TIFFs without a mapping (Workswell WIRIS), in --input-unit."),
    offset: Optional[float] = typer.Option(None, "--offset", help="Temperature at count 0 for --scale, in --input-unit."),
    range_: Optional[Tuple[float, float]] = typer.Option(None, "--range", help="MIN MAX (in --unit) of the one 16-bit mapping of the batch; default: from all inputs."),
) -> None:
    """Convert radiometric thermal images/sequences to one temperature TIFF per image or frame.

    Keeps going past files that cannot be converted, lists them at the end and exits with status 2 (the
    other outputs are complete); bad options or an unusable output folder exit with status 2 before
    anything is read.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from ..errors import ConfigError, ThermogrammetryError
    from ..io.convert import ConvertOptions
    from ..pipeline.convert import convert_files

    console = Console()
    try:
        u = unit.strip().upper().lstrip("°")
        if u not in ("K", "C"):
            raise typer.BadParameter(f"--unit {unit!r}: expected K or C")
        if humidity is not None and not (0 <= humidity <= 100):
            raise typer.BadParameter(f"--humidity {humidity}: expected percent in 0..100")
        if emissivity is not None and not (0 < emissivity <= 1):
            raise typer.BadParameter(f"--emissivity {emissivity}: expected a number in (0, 1]")
        if distance is not None and not (math.isfinite(distance) and distance >= 0):
            raise typer.BadParameter(f"--distance {distance}: expected a finite distance >= 0 m")
        overrides = {
            "emissivity": emissivity,
            "distance_m": distance,
            "relative_humidity": None if humidity is None else humidity / 100.0,
            "reflected_temperature_k": _temperature_k(reflected, u, "--reflected"),
            "atmospheric_temperature_k": _temperature_k(air_temperature, u, "--air-temperature"),
        }
        if dji_sdk is not None:  # a library that cannot be DJI's for this machine: refused before anything is read
            from ..io.dji_sdk import check_dji_sdk

            check_dji_sdk(dji_sdk)
        rng = None
        if range_ is not None:
            rng = tuple(v + 273.15 if u == "C" else v for v in range_)
        opts = ConvertOptions(unit=u, encoding=encoding, overrides={k: v for k, v in overrides.items() if v is not None},
                              dji_sdk=None if dji_sdk is None else str(dji_sdk),
                              input_unit=None if input_unit is None else input_unit.strip().upper().lstrip("°"),
                              scale=scale, offset=offset, raw=raw,
                              references=None if references is None else str(references), range_k=rng)
    except (ConfigError, ValueError) as exc:
        raise typer.BadParameter(str(exc)) from None

    inputs = _expand(inputs, console)
    if not inputs:
        console.print("[red]error:[/] no thermal file among the inputs")
        raise typer.Exit(2)
    tty = console.is_terminal
    with Progress(TextColumn("[bold]convert"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.description}"), console=console, transient=False, disable=not tty) as progress:
        task = progress.add_task("", total=len(inputs))
        count = [0]

        def done(r):
            count[0] += 1
            progress.update(task, advance=1, description=Path(r.path).name)
            if not tty:  # a log gets one line per file
                print(f"convert [{count[0]}/{len(inputs)}] {r.path}: {'ok' if r.ok else 'FAILED'} ({r.seconds:.1f} s)",
                      flush=True)

        def frame(path, idx):
            if idx:  # sequences: show the running frame number
                progress.update(task, description=f"{Path(path).name} frame {idx}")

        try:
            report = convert_files(inputs, out_dir, opts, jobs=jobs, on_file_done=done, on_frame_done=frame)
        except ThermogrammetryError as exc:
            progress.stop()
            print_error(console, exc)
            raise typer.Exit(2)

    off = 273.15 if u == "C" else 0.0
    what = "raw counts" if raw else f"{opts.encoding.value}, {u}"
    table = Table(title=f"convert -> {out_dir} ({what})")
    lo_name, hi_name = ("min [counts]", "max [counts]") if raw else (f"min [{u}]", f"max [{u}]")
    for col in ("file", "reader", "size", lo_name, hi_name, "outputs", "s"):
        table.add_column(col)
    for r in report.results:
        o = 0.0 if raw else off
        if r.ok or r.outputs:
            table.add_row(Path(r.path).name, r.reader if r.ok else "[red]PARTLY FAILED", f"{r.shape[1]}x{r.shape[0]}" if r.shape else "",
                          "" if r.t_min_k is None else f"{r.t_min_k - o:.2f}", "" if r.t_max_k is None else f"{r.t_max_k - o:.2f}",
                          str(len(r.outputs)), f"{r.seconds:.2f}")
        else:
            table.add_row(Path(r.path).name, "[red]FAILED", "", "", "", "0", f"{r.seconds:.2f}")
    console.print(table)
    if opts.overrides:
        console.print("overrides: " + ", ".join(f"{k}={v:g}" for k, v in opts.overrides.items()))
    if report.mapping is not None:
        m = report.mapping
        console.print(f"16-bit mapping shared by the batch: value = code * {m.scale:g} + {m.offset:g} {m.unit.value}")
    if report.empirical is not None:
        console.print(report.empirical.describe(), markup=False, highlight=False, soft_wrap=True)
    n_invalid = sum(r.invalid_pixels for r in report.results)
    if n_invalid:
        console.print(f"{n_invalid} pixel(s) without a valid temperature written as no-data")
    fails = report.failures
    console.print(f"{len(report.results) - len(fails)} of {len(report.results)} file(s) converted, {report.n_outputs} TIFF(s) written")
    if fails:
        console.print(f"[red]{len(fails)} file(s) failed:[/red]")
        for r in fails:
            msg = r.message if r.path in r.message else f"{r.path}: {r.message}"
            console.print(f"  {msg}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=2)
