"""The thermal cameras users fly: pixel pitch, the native core behind an upscaled image, lenses (focal length in mm,
field of view), keyed by the files' make and model (:func:`find_camera`, :func:`table_focal`).

A file that names its camera but not its pixel pitch (DJI and FLIR UAV cameras write no FocalPlaneResolution), or
no focal length at all (the Mavic 2 Enterprise Dual), gets its start value and a prior in pixels with σ from here.
Every value comes from the manufacturer's published specification (the entry's ``source``); a value we could not
confirm is left out rather than guessed, and the lookup then returns None for what it cannot give.

σ of a focal length in pixels (:func:`table_focal`):

- from a focal length in mm and the pixel pitch: :data:`LENS_FOCAL_SIGMA` of the value (nominal focal lengths of
  thermal lenses; the Zenmuse XT 13 mm lens's lab calibration is 741 px against the nominal 13 mm / 17 µm = 765 px,
  -3.1 %);
- from a field of view: the same relative σ combined with the FOV's stated tolerance, or its rounding to whole
  degrees (uniform ±0.5°: σ 0.29°) when none is stated, propagated through ``f = (w / 2) / tan(FOV / 2)``. Published
  fields of view of wide lenses include their distortion and are a few percent wider than the pinhole value.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

__all__ = ["Lens", "ThermalCore", "CameraEntry", "TableFocal", "CAMERA_TABLE", "LENS_FOCAL_SIGMA",
           "normalise_model", "find_camera", "table_focal", "focal_through_distortion"]


#: relative σ of a nominal lens focal length (see the module docstring)
LENS_FOCAL_SIGMA = 0.05

#: σ (degrees) of a field of view given to whole degrees without a tolerance (uniform over ±0.5°)
FOV_ROUNDING_SIGMA_DEG = 0.5 / math.sqrt(3.0)


@dataclass(frozen=True)
class Lens:
    """One lens: focal length (mm) and/or field of view (degrees: horizontal, diagonal), the FOV's stated
    tolerance (degrees) when the specification gives one."""

    focal_mm: float | None = None
    hfov_deg: float | None = None
    dfov_deg: float | None = None
    fov_tol_deg: float | None = None


@dataclass(frozen=True)
class ThermalCore:
    """A thermal core: native size (w, h) px, pixel pitch (µm), the image sizes it is delivered at (an upscaled
    or super-resolution image: larger than the native size) and its lenses."""

    native_size: tuple[int, int]
    pixel_pitch_um: float | None
    output_sizes: tuple[tuple[int, int], ...] = ()
    lenses: tuple[Lens, ...] = ()

    def sizes(self) -> tuple:
        return (tuple(self.native_size),) + tuple(tuple(s) for s in self.output_sizes)


@dataclass(frozen=True)
class CameraEntry:
    """A camera of the table: its name, the makes and model names its files carry (``aliases``: EXIF Model,
    DJI XMP model names), its cores and where the values come from."""

    name: str
    make: str
    aliases: tuple[str, ...]
    cores: tuple[ThermalCore, ...]
    source: str
    note: str = ""


@dataclass(frozen=True)
class TableFocal:
    """A focal length from the table: ``f_px`` with ``sigma_px`` on the image's own pixel grid, how it was
    obtained, the pixel pitch on that grid (µm; the native pitch / upscale), the native size and the upscale
    factor (image width / native width)."""

    camera: str
    f_px: float | None
    sigma_px: float | None
    how: str
    pixel_pitch_um: float | None
    native_size: tuple[int, int]
    upscale: float
    source: str = ""
    extra: dict = field(default_factory=dict)
    fov_half_extent_px: float | None = None  # from a field of view: the half extent (px) it spans (w/2 or diagonal/2)


_S = "manufacturer spec sheet"
# FLIR Tau 2 640 (XT, Vue Pro), 17 µm; the 9 mm lens's published 69° is 11 % wider than its pinhole 62°: left out
_TAU_640 = (Lens(9.0), Lens(13.0, 45.0), Lens(19.0, 32.0))
_TAU_336 = (Lens(9.0, 35.0), Lens(13.0, 25.0), Lens(19.0, 17.0))  # FLIR Tau 2 336

#: the table (add a camera: an entry here, its source, a test in tests/test_camera_table.py; docs/cameras.md)
CAMERA_TABLE: tuple[CameraEntry, ...] = (
    CameraEntry("DJI Zenmuse XT", "DJI", ("XT", "ZENMUSEXT", "FLIRXT", "ZENMUSE XT"),
                (ThermalCore((640, 512), 17.0, (), (Lens(7.5),) + _TAU_640),
                 ThermalCore((336, 256), 17.0, (), (Lens(6.8, 45.0),) + _TAU_336)), _S,
                "FLIR Tau 2 core; the wide lenses' fields of view are not in the table (their published values differ from the "
                "pinhole value by more than 10 %)"),
    CameraEntry("DJI Zenmuse XT2", "DJI", ("XT2", "ZENMUSEXT2"),
                (ThermalCore((640, 512), 17.0, (), _TAU_640 + (Lens(25.0, 25.0),)),
                 ThermalCore((336, 256), 17.0, (), _TAU_336)), _S),
    CameraEntry("DJI Zenmuse XT S", "DJI", ("XTS", "ZENMUSEXTS"),
                (ThermalCore((640, 512), 17.0, (), (Lens(19.0, 32.0),)),), _S),
    CameraEntry("DJI Mavic 2 Enterprise Dual", "DJI", ("M2ED", "MAVIC2ENTERPRISEDUAL", "MAVIC2ENTERPRISE", "ZH2ED"),
                (ThermalCore((160, 120), 12.0, ((640, 480),), (Lens(None, 57.0, None, 2.0),)),), _S,
                "FLIR Lepton 160x120 core delivered upscaled to 640x480; HFOV 57° ± 2°"),
    CameraEntry("DJI Mavic 2 Enterprise Advanced", "DJI", ("M2EA", "MAVIC2ENTERPRISEADVANCED"),
                (ThermalCore((640, 512), 12.0),), _S, "lens not in the table: the files' focal length is used"),
    CameraEntry("DJI Matrice 30T", "DJI", ("M30T",),
                (ThermalCore((640, 512), 12.0, (), (Lens(9.1, None, 61.0),)),), _S),
    CameraEntry("DJI Mavic 3 Thermal", "DJI", ("M3T",),
                (ThermalCore((640, 512), 12.0, (), (Lens(9.1, None, 61.0),)),), _S),
    CameraEntry("DJI Matrice 3TD", "DJI", ("M3TD",),
                (ThermalCore((640, 512), 12.0, (), (Lens(9.1, None, 61.0),)),), _S),
    CameraEntry("DJI Zenmuse H20T", "DJI", ("H20T", "ZH20T", "ZENMUSEH20T"),
                (ThermalCore((640, 512), 12.0, (), (Lens(13.5, None, 40.6),)),), _S),
    CameraEntry("DJI Zenmuse H20N", "DJI", ("H20N", "ZH20N", "ZENMUSEH20N"),
                (ThermalCore((640, 512), 12.0),), _S, "lenses not in the table: the files' focal length is used"),
    CameraEntry("DJI Zenmuse H30T", "DJI", ("H30T", "ZH30T", "ZENMUSEH30T"),
                (ThermalCore((640, 512), 12.0),), _S,
                "its 1280x1024 frames and its lens are not in the table (the published focal length and field of "
                "view do not agree with a 640x512 12 µm core): the files' focal length is used"),
    CameraEntry("DJI Matrice 4T", "DJI", ("M4T",),
                (ThermalCore((640, 512), 12.0, ((1280, 1024),), (Lens(None, None, 45.0),)),), _S,
                "1280x1024 is the super-resolution mode of the 640x512 core; the files' 12 mm with 12 µm gives a "
                "DFOV of 44.6°, the published 45°"),
    CameraEntry("FLIR Vue Pro", "FLIR", ("VUEPRO", "VUEPROR", "FLIRVUEPRO", "FLIRVUEPROR"),
                (ThermalCore((640, 512), 17.0, (), _TAU_640), ThermalCore((336, 256), 17.0, (), _TAU_336)), _S),
    CameraEntry("FLIR Duo Pro", "FLIR", ("DUOPRO", "DUOPROR", "FLIRDUOPRO", "FLIRDUOPROR", "DUO", "DUOR"),
                (ThermalCore((640, 512), 17.0, (), _TAU_640), ThermalCore((336, 256), 17.0, (), _TAU_336)), _S),
    CameraEntry("FLIR A35", "FLIR", ("A35", "FLIRA35", "A35SC"), (ThermalCore((320, 256), 17.0),), _S),
    CameraEntry("FLIR A65", "FLIR", ("A65", "FLIRA65", "A65SC"), (ThermalCore((640, 512), 17.0),), _S),
    CameraEntry("FLIR A320", "FLIR", ("A320", "FLIRA320", "A325", "A325SC", "FLIRA325SC"),
                (ThermalCore((320, 240), 25.0, (), (Lens(18.0, 25.0),)),), _S),
    CameraEntry("FLIR A615", "FLIR", ("A615", "FLIRA615"), (ThermalCore((640, 480), 17.0),), _S),
    CameraEntry("FLIR A655sc", "FLIR", ("A655SC", "FLIRA655SC", "A655"), (ThermalCore((640, 480), 17.0),), _S),
    CameraEntry("FLIR Boson", "FLIR", ("BOSON", "FLIRBOSON", "BOSON640", "BOSON320"),
                (ThermalCore((640, 512), 12.0, (), (Lens(14.0, 32.0), Lens(18.0, 24.0), Lens(24.0, 18.0), Lens(36.0, 12.0))),
                 ThermalCore((320, 256), 12.0)), _S),
    CameraEntry("Workswell WIRIS", "Workswell", ("WIRIS", "WIRISPRO", "WIRIS2NDGEN", "WIRISPROSC", "WORKSWELLWIRIS"),
                (ThermalCore((640, 512), 17.0),), _S, "lenses not in the table: the files' focal length is used"),
)

_MAKES = ("DJI", "FLIR", "FLIRSYSTEMS", "WORKSWELL", "SZDJITECHNOLOGYCO", "SZDJI")


def normalise_model(text) -> str:
    """Upper case, letters and digits only: ``"Zenmuse XT 2"``, ``"zenmuse-xt2"`` -> ``"ZENMUSEXT2"``."""
    return re.sub(r"[^A-Z0-9]", "", str(text or "").upper())


def _index() -> dict:
    out: dict[str, CameraEntry] = {}
    for e in CAMERA_TABLE:
        for a in e.aliases + (e.name,):
            out.setdefault(normalise_model(a), e)
    return out


_INDEX = _index()


def find_camera(make, model) -> CameraEntry | None:
    """The table's entry for a file's make and model (case and spacing ignored; a make repeated in the model,
    ``"FLIR Vue Pro R"``, and a trailing resolution, ``"Vue Pro 640"``, are accepted); None when not in the table."""
    m = normalise_model(model)
    if not m:
        return None
    cands = [m]
    for mk in sorted({normalise_model(make), *_MAKES}, key=len, reverse=True):
        if mk and m.startswith(mk) and len(m) > len(mk):
            cands.append(m[len(mk):])
    for c in list(cands):
        for res in ("640", "336", "320", "160"):
            if c.endswith(res) and len(c) > len(res):
                cands.append(c[: -len(res)])
    for c in cands:
        if c in _INDEX:
            return _INDEX[c]
    return None


def _core_for(entry: CameraEntry, size) -> ThermalCore | None:
    size = tuple(int(v) for v in size)
    for core in entry.cores:
        if size in core.sizes():
            return core
    return None


def _fov_focal(fov_deg: float, extent_px: float, tol_deg: float | None) -> tuple[float, float]:
    """f = (extent / 2) / tan(FOV / 2) and its σ (see the module docstring)."""
    th = math.radians(fov_deg)
    f = 0.5 * extent_px / math.tan(0.5 * th)
    s_th = math.radians(tol_deg if tol_deg is not None else FOV_ROUNDING_SIGMA_DEG)
    df = 0.25 * extent_px / math.sin(0.5 * th) ** 2 * s_th
    return f, math.hypot(df, LENS_FOCAL_SIGMA * f)


def focal_through_distortion(f_pinhole_px: float, half_extent_px: float, k1: float = 0.0, k2: float = 0.0,
                             k3: float = 0.0) -> float:
    """The focal length (px) that puts a field of view's edge ray at the frame edge through radial distortion.

    A published field of view is the angle the frame's edge sees *through the lens*: ``tan(FOV/2) = half_extent /
    f_pinhole`` only for a lens without distortion. Through the OpenCV radial model the edge ray at normalised radius
    ``x = tan(FOV/2)`` lands at ``f · x · (1 + k1 x² + k2 x⁴ + k3 x⁶)``, so the focal length consistent with the field
    of view is ``f_pinhole / (1 + k1 x² + k2 x⁴ + k3 x⁶)``: 10 % longer than the pinhole value for a 57° lens with
    k1 = -0.35 (barrel distortion widens the field a focal length covers; Brown 1971, Close-range camera calibration,
    Photogrammetric Engineering 37(8)).
    """
    x2 = (float(half_extent_px) / float(f_pinhole_px)) ** 2
    d = 1.0 + k1 * x2 + k2 * x2 * x2 + k3 * x2 ** 3
    if not d > 0.2:  # a distortion that folds the field's edge back: no consistent focal length
        return float("nan")
    return float(f_pinhole_px) / d


def table_focal(make, model, image_size, focal_mm: float | None = None) -> TableFocal | None:
    """The focal length in pixels of the image's own grid (``image_size`` (w, h)) with its σ, for a camera of the
    table: from ``focal_mm`` (the files' EXIF focal length) and the core's pixel pitch, else from the lens's field of
    view (the lens whose focal length is ``focal_mm``, or the core's only lens). ``f_px`` None (with ``how`` saying
    why) when the table knows the camera but not enough for a focal length (several lenses and no focal length in
    the file); None when the camera or the image size is not in the table."""
    entry = find_camera(make, model)
    if entry is None:
        return None
    core = _core_for(entry, image_size)
    if core is None:
        return None
    w, h = (int(v) for v in image_size)
    up = w / core.native_size[0]
    pitch = core.pixel_pitch_um / up if core.pixel_pitch_um else None
    base = dict(camera=entry.name, pixel_pitch_um=pitch, native_size=tuple(core.native_size), upscale=up,
                source=entry.source)
    ups = f" ({core.native_size[0]}x{core.native_size[1]} core upscaled {up:g}x)" if up != 1 else ""
    if focal_mm and pitch:
        f = float(focal_mm) / (pitch * 1e-3)
        return TableFocal(f_px=f, sigma_px=LENS_FOCAL_SIGMA * f, how=(
            f"focal {float(focal_mm):g} mm / pitch {core.pixel_pitch_um:g} µm{ups} (camera table: {entry.name})"), **base)
    lens = None
    if focal_mm:
        lens = next((ln for ln in core.lenses if ln.focal_mm and abs(ln.focal_mm / float(focal_mm) - 1) < 0.05), None)
    elif len(core.lenses) == 1:
        lens = core.lenses[0]
    if lens is not None and lens.focal_mm and pitch:
        f = lens.focal_mm / (pitch * 1e-3)
        return TableFocal(f_px=f, sigma_px=LENS_FOCAL_SIGMA * f, how=(
            f"lens {lens.focal_mm:g} mm / pitch {core.pixel_pitch_um:g} µm{ups} (camera table: {entry.name})"), **base)
    if lens is not None and (lens.hfov_deg or lens.dfov_deg):
        fov, ext, kind = ((lens.hfov_deg, w, "horizontal") if lens.hfov_deg else (lens.dfov_deg, math.hypot(w, h), "diagonal"))
        f, s = _fov_focal(fov, ext, lens.fov_tol_deg)
        tol = f" ± {lens.fov_tol_deg:g}°" if lens.fov_tol_deg is not None else ""
        return TableFocal(f_px=f, sigma_px=s, how=f"{kind} field of view {fov:g}°{tol}{ups} (camera table: {entry.name})",
                          fov_half_extent_px=0.5 * ext, **base)
    why = ("the table lists several lenses and the file names none" if len(core.lenses) > 1 else
           "the table has no lens for this camera")
    return TableFocal(f_px=None, sigma_px=None, how=f"camera table: {entry.name}: {why}", **base)
