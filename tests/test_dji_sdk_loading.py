"""DJI's Thermal SDK given by path only: its plugins preloaded (no LD_LIBRARY_PATH), bad paths refused before
anything is written, the message without an SDK, and the count scale of the M3T family.

DJI's libdirp is not on this machine (not redistributable): fake libraries built with the C compiler stand in.
The fake ``libdirp.so`` opens its plugin ``libv_a.so`` by bare name with ``dlopen`` (as DJI's v1.7 opens its
``libv_*`` plugins) and returns -16 when that fails; ``libv_a.so`` needs ``libv_z.so`` (sorted after it, so the
preload has to retry). The plugin's value (8 °C) reaches the temperatures only through the preload.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import data_missing, data_path
from thermogrammetry.cli.main import main
from thermogrammetry.errors import ConfigError
from thermogrammetry.io import read_thermal

V_Z = "int v_z(void) { return 7; }\n"
V_A = "int v_z(void);\nint v_a(void) { return v_z() + 1; }\n"
DIRP = r"""
#include <dlfcn.h>
#include <stdint.h>
#pragma pack(push, 1)
typedef struct { float distance, humidity, emissivity, reflection; } params_t;
#pragma pack(pop)
static params_t P = {5.0f, 70.0f, 1.0f, 23.0f};
static int (*plugin)(void) = 0;
int32_t dirp_create_from_rjpeg(const uint8_t *data, int32_t size, void **ph) {
    void *h = dlopen("libv_a.so", RTLD_NOW);   /* by bare name, as DJI's libdirp opens its plugins */
    if (!h) return -16;
    plugin = (int (*)(void))dlsym(h, "v_a");
    if (!plugin) return -16;
    *ph = (void *)&P; return 0;
}
int32_t dirp_destroy(void *h) { return 0; }
int32_t dirp_get_measurement_params(void *h, params_t *p) { *p = P; return 0; }
int32_t dirp_set_measurement_params(void *h, const params_t *p) { P = *p; return 0; }
int32_t dirp_measure_ex(void *h, float *t, int32_t size) {
    for (int32_t i = 0; i < size / 4; i++) t[i] = (float)plugin();
    return 0;
}
"""


@pytest.fixture(scope="module")
def fake_sdk(tmp_path_factory):
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler to build the fake SDK libraries")
    d = tmp_path_factory.mktemp("tsdk")
    for name, src, extra in (("libv_z", V_Z, []), ("libv_a", V_A, ["-L", str(d), "-lv_z"]), ("libdirp", DIRP, ["-ldl"])):
        (d / f"{name}.c").write_text(src)
        subprocess.run([cc, "-shared", "-fPIC", "-O1", f"-Wl,-soname,{name}.so", "-o", str(d / f"{name}.so"),
                        str(d / f"{name}.c"), *extra], check=True, capture_output=True)
    return d


M3T = ("rjpeg_samples", "images", "M3T", "DJI_0001_R.JPG")


def test_without_the_preload_the_fake_sdk_fails_like_djis(fake_sdk):
    """The control: loading libdirp alone (a fresh process, no LD_LIBRARY_PATH) gives DJI's -16."""
    code = ("import ctypes, sys; lib = ctypes.CDLL(sys.argv[1]); h = ctypes.c_void_p(); b = (ctypes.c_uint8 * 4)(255, 216, 0, 0); "
            "print(lib.dirp_create_from_rjpeg(b, 4, ctypes.byref(h)))")
    env = {k: v for k, v in os.environ.items() if k != "LD_LIBRARY_PATH"}
    out = subprocess.run([sys.executable, "-c", code, str(fake_sdk / "libdirp.so")], capture_output=True, text=True,
                         env=env, check=True)
    assert out.stdout.strip() == "-16"


def test_sdk_by_path_works_thanks_to_the_preload(fake_sdk, monkeypatch):
    monkeypatch.delenv("LD_LIBRARY_PATH", raising=False)
    img = read_thermal(data_path(*M3T), dji_sdk=str(fake_sdk / "libdirp.so"))
    assert img.is_temperature and img.shape == (512, 640)
    # libv_a() = libv_z() + 1 = 8 °C: the plugin and its dependency were found by bare name
    np.testing.assert_allclose(img.temperature_k, 8.0 + 273.15, atol=1e-4)
    assert "Thermal SDK" in img.metadata.notes[0]


def _elf_of_other_machine(src, dst, *, machine=None, bits=None):
    data = bytearray(src.read_bytes())
    if machine is not None:
        data[18:20] = int(machine).to_bytes(2, "little")
    if bits is not None:
        data[4] = 1 if bits == 32 else 2
    dst.write_bytes(bytes(data))
    return dst


def test_bad_sdk_paths_are_refused_by_name(fake_sdk, tmp_path):
    from thermogrammetry.io.dji_sdk import check_dji_sdk, elf_machine, machine_code

    code, name = machine_code()
    if not sys.platform.startswith("linux") or code is None:
        pytest.skip("ELF checks are made on Linux")
    lib = fake_sdk / "libdirp.so"
    assert elf_machine(lib)[1] == code
    other = 183 if code != 183 else 62  # AArch64 on x86-64, else x86-64
    for sub in ("arm", "b32"):
        (tmp_path / sub).mkdir()
    (tmp_path / "readme.so").write_text("not a library\n")
    (tmp_path / "libdirp.dll").write_bytes(b"MZ\x90\x00" + bytes(60))
    cases = [
        (tmp_path / "nope.so", "does not exist"),
        (fake_sdk, "is a folder, expected the library file libdirp.so itself (the folder holds libdirp.so"),
        (tmp_path / "readme.so", "not an ELF shared library"),
        (tmp_path / "libdirp.dll", "a Windows DLL"),
        (_elf_of_other_machine(lib, tmp_path / "arm" / "libdirp.so", machine=other), f"this machine is {name}"),
        (_elf_of_other_machine(lib, tmp_path / "b32" / "libdirp.so", bits=32), "is a 32-bit library"),
        (fake_sdk / "libv_z.so", "does not export dirp_create_from_rjpeg"),
    ]
    for path, msg in cases:
        with pytest.raises(ConfigError) as ei:
            check_dji_sdk(path)
        text = str(ei.value)
        assert msg in text and str(path) in text and "install DJI Thermal SDK" in text and "--dji-sdk" in text, text


