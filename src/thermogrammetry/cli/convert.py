"""``thermogrammetry convert``: radiometric thermal files -> temperature TIFFs (float32 K/°C or 16-bit)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import List, Optional

import typer

from .app import app

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


@app.command("convert")
def convert(
    inputs: List[Path] = typer.Argument(..., help="Thermal files (FLIR/DJI/Workswell R-JPEG, SEQ, CSQ, FFF, TIFF, CSV/NPY) or folders of them."),
    out_dir: Path = typer.Option(..., "-o", "--out", help="Output folder (created)."),
    unit: str = typer.Option("K", "--unit", help="Output unit: K or C."),
    encoding: str = typer.Option("float32", "--encoding", help="float32, or uint16 with GDAL scale/offset (<= 0.01 K step)."),
    emissivity: Optional[float] = typer.Option(None, "--emissivity", help="Override object emissivity (0-1]."),
    distance: Optional[float] = typer.Option(None, "--distance", help="Override object distance in metres."),
    humidity: Optional[float] = typer.Option(None, "--humidity", help="Override relative humidity in percent (0-100)."),
    reflected: Optional[str] = typer.Option(None, "--reflected", help="Override reflected apparent temperature, e.g. 20C or 293.15K (bare number: --unit)."),
    air_temperature: Optional[str] = typer.Option(None, "--air-temperature", help="Override air temperature, e.g. 20C or 293.15K (bare number: --unit)."),
    dji_sdk: Optional[Path] = typer.Option(None, "--dji-sdk", help="Path of DJI's Thermal SDK library (libdirp) for DJI R-JPEGs."),
    jobs: int = typer.Option(1, "--jobs", "-j", help="Files converted at once (threads)."),
    input_unit: Optional[str] = typer.Option(None, "--input-unit", help="Unit (K or C) of CSV/NPY temperature matrices, which carry none."),
) -> None:
    """Convert radiometric thermal images/sequences to one temperature TIFF per image or frame.

    Keeps going past files that cannot be converted, lists them at the end and exits with status 1.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from ..errors import ConfigError
    from ..io.convert import ConvertOptions, convert_files

    console = Console()
    try:
        u = unit.strip().upper().lstrip("°")
        if u not in ("K", "C"):
            raise typer.BadParameter(f"--unit {unit!r}: expected K or C")
        if humidity is not None and not (0 <= humidity <= 100):
            raise typer.BadParameter(f"--humidity {humidity}: expected percent in 0..100")
        overrides = {
            "emissivity": emissivity,
            "distance_m": distance,
            "relative_humidity": None if humidity is None else humidity / 100.0,
            "reflected_temperature_k": _temperature_k(reflected, u, "--reflected"),
            "atmospheric_temperature_k": _temperature_k(air_temperature, u, "--air-temperature"),
        }
        opts = ConvertOptions(unit=u, encoding=encoding, overrides={k: v for k, v in overrides.items() if v is not None},
                              dji_sdk=None if dji_sdk is None else str(dji_sdk),
                              input_unit=None if input_unit is None else input_unit.strip().upper().lstrip("°"))
    except ConfigError as exc:
        raise typer.BadParameter(str(exc)) from None

    files: list[Path] = []
    for item in inputs:  # a folder stands for the files directly inside it (sorted)
        files += sorted(q for q in item.iterdir() if q.is_file() and not q.name.startswith(".")) if item.is_dir() else [item]
    inputs = files

    with Progress(TextColumn("[bold]convert"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.description}"), console=console, transient=False) as progress:
        task = progress.add_task("", total=len(inputs))

        def done(r):
            progress.update(task, advance=1, description=Path(r.path).name)

        def frame(path, idx):
            if idx:  # sequences: show the running frame number
                progress.update(task, description=f"{Path(path).name} frame {idx}")

        report = convert_files(inputs, out_dir, opts, jobs=jobs, on_file_done=done, on_frame_done=frame)

    off = 273.15 if u == "C" else 0.0
    table = Table(title=f"convert -> {out_dir} ({opts.encoding.value}, {u})")
    for col in ("file", "reader", "size", f"min [{u}]", f"max [{u}]", "outputs", "s"):
        table.add_column(col)
    for r in report.results:
        if r.ok:
            table.add_row(Path(r.path).name, r.reader, f"{r.shape[1]}x{r.shape[0]}" if r.shape else "",
                          "" if r.t_min_k is None else f"{r.t_min_k - off:.2f}", "" if r.t_max_k is None else f"{r.t_max_k - off:.2f}",
                          str(len(r.outputs)), f"{r.seconds:.2f}")
        else:
            table.add_row(Path(r.path).name, "[red]FAILED", "", "", "", "0", f"{r.seconds:.2f}")
    console.print(table)
    if overrides and any(v is not None for v in overrides.values()):
        console.print("overrides: " + ", ".join(f"{k}={v:g}" for k, v in opts.overrides.items()))
    fails = report.failures
    console.print(f"{len(report.results) - len(fails)} of {len(report.results)} file(s) converted, {report.n_outputs} TIFF(s) written")
    if fails:
        console.print(f"[red]{len(fails)} file(s) failed:[/red]")
        for r in fails:
            msg = r.message if r.path in r.message else f"{r.path}: {r.message}"
            console.print(f"  {msg}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=1)
