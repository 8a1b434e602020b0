"""The thin image reader used in front of the detectors (bit depth kept, clear errors)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from thermogrammetry.calibration.detect_io import read_image
from thermogrammetry.errors import CorruptFileError, DataFileError, UnsupportedFormatError


def test_reads_8bit_16bit_and_float_as_stored(tmp_path, rng):
    u8 = rng.integers(0, 256, (30, 40), dtype=np.uint8)
    u16 = rng.integers(0, 65536, (30, 40), dtype=np.uint16)
    f32 = rng.normal(300.0, 2.0, (30, 40)).astype(np.float32)
    cv2.imwrite(str(tmp_path / "a.png"), u8)
    cv2.imwrite(str(tmp_path / "b.png"), u16)
    tifffile.imwrite(tmp_path / "c.tif", u16)
    tifffile.imwrite(tmp_path / "d.tiff", f32)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), u8)
    b = read_image(tmp_path / "b.png")
    assert b.dtype == np.uint16
    np.testing.assert_array_equal(b, u16)
    np.testing.assert_array_equal(read_image(tmp_path / "c.tif"), u16)
    d = read_image(str(tmp_path / "d.tiff"))
    assert d.dtype == np.float32
    np.testing.assert_array_equal(d, f32)


def test_reader_errors_name_the_file(tmp_path):
    with pytest.raises(DataFileError, match="nope.png"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "x.gif").write_bytes(b"GIF89a")
    with pytest.raises(UnsupportedFormatError, match=r"x\.gif.*'\.gif'"):
        read_image(tmp_path / "x.gif")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(CorruptFileError, match="broken.png"):
        read_image(tmp_path / "broken.png")
    (tmp_path / "broken.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(CorruptFileError, match="broken.tif"):
        read_image(tmp_path / "broken.tif")