@pytest.mark.parametrize("verb", ["convert", "survey", "run", "dense", "ortho"])
def test_a_bad_sdk_path_exits_2_and_writes_nothing(verb, tmp_path, capsys):
    bad = tmp_path / "libdirp.so"
    bad.write_text("not a library\n")
    out = tmp_path / "out"
    src = str(data_path(*M3T))
    sv = tmp_path / "survey"  # (beside OUT: an OUT inside the survey folder is refused before anything else)
    args = {"convert": [src], "survey": [src], "run": [src], "dense": [str(sv)],
            "ortho": [str(sv), "--dsm", str(sv / "dsm.tif")]}[verb]
    if verb in ("dense", "ortho"):  # a survey folder of counts from the M3T file (the SDK is checked first)
        pytest.importorskip("rasterio")
        sv.mkdir()
        _counts_survey(sv)
    assert main([verb, *args, "-o", str(out), "--dji-sdk", str(bad)]) == 2
    cap = capsys.readouterr()
    assert not out.exists()
    text = " ".join(re.sub("[│╭╮╰╯─]", " ", cap.err + cap.out).split())  # (typer draws a box around convert's)
    assert "DJI Thermal SDK library" in text and "not an ELF shared library" in text and "install DJI Thermal SDK" in text


def _counts_survey(folder):
    """A survey folder whose three frames are counts from the M3T R-JPEG (cameras.json names it as their source)."""
    import tifffile

    from thermogrammetry.camera import Camera
    from thermogrammetry.io.oriented import OrientedCameras, OrientedImage

    (folder / "frames").mkdir(exist_ok=True)
    img = read_thermal(data_path(*M3T))
    ims = []
    for k in range(3):
        tifffile.imwrite(folder / "frames" / f"f{k}.tif", img.raw_counts)
        ims.append(OrientedImage(f"f{k}", "thermal", np.eye(3), np.array([k * 5.0, 0.0, 50.0]), frame=f"frames/f{k}.tif",
                                 unit="counts", source=str(data_path(*M3T))))
    cam = Camera.from_opencv(np.array([[800.0, 0, 319.5], [0, 800.0, 255.5], [0, 0, 1]]), np.zeros(5), (640, 512))
    OrientedCameras({"thermal": cam}, ims, crs=None).save(folder / "cameras.json")


def test_dense_and_ortho_read_the_dji_frames_again_through_the_sdk(fake_sdk, tmp_path):
    """A survey of DJI R-JPEGs decoded as counts: with --dji-sdk its frames are the SDK's kelvin."""
    from thermogrammetry.pipeline.frames import SurveyFrames

    _counts_survey(tmp_path)
    assert SurveyFrames(tmp_path).unit == "counts"
    sv = SurveyFrames(tmp_path, dji_sdk=str(fake_sdk / "libdirp.so"))
    assert sv.unit == "K"
    np.testing.assert_allclose(sv(1), 8.0 + 273.15, atol=1e-4)


def test_without_an_sdk_the_message_says_what_to_install_and_raw_counts_remain(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("THERMOGRAMMETRY_DJI_TSDK", raising=False)
    assert main(["convert", str(data_path(*M3T)), "-o", str(tmp_path / "c")]) == 2
    text = " ".join(capsys.readouterr().out.split())
    for want in ("raw counts only", "install DJI Thermal SDK", "--dji-sdk", "$THERMOGRAMMETRY_DJI_TSDK", "libdirp.so", "--raw"):
        assert want in text, want
    assert main(["convert", str(data_path(*M3T)), "-o", str(tmp_path / "raw"), "--raw"]) == 0
    assert (tmp_path / "raw" / "DJI_0001_R.tif").is_file()


def test_m3t_family_counts_are_four_times_the_sdk_raw(shared_data):
    """DJI M3T/M30T/M4T/H30T/M2EA/H20N: the APP3 counts have their two low bits 0 (4 × the SDK's original raw);
    H20T, M3TD and the XT S do not (measured: all three have counts ≡ 1..3 mod 4)."""
    flight = sorted((shared_data / "uav_m3t_flight" / "Test_image").glob("*_T.JPG"))
    fams = ["M3T", "M30T", "M4T", "H30T", "M2EA", "H20N"]
    files = flight + [next((shared_data / "rjpeg_samples" / "images" / f).glob("*.JPG")) for f in fams]
    if len(flight) < 32:
        data_missing("the shared M3T flight is absent")
    for f in files:
        r = read_thermal(f).raw_counts
        assert r.dtype == np.uint16 and r.min() > 4000 and np.all(r % 4 == 0), f
    other = read_thermal(next((shared_data / "rjpeg_samples" / "images" / "H20T").glob("*.JPG"))).raw_counts
    assert np.any(other % 4 != 0)
