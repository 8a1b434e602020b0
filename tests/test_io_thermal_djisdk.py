"""The DJI Thermal SDK binding (ctypes), exercised with a stand-in C library of the same interface.

DJI's libdirp is not redistributable; the stand-in checks our side of the contract: the R-JPEG bytes are
handed over, the measurement parameters (and overrides, in the SDK's units) reach the library, and its
float32 °C image becomes ``temperature_k``.  It says nothing about DJI's own conversion.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from conftest import data_path
from thermogrammetry.io import read_thermal

STAND_IN = r"""
#include <stdint.h>
#include <string.h>
#pragma pack(push, 1)
typedef struct { float distance, humidity, emissivity, reflection; } params_t;
#pragma pack(pop)
static params_t P = {5.0f, 70.0f, 1.0f, 23.0f};
static int32_t SIZE = 0;
int32_t dirp_register_app(const char *key) { return strcmp(key, "DJI_TSDK") == 0 ? 0 : -1; }
int32_t dirp_create_from_rjpeg(const uint8_t *data, int32_t size, void **ph) {
    if (size < 4 || data[0] != 0xFF || data[1] != 0xD8) return -2;
    SIZE = size; *ph = (void *)&P; return 0;
}
int32_t dirp_destroy(void *h) { return 0; }
int32_t dirp_get_measurement_params(void *h, params_t *p) { *p = P; return 0; }
int32_t dirp_set_measurement_params(void *h, const params_t *p) {
    if (p->distance < 1 || p->distance > 25) return -3;
    P = *p; return 0;
}
int32_t dirp_measure_ex(void *h, float *t, int32_t size) {
    int32_t n = size / 4;
    for (int32_t i = 0; i < n; i++)
        t[i] = 20.0f + P.emissivity + P.distance / 100.0f + P.humidity / 1000.0f + P.reflection / 10000.0f + (i % 7);
    return 0;
}
"""


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory):
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler to build the stand-in SDK library")
    d = tmp_path_factory.mktemp("dirp")
    (d / "dirp.c").write_text(STAND_IN)
    lib = d / "libdirp_standin.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(lib), str(d / "dirp.c")], check=True, capture_output=True)
    return lib


def test_dji_sdk_binding_passes_parameters_and_returns_kelvin(stand_in, monkeypatch):
    p = data_path("rjpeg_samples", "images", "M3T", "DJI_0001_R.JPG")
    img = read_thermal(p, dji_sdk=str(stand_in))
    assert img.is_temperature and img.raw_counts is not None and img.shape == (512, 640)
    base = 20.0 + 1.0 + 5.0 / 100 + 70.0 / 1000 + 23.0 / 10000  # the library's own parameters
    i = np.arange(img.temperature_k.size) % 7
    np.testing.assert_allclose(img.temperature_k.ravel(), base + i + 273.15, atol=1e-4)
    assert "Thermal SDK" in img.metadata.notes[0]
    # overrides reach the library in its units (humidity %, reflection °C)
    img2 = read_thermal(p, dji_sdk=str(stand_in), emissivity=0.5, distance_m=10.0, relative_humidity=0.4,
                        reflected_temperature_k=273.15 + 30.0)
    want = 20.0 + 0.5 + 10.0 / 100 + 40.0 / 1000 + 30.0 / 10000
    assert float(img2.temperature_k.ravel()[0]) == pytest.approx(want + 273.15, abs=1e-4)
    # the environment variable works too; a value outside the SDK's range is refused by name
    monkeypatch.setenv("THERMOGRAMMETRY_DJI_TSDK", str(stand_in))
    assert read_thermal(p).is_temperature
    with pytest.raises(ValueError, match="distance 50 m"):
        read_thermal(p, distance_m=50.0)


def test_dji_sdk_missing_library_is_a_config_error(tmp_path):
    from thermogrammetry.errors import ConfigError

    p = data_path("rjpeg_samples", "images", "M3T", "DJI_0001_R.JPG")
    with pytest.raises(ConfigError, match="does not exist"):
        read_thermal(p, dji_sdk=str(tmp_path / "nope.so"))
