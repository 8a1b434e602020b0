"""Thermal image readers on the shared real data (skip when absent) and on files made in tmp_path."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, data_missing, data_path
from thermogrammetry.errors import ConfigError, DataFileError, InvalidInputError, ShapeError, UnsupportedFormatError
from thermogrammetry.io import read_thermal
from thermogrammetry.io.thermal import ThermalImage, iter_thermal, registered_readers
from thermogrammetry.io.tiff import write_temperature_tiff

pytestmark = pytest.mark.realdata

THERMIMAGE = ("flir_thermimage", "inst", "extdata")


def _dump(path: Path) -> dict[str, str]:
    """exiftool text dump (UTF-16 LE or ASCII) -> {tag name: value}; first occurrence wins."""
    b = path.read_bytes()
    text = b.decode("utf-16") if b[:2] == b"\xff\xfe" else b.replace(b"\x00", b"").decode("utf-8", "replace")
    out: dict[str, str] = {}
    for line in text.splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            out.setdefault(k.strip(), v.strip())
    return out


def _num(s: str) -> float:
    return float(re.match(r"[-+]?\d+(\.\d+)?", s.strip()).group(0))


# ----------------------------------------------------------------------------------------- references

def test_ir_2412_matches_thermimage_reference_within_0p05k():
    img = read_thermal(data_path(*THERMIMAGE, "IR_2412.jpg"))
    ref_c = np.fromfile(data_path("flir_thermimage", "Uploads", "FLIRjpg_W640_H480_F1_I.raw"), "<f4").reshape(480, 640)
    assert img.is_temperature and img.signal_unit == "K"
    assert img.raw_counts.dtype == np.uint16 and img.raw_counts.shape == (480, 640)
    assert (int(img.raw_counts.min()), int(img.raw_counts.max())) == (17917, 20218)  # SOURCE.md
    diff = img.temperature_k.astype(np.float64) - (ref_c.astype(np.float64) + 273.15)
    # the requirement is 0.05 K; with identical constants and model the residual is float32 rounding (~3e-5 K)
    assert np.max(np.abs(diff)) < 0.05
    assert np.max(np.abs(diff)) < 1e-3
    # parameter sensitivity: without the 1 m atmospheric path the difference is the 0.12 K that
    # flir_thermimage/SOURCE.md found with a Planck + emissivity-only model -- the atmosphere term is live
    no_atm = img.recompute(distance_m=0.0).temperature_k.astype(np.float64) - (ref_c.astype(np.float64) + 273.15)
    assert 0.10 < np.max(np.abs(no_atm)) < 0.14
    md = img.metadata
    assert md.planck.r1 == pytest.approx(21106.77, rel=1e-6) and md.planck.o == -7340
    assert md.emissivity == pytest.approx(0.95, abs=1e-6) and md.object_distance_m == pytest.approx(1.0)
    assert md.relative_humidity == pytest.approx(0.5, abs=1e-6)
    assert md.model == "FLIR SC660" and md.reader == "flir_rjpeg"


def test_seq_frames_match_thermimage_reference_within_0p05k():
    frames = list(iter_thermal(data_path(*THERMIMAGE, "SampleSEQ.seq")))
    ref = np.fromfile(data_path("flir_thermimage", "Uploads", "SampleSEQ_W640_H480_F2_I3.97.raw"), "<f4").reshape(2, 480, 640)
    assert len(frames) == 2
    for i, img in enumerate(frames):
        assert img.metadata.frame_index == i and img.metadata.reader == "flir_seq"
        d = img.temperature_k.astype(np.float64) - (ref[i].astype(np.float64) + 273.15)
        assert np.max(np.abs(d)) < 1e-3  # requirement 0.05 K; float32 rounding only
    # the two frames differ (it is a sequence, not one frame twice)
    assert np.mean(np.abs(frames[0].temperature_k - frames[1].temperature_k)) > 0.05
    # frame selection
    assert read_thermal(data_path(*THERMIMAGE, "SampleSEQ.seq"), frame=1).metadata.frame_index == 1


def test_csq_jpegls_frames():
    path = data_path(*THERMIMAGE, "SampleCSQ.csq")
    frames = list(iter_thermal(path))
    assert len(frames) == 8
    for img in frames:
        assert img.shape == (768, 1024) and img.raw_counts.dtype == np.uint16
        p = img.metadata.planck  # SOURCE.md (exiftool)
        assert (p.r1, p.b, p.o) == (pytest.approx(21546.203, rel=1e-6), pytest.approx(1507.2, rel=1e-6), -6331)
        assert p.r2 == pytest.approx(0.016229488, rel=1e-6)
        t_c = img.temperature_k - 273.15
        assert 10.0 < np.nanmin(t_c) < 20.0 and 30.0 < np.nanmax(t_c) < 40.0  # indoor scene with a person
    # CSQ raw frames are JPEG-LS *near-lossless*: the file itself stores every count within +-NEAR of the
    # sensor's value (NEAR read from each scan header, here 5..20 counts).  imagecodecs (CharLS) decodes
    # the stream exactly; the compression bound in kelvin is NEAR * dT/draw, reported in the notes.
    nears = []
    for img in frames:
        note = img.metadata.notes[0]
        m = re.search(r"NEAR=(\d+)", note)
        assert m, note
        nears.append(int(m.group(1)))
    assert min(nears) >= 1 and max(nears) <= 32
    raw_hot = float(np.nanmax(frames[0].raw_counts))
    from thermogrammetry.radiometry import temperature_from_raw

    dtdraw = float(temperature_from_raw(raw_hot + 1, frames[0].metadata.planck) - temperature_from_raw(raw_hot, frames[0].metadata.planck))
    assert 0.005 < dtdraw < 0.1  # K per count near 35 C for this camera


def test_flyr_agrees_on_handheld_flir_and_we_read_dji_flir_cores():
    flyr = pytest.importorskip("flyr")
    for name in ("FLIR_E40.jpg", "FLIR.jpg", "FLIR_AX8.jpg"):  # (T640 also agrees, but flyr is slow on it)
        p = data_path("rjpeg_samples", "images", name)
        ours = read_thermal(p).temperature_k.astype(np.float64)
        theirs = np.asarray(flyr.unpack(str(p)).kelvin, dtype=np.float64)
        assert ours.shape == theirs.shape
        assert np.nanmax(np.abs(ours - theirs)) < 1e-3  # same model; float32 rounding + flyr's 0.01 K rounding of inputs
    # flyr fails on the DJI XT2/XTR FLIR cores (KeyError after ~30 s of byte-wise scanning: shown in
    # benchmarks/convert.py, too slow for a test); we read them:
    for name in ("DJI_XT2.jpg", "DJI_XTR.jpg"):
        img = read_thermal(data_path("rjpeg_samples", "images", name))
        assert img.is_temperature and img.shape == (512, 640)


# ------------------------------------------------------------------ every sample file: read or refuse

def _sample_files() -> list[Path]:
    out = []
    for folder in ("rjpeg_samples", "flir_fff_tiff"):
        root = SHARED_DATA / folder
        if root.is_dir():
            out += sorted(p for p in root.rglob("*") if p.is_file())
    return out


_FILES = _sample_files()

# DJI-native sensors: raw counts, sensor size (the visible JPEG may be a 2x preview, M30T)
_DJI_NATIVE = {"DJI_H20T.jpg", "DJI_XTS.jpg", "H20N", "H20T", "M2EA", "M30T", "M3T", "M3TD", "M4T", "XTS", "H30T"}


@pytest.mark.parametrize("path", _FILES or [None], ids=[str(p.relative_to(SHARED_DATA)) for p in _FILES] or ["none"])
def test_every_sample_file_is_read_or_refused_specifically(path):
    if path is None:
        data_missing(f"no sample files under {SHARED_DATA}/rjpeg_samples or flir_fff_tiff")
    # exiftool dumps, licences and READMEs are not thermal images: they must be refused, by name, with a reason
    not_thermal = path.suffix.lower() in (".txt", ".md") or path.name.upper().startswith(("LICENSE", "README"))
    try:
        frames = list(iter_thermal(path))
    except DataFileError as exc:  # a refusal must name the file and say why
        assert str(path) in str(exc) and "not a radiometric thermal file" in str(exc)
        assert not_thermal, f"sample refused: {exc}"
        return
    assert not not_thermal, f"{path} should have been refused"
    assert len(frames) >= 1
    img = frames[0]
    assert isinstance(img, ThermalImage) and img.metadata.source_path == str(path)
    dump_path = path.with_suffix(".txt")
    dump = _dump(dump_path) if dump_path.exists() and path.suffix.lower() != ".tiff" else {}
    key = path.parent.name if path.parent.name != "images" else path.name
    if key in _DJI_NATIVE:
        # no documented conversion: raw counts, clearly flagged, never degrees
        assert not img.is_temperature and img.signal_unit == "counts"
        assert img.raw_counts.dtype == np.uint16
        assert img.shape == ((1024, 1280) if key == "H30T" else (512, 640))
        assert "raw counts only" in " ".join(img.metadata.notes)
        with pytest.raises(UnsupportedFormatError, match="raw counts only"):
            img.require_temperature()
        assert img.signal() is img.raw_counts
        assert (dump.get("Camera Model Name") or "").replace(" ", "") in (img.metadata.model or "").replace(" ", "")
        return
    if path.suffix.lower() in (".tiff", ".tif"):
        # example_radiometric.tiff declares no mapping: counts, flagged
        assert not img.is_temperature and "without a declared" in " ".join(img.metadata.notes)
        assert (int(img.raw_counts.min()), int(img.raw_counts.max())) == (6743, 7077)  # SOURCE.md
        return
    # FLIR FFF-based: temperatures + every constant as exiftool read it
    assert img.is_temperature and img.temperature_k.dtype == np.float32
    if not dump:  # frame_000000_le.fff has no dump: constants from flir_fff_tiff/SOURCE.md (exiftool)
        assert path.name == "frame_000000_le.fff"
        dump = {"Raw Thermal Image Height": "240", "Raw Thermal Image Width": "320", "Planck R1": "16125.788",
                "Planck R2": "0.010903412", "Planck B": "1420.1", "Planck O": "-5588", "Emissivity": "0.95"}
    assert img.shape == (int(_num(dump["Raw Thermal Image Height"])), int(_num(dump["Raw Thermal Image Width"])))
    p = img.metadata.planck
    assert p.r1 == pytest.approx(_num(dump["Planck R1"]), rel=1e-6)
    assert p.r2 == pytest.approx(_num(dump["Planck R2"]), rel=1e-6)
    assert p.b == pytest.approx(_num(dump["Planck B"]), rel=1e-6)
    assert p.o == pytest.approx(_num(dump["Planck O"]), abs=0.5)
    assert img.metadata.emissivity == pytest.approx(_num(dump["Emissivity"]), abs=0.006)
    if "Object Distance" in dump:
        assert img.metadata.object_distance_m == pytest.approx(_num(dump["Object Distance"]), abs=0.006)
        assert img.metadata.relative_humidity * 100 == pytest.approx(_num(dump["Relative Humidity"]), abs=0.06)
        assert img.metadata.reflected_temperature_k - 273.15 == pytest.approx(_num(dump["Reflected Apparent Temperature"]), abs=0.06)
    t_c = img.temperature_k - 273.15
    assert np.isfinite(t_c).mean() > 0.99 and -80 < np.nanmin(t_c) and np.nanmax(t_c) < 150
    if "GPS Latitude" in dump:
        assert img.metadata.geotag.latitude_deg is not None
        d, m, s = (float(x) for x in re.findall(r"[\d.]+", dump["GPS Latitude"])[:3])
        assert abs(img.metadata.geotag.latitude_deg) == pytest.approx(d + m / 60 + s / 3600, abs=1e-5)


def test_dji_geotags_and_params():
    # DJI_H20T.jpg: values of its exiftool dump (XMP drone-dji + EXIF GPS)
    g = read_thermal(data_path("rjpeg_samples", "images", "DJI_H20T.jpg")).metadata.geotag
    assert g.relative_altitude_m == pytest.approx(16.508) and g.altitude_m == pytest.approx(221.404)
    assert (g.gimbal_pitch_deg, g.gimbal_yaw_deg, g.flight_yaw_deg) == (pytest.approx(-10.5), pytest.approx(32.5), pytest.approx(30.3))
    assert g.latitude_deg == pytest.approx(40 + 33 / 60 + 49.61 / 3600, abs=2e-6)
    assert g.longitude_deg == pytest.approx(-(79 + 45 / 60 + 53.87 / 3600), abs=2e-6)  # West -> negative
    img = read_thermal(data_path("rjpeg_samples", "images", "M3T", "DJI_0001_R.JPG"))
    # (this sample's XMP was stripped after its dump was made: no pose here, only EXIF)
    assert img.metadata.focal_length_mm == pytest.approx(9.1)
    m = img.metadata.measurement  # APP4 "iirp" block: 25 C ambient, 5 m, 0.95, 50 %, 25 C reflected
    assert (m.emissivity, m.distance_m, m.relative_humidity) == (pytest.approx(0.95), pytest.approx(5.0), pytest.approx(0.5))
    h20t = read_thermal(data_path("rjpeg_samples", "images", "H20T", "DJI_0001_R.JPG")).metadata.measurement
    # exiftool dump: Object Distance 5, Relative Humidity 70, Emissivity 100, Reflection 230 (0.1 C)
    assert (h20t.distance_m, h20t.relative_humidity, h20t.emissivity) == (5.0, pytest.approx(0.7), pytest.approx(1.0))
    assert h20t.reflected_temperature_k == pytest.approx(23.0 + 273.15)


def test_uav_m3t_rtk_geotags():
    p = data_path("uav_m3t_flight", "Test_image", "DJI_20240806173449_0008_T.JPG")
    g = read_thermal(p).metadata.geotag
    assert g.rtk_flag == 50
    assert g.rtk_std_m == (pytest.approx(0.0086, abs=1e-4), pytest.approx(0.0120, abs=1e-4), pytest.approx(0.0195, abs=1e-4))
    assert 51.40 < g.latitude_deg < 51.41 and 4.42 < g.longitude_deg < 4.44
    assert 74.9 < g.relative_altitude_m < 75.1 and g.gimbal_pitch_deg == pytest.approx(-90.0, abs=0.5)


def test_workswell_jpeg_raw_equals_its_tiff():
    jpg = read_thermal(data_path("rgb_thermal_frescoes", "RadJPG_sample", "10-50-42-994-radiometric.jpg"))
    tif = read_thermal(data_path("rgb_thermal_frescoes", "RadTIFF", "10-50-42-994-radiometric.tiff"))
    assert not jpg.is_temperature and not tif.is_temperature  # no documented mapping in either file
    np.testing.assert_array_equal(jpg.raw_counts, tif.raw_counts)
    for md in (jpg.metadata, tif.metadata):  # SOURCE.md: 13 mm lens, 588.24 px/cm focal plane = 17 um pitch
        assert md.make == "Workswell" and md.focal_length_mm == pytest.approx(13.0)
        assert md.pixel_pitch_um[0] == pytest.approx(17.0, abs=0.01) and md.pixel_pitch_um[1] == pytest.approx(17.0, abs=0.02)
    assert jpg.metadata.serial == "1017-WWP-190408" and jpg.metadata.reader == "workswell_rjpeg"
    assert (int(tif.raw_counts.min()), int(tif.raw_counts.max())) == (4534, 4889)  # screen_readouts_transcribed.csv
    # with a declared mapping the TIFF yields temperatures (here an illustrative one, ~0.022 K/count)
    t = read_thermal(tif.metadata.source_path, scale=0.022, offset=-85.3, unit="C")
    assert t.is_temperature and t.temperature_k[256, 320] == pytest.approx(4565 * 0.022 - 85.3 + 273.15, abs=5e-5)  # float32 (half ulp 1.5e-5 K); measured 1.2e-6 K


# ------------------------------------------------------------------------- recompute, truncation, TIFF

def test_recompute_with_per_pixel_maps_equals_scalar_runs():
    img = read_thermal(data_path(*THERMIMAGE, "IR_2412.jpg"))
    h, w = img.shape
    emis = np.where(np.arange(w)[None, :] < w // 2, 0.9, 0.98) * np.ones((h, 1))
    dist = np.full((h, w), 3.0)
    mapped = img.recompute(emissivity=emis, distance_m=dist)
    left = img.recompute(emissivity=0.9, distance_m=3.0)
    right = img.recompute(emissivity=0.98, distance_m=3.0)
    np.testing.assert_allclose(mapped.temperature_k[:, : w // 2], left.temperature_k[:, : w // 2], atol=1e-4)
    np.testing.assert_allclose(mapped.temperature_k[:, w // 2 :], right.temperature_k[:, w // 2 :], atol=1e-4)
    # lower emissivity -> hotter object for the same counts (scene above reflected 20 C)
    assert np.median(left.temperature_k - right.temperature_k) > 0.3
    assert "overridden" in mapped.metadata.notes[-1]
    same = read_thermal(img.metadata.source_path, emissivity=0.9, distance_m=3.0)
    np.testing.assert_allclose(same.temperature_k, left.temperature_k, atol=1e-5)
    with pytest.raises(ConfigError, match="emisivity"):
        read_thermal(img.metadata.source_path, emisivity=0.9)
    with pytest.raises(InvalidInputError, match="emissivity"):  # out of range: not reported as a corrupt file
        read_thermal(img.metadata.source_path, emissivity=1.5)
    with pytest.raises(ShapeError, match=r"distance_m: per-pixel map of shape \(10, 10\)"):
        img.recompute(distance_m=np.ones((10, 10)))


@pytest.mark.parametrize("name", ["IR_2412.jpg", "SampleSEQ.seq", "SampleCSQ.csq"])
def test_truncated_files_raise_data_errors_only(tmp_path, name):
    data = data_path(*THERMIMAGE, name).read_bytes()
    for frac in (0.0005, 0.01, 0.1, 0.3, 0.6, 0.9, 0.999):
        p = tmp_path / f"cut_{frac}_{name}"
        p.write_bytes(data[: int(len(data) * frac)])
        try:
            frames = list(iter_thermal(p))
        except DataFileError as exc:
            assert str(p) in str(exc)
            continue
        # if the radiometric part survived the cut (e.g. only JPEG scan data lost), the result must be whole
        assert frames and all(f.raw_counts.shape[0] > 0 for f in frames)
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    with pytest.raises(UnsupportedFormatError, match="empty file"):
        read_thermal(empty)


def test_jpeg_without_radiometric_data_is_refused(tmp_path):
    from PIL import Image

    p = tmp_path / "photo.jpg"
    Image.new("RGB", (32, 24), (200, 100, 50)).save(p)
    with pytest.raises(UnsupportedFormatError, match="JPEG without radiometric data") as ei:
        read_thermal(p)
    assert str(p) in str(ei.value)


def test_temperature_tiff_roundtrip_gdal_and_geotags(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from PIL import Image

    img = read_thermal(data_path("rjpeg_samples", "images", "DJI_XT2.jpg"))
    t64 = img.temperature_k.astype(np.float64)
    for unit, off in (("K", 0.0), ("C", 273.15)):
        p = tmp_path / f"xt2_{unit}.tif"
        m = write_temperature_tiff(p, img.temperature_k, unit=unit, encoding="uint16", metadata=img.metadata)
        assert m.scale <= 0.01
        with rasterio.open(p) as ds:  # GDAL applies nothing itself; scale/offset/unit are in the metadata
            codes = ds.read(1)
            assert ds.units[0] == unit and ds.nodata == 0
            ex = ds.tags(ns="EXIF")  # GDAL, an independent reader, sees EXIF, GPS and XMP
            assert ex["EXIF_GPSLatitudeRef"] == "N" and ex["EXIF_GPSLongitude"].startswith("(76) (22)")
            assert "xml:XMP" in ds.tag_namespaces()
            gis = codes * ds.scales[0] + ds.offsets[0] + off
        assert np.max(np.abs(gis - t64)) <= 0.5 * m.scale * (1 + 1e-6)  # below half a quantisation step
        back = read_thermal(p)
        assert np.max(np.abs(back.temperature_k.astype(np.float64) - t64)) <= 0.5 * m.scale + 3e-5  # + float32
        g = back.metadata.geotag
        assert g.latitude_deg == pytest.approx(img.metadata.geotag.latitude_deg, abs=1e-7)
        assert g.longitude_deg == pytest.approx(img.metadata.geotag.longitude_deg, abs=1e-7)
        assert g.gimbal_yaw_deg == pytest.approx(82.400002, abs=1e-9) and g.relative_altitude_m == pytest.approx(1.9)  # XMP kept
        exif = Image.open(p).getexif()
        gps = exif.get_ifd(0x8825)
        assert gps[1] == "N" and gps[3] == "E" and float(gps[2][0]) == 9.0  # 9° 58' 19.77" N
        assert exif.get_ifd(0x8769)[37386] == pytest.approx(19.0)  # focal length kept
    pf = tmp_path / "xt2_f32.tif"
    write_temperature_tiff(pf, img.temperature_k, unit="C", encoding="float32", metadata=img.metadata)
    with rasterio.open(pf) as ds:
        assert ds.dtypes[0] == "float32" and ds.units[0] == "C"
        np.testing.assert_allclose(ds.read(1) + 273.15, t64, atol=3e-5)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporaries


def test_matrix_readers_need_explicit_unit(tmp_path, rng):
    t_c = rng.uniform(10, 40, size=(12, 16))
    csv = tmp_path / "m.csv"
    csv.write_text("header,of,columns\n" + "\n".join(",".join(f"{v:.6f}" for v in row) for row in t_c))
    npy = tmp_path / "m.npy"
    np.save(npy, t_c + 273.15)
    with pytest.raises(ConfigError, match="unit"):
        read_thermal(csv)
    a = read_thermal(csv, unit="C")
    b = read_thermal(npy, unit="K")
    np.testing.assert_allclose(a.temperature_k, t_c + 273.15, atol=1e-5)  # 6 decimals in the CSV + float32
    np.testing.assert_allclose(b.temperature_k, t_c + 273.15, atol=3e-5)
    assert a.raw_counts is None and a.metadata.reader == "matrix"


def test_registry_lists_all_formats():
    names = {r.name for r in registered_readers()}
    assert {"flir_rjpeg", "flir_fff", "workswell_rjpeg", "dji_rjpeg", "tiff", "matrix"} <= names


def test_directional_correction_on_a_real_image():
    from thermogrammetry.radiometry import FresnelEmissivity

    img = read_thermal(data_path(*THERMIMAGE, "IR_2412.jpg"))
    h, w = img.shape
    angle = np.deg2rad(np.broadcast_to(np.linspace(0, 70, w)[None, :], (h, w)))
    model = FresnelEmissivity(1.5, normal_emissivity=0.95)
    corr = img.correct_directional(angle, model, distance_m=np.full((h, w), 1.0))
    # at normal view the Fresnel model scaled to 0.95 equals the file's emissivity 0.95: no change
    np.testing.assert_allclose(corr.temperature_k[:, 0], img.temperature_k[:, 0], atol=1e-4)
    # at 70° emissivity drops to ~0.83: warm surfaces (scene 23-35 C above reflected 20 C) come out warmer
    assert np.all(corr.temperature_k[:, -1] > img.temperature_k[:, -1])
    with pytest.raises(InvalidInputError, match="grazing"):
        img.correct_directional(np.full((h, w), np.deg2rad(80.0)), model)


def test_emissivity_table_csv(tmp_path):
    from thermogrammetry.io.matrix import read_emissivity_table

    p = tmp_path / "brick.csv"
    p.write_text("angle_deg,emissivity\n0,0.93\n45,0.92\n70,0.85\n")
    tab = read_emissivity_table(p)
    assert float(tab(np.deg2rad(57.5))) == pytest.approx(0.885, abs=1e-12)
    bad = tmp_path / "bad.csv"
    bad.write_text("0,0.9\n10,1.2\n")
    with pytest.raises(InvalidInputError, match=r"bad\.csv: .*\(0, 1\]"):
        read_emissivity_table(bad)
