"""Thermal video: 16-bit frames decoded as kelvin, frames extracted at a target forward overlap."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.errors import ConfigError, DataFileError, UnsupportedFormatError
from thermogrammetry.pipeline import MemoryProject
from thermogrammetry.synthetic.survey import SurveyConfig, make_survey, render_frame, write_survey
from thermogrammetry.synthetic.terrain import TerrainConfig

pytest.importorskip("av")


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    cfg = SurveyConfig(terrain=TerrainConfig(width_m=90.0, height_m=60.0, n_buildings=4, n_trees=6, n_roads=1),
                       image_size=(160, 128), focal_mm=6.25, flight_height_m=60.0, n_gcp=3, n_check=2, seed=3,
                       video_fps=10.0, speed_mps=5.0, max_frames=40)
    sc = make_survey(cfg)
    proj = MemoryProject()
    write_survey(proj, sc, threads=1)
    path = tmp_path_factory.mktemp("video") / "thermal.mkv"
    path.write_bytes(proj.read_bytes("survey/video/thermal.mkv"))
    return sc, proj, path


def _true_shift_px(sc, a, b):
    """Median image motion (px) of the ground seen in the middle of frame a, from a to b (truth)."""
    cam = sc.camera
    depth = render_frame(sc, a, with_truth=True, sensor=False)["depth_m"]
    h, w = depth.shape
    ys, xs = np.mgrid[h // 4:3 * h // 4:4, w // 4:3 * w // 4:4]
    xy = np.c_[xs.ravel(), ys.ravel()].astype(float)
    rays = cam.unproject(xy)
    pc = np.c_[rays[:, :2] / rays[:, 2:3], np.ones(len(xy))] * depth[ys.ravel(), xs.ravel()][:, None]
    pw = sc.frames[a].pose.inverse().transform(pc)
    return np.median(cam.project(sc.frames[b].pose.transform(pw)) - xy, axis=0)


def test_video_frames_are_kelvin_equal_to_the_rendered_frames(video):
    import io

    import tifffile

    from thermogrammetry.io.video import probe_video, read_video_frames

    sc, proj, path = video
    info = probe_video(path)
    assert (info.width, info.height, info.bits) == (160, 128, 16) and info.fps == pytest.approx(10.0)
    frames = list(read_video_frames(path, every=7))
    assert [f.index for f in frames] == list(range(0, 40, 7))
    for f in frames[:3]:
        assert f.unit == "K" and f.image.dtype == np.float32
        tif = tifffile.imread(io.BytesIO(proj.read_bytes(f"survey/images/T{f.index:04d}.tif")))
        assert np.nanmax(np.abs(f.image - tif)) <= 0.5 * info.scale + 1e-4  # 16-bit quantisation only
        assert f.time_s == pytest.approx(sc.frames[f.index].time_s, abs=1e-9)  # measured 1.1e-16 s


def test_frames_extracted_at_the_target_forward_overlap(video):
    from thermogrammetry.io.video import read_video_frames

    sc, _, path = video
    h = sc.camera.image_size[1]
    kept = [f.index for f in read_video_frames(path, forward_overlap=0.8)]
    assert 4 <= len(kept) <= 6 and kept[0] == 0
    # frame-to-frame motion (attitude jitter of 1 deg per frame included) bounds the overshoot
    steps = [abs(_true_shift_px(sc, i, i + 1)[1]) / h for i in range(0, kept[-1])]
    for a, b in zip(kept[:-1], kept[1:]):
        moved = abs(_true_shift_px(sc, a, b)[1]) / h  # the flight runs along the image's y axis
        assert 0.2 - 0.02 <= moved <= 0.2 + max(steps[a:b]) + 0.02, (a, b, moved)


def test_video_bad_input(tmp_path):
    from thermogrammetry.io.video import extraction_stride, read_video_frames

    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42 not really a video")
    with pytest.raises(UnsupportedFormatError, match="clip.mp4"):
        list(read_video_frames(bad))
    with pytest.raises(DataFileError, match="no such video"):
        list(read_video_frames(tmp_path / "missing.mkv"))
    with pytest.raises(ConfigError, match="forward_overlap=1.2"):
        list(read_video_frames(bad, forward_overlap=1.2))
    assert extraction_stride(30.0, 5.0, 40.0, 0.8) == 48  # 0.2 * 40 m / (5 m/s / 30 Hz)
    with pytest.raises(ConfigError, match="speed_mps=0"):
        extraction_stride(30.0, 0, 40.0, 0.8)


def test_survey_orients_the_frames_of_a_thermal_video(video, tmp_path):
    """thermal video -> frames at 80 % overlap -> survey (no GNSS: a free block), values kept as kelvin."""
    import json

    from thermogrammetry.cli.main import main
    from thermogrammetry.geometry.helmert import umeyama
    from thermogrammetry.io.oriented import OrientedCameras

    sc, _, path = video
    assert main(["survey", str(path), "-o", str(tmp_path / "s"), "--gnss", "none", "--workers", "0"]) == 0
    s = json.loads((tmp_path / "s" / "survey.json").read_text())
    assert 4 <= s["images_total"] <= 6 and s["images_oriented"] == s["images_total"]
    assert all(im["unit"] == "K" for im in s["images"])
    oc = OrientedCameras.load(tmp_path / "s")
    idx = [int(im.name.rsplit("_f", 1)[1]) for im in oc]
    est = np.array([im.center for im in oc])
    true = np.array([sc.frames[i].pose.center for i in idx])
    S = umeyama(est, true)
    rms = float(np.sqrt(np.mean(np.sum((S(est) - true) ** 2, axis=1))))
    # one strip of ~5 frames 4-5 m apart at 60 m, focal self-calibrated from a start 2.3x too short (no EXIF in a
    # video): measured 0.14 m after a similarity; a failed block is metres off
    assert rms < 0.3


# ------------------------------------------------------------------------------------------------------------------
# a low-texture facade walk: the fixed pattern (or a burned-in display) outweighs the scene


@pytest.fixture(scope="module")
def facade_walk():
    """40 frames 320x256 of a plain wall, ~2 % of the frame width apart with hand-held jitter (a 25 fps walk)."""
    from thermogrammetry.synthetic.lowtexture_facade import (LowTextureFacadeConfig, make_lowtexture_facade,
                                                             render_lowtexture_frame)

    sc = make_lowtexture_facade(LowTextureFacadeConfig(n_frames=40, overlap=0.98, jitter_deg=0.2, image_size=(320, 256),
                                                       pixel_pitch_um=34.0, supersample=1, seed=2))
    return sc, [render_lowtexture_frame(sc, k) for k in range(40)]


def _wall_flow(sc, a, b) -> float:
    """Median horizontal image motion from frame a to b as a fraction of the frame width (truth: rays of a pixel grid
    intersected with the wall and the ground)."""
    cam = sc.camera
    w, h = cam.image_size
    ys, xs = np.mgrid[8:h:16, 8:w:16]
    xy = np.c_[xs.ravel(), ys.ravel()].astype(float)
    pa, pb = sc.poses[a], sc.poses[b]
    r = cam.unproject(xy)
    d = (r / np.linalg.norm(r, axis=1, keepdims=True)) @ pa.R
    C = pa.center
    with np.errstate(divide="ignore"):
        t = np.minimum(np.where(d[:, 1] > 0, -C[1] / d[:, 1], np.inf), np.where(d[:, 2] < 0, -C[2] / d[:, 2], np.inf))
    X = C + t[:, None] * d
    return abs(float(np.median(cam.project(X @ pb.R.T + pb.t)[:, 0] - xy[:, 0]))) / w


@pytest.mark.parametrize("rendering", ["kelvin", "8-bit with a display"])
def test_frames_of_a_low_texture_walk_extracted_at_the_target_overlap(facade_walk, rendering, tmp_path):
    """Before the static pattern was projected out (phase correlation of the raw frames): 1-2 frames kept of 40, the
    correlation pinned at zero motion by the fixed pattern or the display."""
    import av

    from thermogrammetry.io.video import read_video_frames
    from thermogrammetry.synthetic.display import render_8bit
    from thermogrammetry.synthetic.survey import _VideoWriter

    sc, frames = facade_walk
    path = tmp_path / "walk.mkv"
    if rendering == "kelvin":
        wr = _VideoWriter(25.0)
        for k, a in enumerate(frames):
            wr.add(a, k / 25.0)
        path.write_bytes(wr.finish())
    else:
        with av.open(str(path), mode="w", format="matroska") as c:
            st = c.add_stream("ffv1", rate=25)
            st.width, st.height, st.pix_fmt = 320, 256, "gray"
            for k, a in enumerate(frames):
                fr = av.VideoFrame.from_ndarray(render_8bit(a, mode="grey", display=True), format="gray")
                fr.pts = k
                c.mux(st.encode(fr))
            c.mux(st.encode())
    kept = [f.index for f in read_video_frames(path, forward_overlap=0.8)]
    assert len(kept) == 4 and kept[0] == 0, kept
    steps = [_wall_flow(sc, i, i + 1) for i in range(kept[-1])]
    for a, b in zip(kept[:-1], kept[1:]):
        # a frame is kept at most one frame's motion past 20 % of the width; 0.01 for the estimate (measured <= 0.008)
        moved = _wall_flow(sc, a, b)
        assert 0.2 - 0.01 <= moved <= 0.2 + max(steps[a:b]) + 0.01, (a, b, moved)


def test_survey_video_overlap_option(video, tmp_path, capsys):
    """``--video-overlap`` sets the extraction's target: fewer frames at 0.6 than at 0.8 (4-6 frames there); a value
    outside [0, 1) is refused before anything is decoded."""
    import json

    from thermogrammetry.cli.main import main

    sc, _, path = video
    assert main(["survey", str(path), "-o", str(tmp_path / "bad"), "--video-overlap", "1.2"]) == 2
    assert "--video-overlap 1.2" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    main(["survey", str(path), "-o", str(tmp_path / "s"), "--gnss", "none", "--workers", "0", "--video-overlap", "0.6"])
    s = json.loads((tmp_path / "s" / "survey.json").read_text())
    assert 2 <= s["images_total"] <= 3  # 40 % of the frame height between kept frames: frames 0, ~15, ~30


def test_survey_keeps_the_frames_of_a_flir_recording_for_the_overlap():
    """A FLIR CSQ recording (8 hand-held frames of one scene, 1024x768): survey's inputs keep its frames like a video's
    (:class:`OverlapSelector`). Measured motion from frame 0: at most 14 px along x, 15 px along y (~1.5-2 % of the
    frame), so at 80 % overlap only the first frame is kept; at 99.5 % (5.1 / 3.8 px) a few (measured: 0, 3, 4, 5)."""
    from conftest import data_path

    from thermogrammetry.pipeline.survey import _decode

    p = data_path("flir_thermimage", "inst", "extdata", "SampleCSQ.csq")
    every = _decode(p, None, None)
    assert [d[0] for d in every] == [f"_f{k:05d}" for k in range(8)]
    kept = _decode(p, None, 0.8)
    assert [d[0] for d in kept] == ["_f00000"] and "frame 0 of 8 in the recording" in kept[0][5]
    dense = _decode(p, None, 0.995)
    assert 3 <= len(dense) <= 6 and dense[0][0] == "_f00000"
    for a, b in zip(every, every[1:]):
        assert a[1].shape == b[1].shape
    # the kept frames are the recording's own values
    by_name = {d[0]: d[1] for d in every}
    assert all(np.array_equal(d[1], by_name[d[0]]) for d in dense)


def test_overlap_selector_counts_what_it_could_measure():
    """Frames cut from one smooth random field 10 px apart (160 px wide, target 80 %: 32 px) are kept every 4th, every
    pair measured; frames from unrelated fields have no significant peak (``measured`` stays low, which makes survey
    keep every frame of such a recording) and only the first is kept."""
    import cv2

    from thermogrammetry.io.video import OverlapSelector

    rng = np.random.default_rng(5)
    field = cv2.GaussianBlur(rng.normal(size=(128, 260)).astype(np.float32), (0, 0), 2.0)
    sel = OverlapSelector(0.8)
    kept = [k for k in range(9) if sel(field[:, 10 * k:10 * k + 160])]
    assert kept == [0, 4, 8] and (sel.pairs, sel.measured) == (8, 8)
    sel = OverlapSelector(0.8)
    fields = [cv2.GaussianBlur(rng.normal(size=(128, 160)).astype(np.float32), (0, 0), 2.0) for _ in range(8)]
    kept = [k for k, f in enumerate(fields) if sel(f)]
    assert kept == [0] and sel.pairs == 7 and sel.measured <= 1


def test_survey_samples_a_video_whose_motion_cannot_be_measured(tmp_path):
    """40 frames of unrelated noise at 25 fps: no frame-to-frame motion can be measured, so instead of the first frame
    alone survey's inputs take a frame every 0.5 s (every 12th: 0, 12, 24, 36), each saying why."""
    from thermogrammetry.pipeline.survey import _decode_video
    from thermogrammetry.synthetic.survey import _VideoWriter

    rng = np.random.default_rng(3)
    wr = _VideoWriter(25.0)
    for k in range(40):
        wr.add((290.0 + rng.normal(0, 0.5, (96, 128))).astype(np.float32), k / 25.0)
    path = tmp_path / "noise.mkv"
    path.write_bytes(wr.finish())
    out = _decode_video(path, 0.8)
    assert [d[0] for d in out] == ["_f000000", "_f000012", "_f000024", "_f000036"]
    assert all("measurable in" in d[5] and "every 0.48 s" in d[5] for d in out)
