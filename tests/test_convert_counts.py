"""convert --raw, --references (empirical in-scene calibration), --scale/--offset (Workswell), --range."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import data_path
from test_bad_inputs import counts_img, fff_frame, tiff_bytes, write
from thermogrammetry.cli.main import main
from thermogrammetry.io import read_thermal
from thermogrammetry.radiometry.empirical import Reference, fit_empirical_mapping, region_mask

M3T = ("uav_m3t_flight", "Test_image")


def test_dji_m3t_raw_counts_written_as_labelled_uint16(tmp_path, capsys):
    src = [data_path(*M3T, "DJI_20240806173449_0008_T.JPG"), data_path(*M3T, "DJI_20240806173450_0009_T.JPG")]
    assert main(["convert", *map(str, src), "--raw", "-o", str(tmp_path / "OUT")]) == 0
    import tifffile

    for s in src:
        out = tmp_path / "OUT" / (s.stem + ".tif")
        with tifffile.TiffFile(out) as tf:
            arr = tf.pages[0].asarray()
            xml = tf.pages[0].tags[42112].value
        assert arr.dtype == np.uint16 and arr.shape == (512, 640)
        np.testing.assert_array_equal(arr, read_thermal(s).raw_counts)  # bit-exact counts
        assert 'role="unittype">counts<' in xml and "raw sensor counts (not temperature)" in xml
        back = read_thermal(out)  # read back as counts, never as temperatures
        assert back.temperature_k is None and back.metadata.geotag.has_position


def test_dji_m3t_references_give_an_empirical_mapping(tmp_path, capsys):
    src = data_path(*M3T, "DJI_20240806173449_0008_T.JPG")
    counts = read_thermal(src).raw_counts.astype(float)
    # two in-scene references: a cool and a warm 5x5 patch, temperatures stated by the (hypothetical) user
    cool = np.unravel_index(np.argmin(counts[2:-2, 2:-2]), counts[2:-2, 2:-2].shape)
    warm = np.unravel_index(np.argmax(counts[2:-2, 2:-2]), counts[2:-2, 2:-2].shape)
    (yc, xc), (yw, xw) = [(a + 2, b + 2) for a, b in (cool, warm)]
    refs = write(tmp_path / "refs.csv",
                 "image,polygon,temperature_c,sigma_k\n"
                 f"{src.name},{xc - 2} {yc - 2}; {xc + 2} {yc - 2}; {xc + 2} {yc + 2}; {xc - 2} {yc + 2},25.0,0.5\n"
                 f"{src.name},{xw - 2} {yw - 2}; {xw + 2} {yw - 2}; {xw + 2} {yw + 2}; {xw - 2} {yw + 2},45.0,0.5\n")
    assert main(["convert", str(src), "--references", str(refs), "-o", str(tmp_path / "OUT"), "--unit", "C"]) == 0
    img = read_thermal(tmp_path / "OUT" / (src.stem + ".tif"))
    md = img.metadata.extra["gdal_metadata"]
    assert md["THERMOGRAMMETRY_TEMPERATURE_SOURCE"].startswith("empirical")
    assert md["THERMOGRAMMETRY_EMPIRICAL_REFERENCES"] == "2 (redundancy 0)"
    sig = float(md["THERMOGRAMMETRY_EMPIRICAL_SIGMA_K"])
    assert 0 < sig < 0.5  # the two 0.5 K references, interpolated at mid-range: below either
    t = img.temperature_k - 273.15
    # the references' regions come back at their stated temperatures (a line through 2 points is exact)
    from thermogrammetry.radiometry.empirical import read_references_csv

    for r, tc in zip(read_references_csv(refs), (25.0, 45.0)):
        m = region_mask(r, t.shape)
        assert m.sum() == 16  # 4x4: left/top edges inclusive, right/bottom exclusive
        assert abs(float(t[m].mean()) - tc) < 2e-3  # float32 TIFF of ~300 K values: ~2e-5 K per pixel


def test_empirical_fit_recovers_a_known_line_within_its_sigma():
    """Counts from a known line T = a c + b plus Gaussian pixel noise; 4 references, redundancy 2."""
    rng = np.random.default_rng(3)
    a_true, b_true = 0.015625, 27.0  # K per count, K
    temps = np.array([280.0, 295.0, 310.0, 330.0])
    img = np.zeros((40, 40))
    refs = []
    for k, tk in enumerate(temps):
        c0 = (tk - b_true) / a_true
        img[:, 10 * k:10 * k + 10] = c0 + rng.normal(0, 8.0, (40, 10))  # 8 counts = 0.125 K pixel noise
        refs.append(Reference("x", float(tk), 0.0, polygon=((10 * k + 1, 1), (10 * k + 8, 1), (10 * k + 8, 38),
                                                             (10 * k + 1, 38)), row=k + 2))
    m = fit_empirical_mapping(refs, {"x": img})
    assert m.dof == 2
    # SEM of a 8x38 region: 8/sqrt(304) counts = 0.0072 K; 4-sigma two-sided bounds on a and b
    assert abs(m.a - a_true) < 4 * np.sqrt(m.cov[0, 0])
    assert abs(m.b - b_true) < 4 * np.sqrt(m.cov[1, 1])
    assert np.sqrt(m.cov[0, 0]) < 1e-5  # and the σ is small: the line is well determined


def test_region_mask_polygon_and_disc():
    r = Reference("x", 300.0, polygon=((1, 1), (3, 1), (3, 2), (1, 2)))
    # pixel centres inside; left/top edges inclusive, right/bottom exclusive: (1, 1) and (2, 1)
    assert np.argwhere(region_mask(r, (5, 5))).tolist() == [[1, 1], [1, 2]]
    d = Reference("x", 300.0, xy=(2, 2), radius_px=1.0)
    assert region_mask(d, (5, 5)).sum() == 5


def test_workswell_like_tiff_scale_offset_flags(tmp_path):
    counts = (10000 + np.arange(20).reshape(4, 5) * 10).astype(np.uint16)
    p = write(tmp_path / "wiris.tif", tiff_bytes(counts))
    assert main(["convert", str(p), "-o", str(tmp_path / "OUT"), "--scale", "0.01", "--offset", "-73.15",
                 "--input-unit", "C"]) == 0
    t = read_thermal(tmp_path / "OUT" / "wiris.tif").temperature_k
    np.testing.assert_allclose(t, counts * 0.01 - 73.15 + 273.15, atol=1e-4)  # float32 of ~300 K: 3e-5 K


def test_uint16_batch_shares_one_mapping(tmp_path, capsys):
    a = write(tmp_path / "a.fff", fff_frame(counts_img(level=14000)))
    b = write(tmp_path / "b.fff", fff_frame(counts_img(level=18000)))
    assert main(["convert", str(a), str(b), "--encoding", "uint16", "-o", str(tmp_path / "OUT")]) == 0
    import tifffile

    xml = [tifffile.TiffFile(tmp_path / "OUT" / n).pages[0].tags[42112].value for n in ("a.tif", "b.tif")]
    scale = [x.split('role="scale">')[1].split("<")[0] for x in xml]
    offset = [x.split('role="offset">')[1].split("<")[0] for x in xml]
    assert scale[0] == scale[1] and offset[0] == offset[1]
    for n, src in (("a.tif", a), ("b.tif", b)):  # and each decodes to its own temperatures within half a step
        d = read_thermal(tmp_path / "OUT" / n).temperature_k - read_thermal(src).temperature_k
        assert np.abs(d).max() <= 0.5 * float(scale[0]) + 1e-4
    # --range 280 281: the finest step covering it is 0.001 K, codes reach ~345 K; a (269.6..271.4 K) lies
    # below the mapping and fails, b (296.4..297.7 K) is converted
    assert main(["convert", str(a), str(b), "--encoding", "uint16", "--range", "280", "281",
                 "-o", str(tmp_path / "OUT2")]) == 2
    text = " ".join(capsys.readouterr().out.split())
    assert "outside the 16-bit mapping" in text and "a.fff" in text.split("failed:")[1]
    assert sorted(p.name for p in (tmp_path / "OUT2").glob("*.tif")) == ["b.tif"]
