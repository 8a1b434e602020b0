"""``thermogrammetry calibrate``: camera calibration with standard deviations (Yastikli & Guler 2013; Khodaei et al. 2015).

Routes (public contract)::

    thermogrammetry calibrate IMAGES... --target chessboard --corners 6x5 --spacing-mm 100 -o OUT
    thermogrammetry calibrate IMAGES... --target circles --grid 7x4 --spacing-mm 50 [--asymmetric] -o OUT
    thermogrammetry calibrate IMAGES... --target circles --grid 7x4 --spacing-mm 50 --diameter-mm 20 \
        --coded-marks default -o OUT          (Khodaei et al. 2015: 28 circles, 4 ring-coded marks)
    thermogrammetry calibrate IMAGES... --target coded --corners 11x9 --spacing-mm 50.5 --marker-mm 161.5 -o OUT
    thermogrammetry calibrate IMAGES... --target coded --target-file parameters.yaml -o OUT
    thermogrammetry calibrate --control control.csv --measurements measurements.csv \\
        --image-size 320x240 --pixel-pitch-um 25 --focal-mm 18 -o OUT

Every route takes ``--model photogrammetric`` (default: the correction form, Brown 1971 / Fraser 1997) or
``--model opencv`` (OpenCV's forward form as cv2.calibrateCamera estimates it: fx fy cx cy k1 k2 p1 p2 k3;
``--fix-k3``, ``--rational``); camera.json is in that model and the exports to the same model are exact.

IMAGES may be files or folders (8-bit JPEG/PNG, 16-bit TIFF/PNG, float TIFF). Everything is computed
in memory and written to OUT only at the end (each file atomically), so a failed run leaves OUT as
it was. Bad input exits with status 2 and a message naming the file (and row).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..pipeline.calibrate import _coded_spec, read_image  # noqa: F401 (kept importable from here)
from .app import app, print_error, print_plain


@app.command("calibrate")
def calibrate(
    images: Optional[List[Path]] = typer.Argument(None, help="Images (or folders of images) of a target."),
    target: Optional[str] = typer.Option(None, "--target", help="Target kind: chessboard, circles or coded (checkerboard with an ArUco marker on its central corner, Schramm et al. 2021)."),
    corners: Optional[str] = typer.Option(None, "--corners", help="Chessboard / coded checkerboard inner corners COLUMNSxROWS (OpenCV patternSize), e.g. 6x5 or 11x9."),
    marker_mm: Optional[float] = typer.Option(None, "--marker-mm", help="Coded target: side of the ArUco marker (outer black border) in mm, e.g. 161.5."),
    hidden_squares: Optional[int] = typer.Option(None, "--hidden-squares", help="Coded target: the marker blanks NxN squares around the central corner (default 4)."),
    marker_bits: Optional[int] = typer.Option(None, "--marker-bits", help="Coded target: inner bits per marker side of the custom dictionary (default 3: custom_dictionary(1, 3))."),
    dictionary: Optional[str] = typer.Option(None, "--dictionary", help="Coded target: a predefined cv2.aruco dictionary (e.g. DICT_4X4_50) instead of the custom one."),
    marker_id: Optional[int] = typer.Option(None, "--marker-id", help="Coded target: id of the marker in its dictionary (default 0)."),
    bottom_left_square: Optional[str] = typer.Option(None, "--bottom-left-square", help="Coded target: colour of the board's bottom-left square as printed, white or black (default white)."),
    target_file: Optional[Path] = typer.Option(None, "--target-file", help="Coded target: its own description (MRT parameters.yaml); flags given as well override it."),
    grid: Optional[str] = typer.Option(None, "--grid", help="Circle grid COLUMNSxROWS of centres, e.g. 7x4."),
    spacing_mm: Optional[float] = typer.Option(None, "--spacing-mm", help="Square size / centre spacing in mm."),
    asymmetric: bool = typer.Option(False, "--asymmetric", help="Asymmetric (staggered) circle grid."),
    diameter_mm: Optional[float] = typer.Option(None, "--diameter-mm", help="Circle diameter in mm: each circle's centroid bias is removed, iterated with the calibration (see docs/verbs/calibrate.md)."),
    coded_marks: Optional[str] = typer.Option(None, "--coded-marks", help="Ring-coded marks on the circle grid: 'default' (Khodaei et al. 2015's 7x4 layout) or COLUMNxROW=CODE,...; needs --diameter-mm (see docs/verbs/calibrate.md)."),
    control: Optional[Path] = typer.Option(None, "--control", help="Control points CSV: id,X,Y,Z[,sX,sY,sZ] (metres)."),
    measurements: Optional[Path] = typer.Option(None, "--measurements", help="Image measurements CSV: image,id,x,y[,sx,sy] (pixels)."),
    image_size: Optional[str] = typer.Option(None, "--image-size", help="WIDTHxHEIGHT in pixels (CSV route), e.g. 320x240."),
    pixel_pitch_um: Optional[float] = typer.Option(None, "--pixel-pitch-um", help="Pixel pitch in micrometres."),
    focal_mm: Optional[float] = typer.Option(None, "--focal-mm", help="Nominal focal length in mm (required for the CSV route)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder."),
    k45: bool = typer.Option(False, "--k45", help="Also estimate K4, K5 (as Khodaei et al. 2015 do)."),
    affinity: bool = typer.Option(False, "--affinity", help="Also estimate affinity/shear B1, B2."),
    model: str = typer.Option("photogrammetric", "--model", help="Camera model estimated: photogrammetric (correction form, Brown 1971 / Fraser 1997: c x0 y0 K1-K3 P1 P2) or opencv (forward form as cv2.calibrateCamera: fx fy cx cy k1 k2 p1 p2 k3); camera.json is in this model, its exports to the same model exact."),
    fix_k3: bool = typer.Option(False, "--fix-k3", help="Hold K3 (photogrammetric) / k3 (opencv) at 0, as cv2.CALIB_FIX_K3."),
    rational: bool = typer.Option(False, "--rational", help="--model opencv: also estimate k4, k5, k6 (cv2.CALIB_RATIONAL_MODEL)."),
    name: str = typer.Option("camera", "--name", help="Camera name written into camera.json."),
) -> None:
    """Calibrate a (thermal) camera: parameters with standard deviations, report and exports in OUT."""
    from rich.console import Console

    from ..errors import ThermogrammetryError
    from ..pipeline.calibrate import CalibrateUsageError, run_calibrate
    from .progress import progress

    err = Console(stderr=True, soft_wrap=True)
    console = Console(soft_wrap=True)
    try:
        coded = dict(marker_mm=marker_mm, hidden_squares=hidden_squares, marker_bits=marker_bits, dictionary=dictionary,
                     marker_id=marker_id, bottom_left_square=bottom_left_square, target_file=target_file,
                     coded_marks=coded_marks)
        run = run_calibrate(images, target, corners, grid, spacing_mm, asymmetric, diameter_mm, control, measurements,
                            image_size, pixel_pitch_um, focal_mm, output, k45, affinity, name, coded,
                            model=model, fix_k3=fix_k3, rational=rational, progress=lambda: progress(console, "calibrate"))
    except CalibrateUsageError as exc:
        print_error(err, exc)
        raise typer.Exit(2) from None
    except ThermogrammetryError as exc:
        print_error(err, f"{type(exc).__name__}: {exc}")
        err.print(f"nothing was written to {output}", highlight=False)
        raise typer.Exit(2) from None
    if run.failed is not None:
        err.print(f"[bold red]calibration failed[/] in step {run.failed.name!r}: {run.failed.error}; "
                  f"nothing was written to {output}", highlight=False)
        raise typer.Exit(1)
    _summary(console, run.calibration, output, run.keys)


def _summary(console, cal: dict, output, keys) -> None:
    """One screen: parameters with σ and t-test, σx σy, warnings, rejected images, files written."""
    from rich.table import Table

    n_img = len(cal["per_image"])
    dets = cal["run"].get("target", {}).get("detections") if isinstance(cal.get("run"), dict) else None
    if dets:
        from collections import Counter

        cnt = Counter(v["method"] for v in dets.values() if v.get("found"))
        console.print(f"target found in {sum(cnt.values())}/{len(dets)} images"
                      + (f" ({', '.join(f'{m}: {k}' for m, k in sorted(cnt.items(), key=lambda x: -x[1]))})" if cnt else ""),
                      highlight=False)
        coded = [v["coded_marks"] for v in dets.values() if v.get("found") and "coded_marks" in v]
        if coded:
            n_dec = sum(len(c["decoded"]) for c in coded)
            n_num = sum(c["ordering"] == "coded marks" for c in coded)
            console.print(f"coded marks: {n_dec} decoded in {len(coded)} images; numbering fixed by them in {n_num}/"
                          f"{len(coded)}" + (" (the others keep the geometric numbering)" if n_num < len(coded) else ""),
                          highlight=False)
    cb = cal["run"].get("target", {}).get("centre_bias") if isinstance(cal.get("run"), dict) else None
    if cb and cb.get("rounds"):
        ch = ", ".join(f"{h['bias_change_px']:.4f}" for h in cb["rounds"] if h.get("bias_change_px") is not None)
        console.print(f"circle-centre bias: max {cb['max_bias_px']:.3f} px, change per round {ch} px", highlight=False)
    console.print(f"[bold]calibration[/] {cal['termination']}: {len(cal['images_used'])}/{n_img} images used, "
                  f"RMS {cal['rms_px']:.3f} px, σ0 {cal['sigma0']:.3f}, redundancy {cal['dof']}", highlight=False)
    for wtext in cal.get("warnings", []):
        print_error(console, wtext, "warning:", "yellow")
    assumed = cal["run"].get("pixel_pitch_assumed")
    for cam in cal["cameras"]:
        w, h = cam["image_size"]
        t = Table(title=f"{cam['name']} {w}x{h}, pitch {cam['pixel_pitch_um'][0]:g} µm" + (" (assumed)" if assumed else ""),
                  show_edge=False)
        for col in ("parameter", "value", "std", "unit", "t", "signif."):
            t.add_column(col, justify="right")
        for n, p in cam["parameters"].items():
            if p["estimated"]:
                t.add_row(n, f"{p['value']:.6g}", f"{p['std']:.2g}", p["unit"], "" if "t" not in p else f"{p['t']:.1f}",
                          "" if "significant" not in p else ("yes" if p["significant"] else "no"))
        console.print(t)
        console.print(f"σx {cam['sigma_x_px']:.3f} px ({cam['sigma_x_um']:.2f} µm), σy {cam['sigma_y_px']:.3f} px "
                      f"({cam['sigma_y_um']:.2f} µm)", highlight=False)
        for wv in cam["correlation_warnings"]:
            console.print(f"[yellow]warning:[/] |ρ({wv['a']}, {wv['b']})| = {abs(wv['rho']):.3f} > 0.9", highlight=False)
    rej = cal["images_rejected"]
    if rej:
        console.print(f"[yellow]{len(rej)} image(s) rejected[/]:", highlight=False)
        for k, (nm, why) in enumerate(rej.items()):
            if k == 5:
                console.print(f"  ... and {len(rej) - 5} more (see calibration.json)")
                break
            print_plain(console, f"  {nm}: {why}")
    if cal["blunders"]:
        console.print(f"{len(cal['blunders'])} observation(s) rejected as blunders ({cal['blunder_test']})", highlight=False)
    for info in cal.get("exports", {}).values():
        colmap_apart = "same_as" not in info.get("colmap", {"same_as": "opencv"})
        for fmt, key in (("OpenCV" if colmap_apart else "OpenCV/COLMAP", "opencv"), ("COLMAP", "colmap"),
                         ("Metashape", "metashape"), ("photogrammetric", "photogrammetric")):
            o = info.get(key, {})
            if key == "colmap" and not colmap_apart:
                continue
            if o.get("max_residual_px") is not None:
                area = o.get("area_max_residual_px")
                label = "residual of the file read back" if (o.get("method") or o.get("residual")) else "conversion residual"
                console.print(f"{fmt} export: {label} max {o['max_residual_px']:.3g} px / "
                              f"RMS {o['rms_residual_px']:.3g} px over the whole frame"
                              + (f", max {area:.3g} px / RMS {o['area_rms_residual_px']:.3g} px over the data area"
                                 if area is not None else ""), highlight=False)
            if o.get("warning"):
                print_error(console, o["warning"], "warning:", "yellow")
    print_plain(console, f"wrote {len(keys)} files to {output}: {', '.join(k for k in keys if '/' not in k)}")
