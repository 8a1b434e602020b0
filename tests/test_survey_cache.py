"""``survey --cache DIR``: features and verified matches kept by content. A survey that reads them gives the same
outputs, byte for byte, as one that computes them; what changes the features (the frame, the options) or the
matches (a camera) is a miss, never a stale hit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thermogrammetry.cli.main import main

from survey_truth import SMALL_BLOCK_FRAMES as FRAMES
from survey_truth import write_small_block


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    root = tmp_path_factory.mktemp("cacheblock")
    return root, write_small_block(root)[1]


def _outputs(out):
    """The files a user reads, survey.json without its timings and its cache counts."""
    s = json.loads((out / "survey.json").read_text())
    s.pop("seconds", None)
    s.pop("steps", None)
    return {"survey": s, "cameras": (out / "cameras.json").read_bytes(), "ply": (out / "sparse.ply").read_bytes(),
            "colmap": (out / "colmap" / "images.txt").read_bytes()}


def _from_cache(out):
    """(features, pairs) read from the cache, from the step reports; (features tried, pairs tried)."""
    f = json.loads((out / "reports" / "features.json").read_text())["summary"]
    m = json.loads((out / "reports" / "matching.json").read_text())["summary"]
    return (f.get("from_cache"), m.get("from_cache", {}).get("pairs")), (f["images"], m["pairs_tried"])


def test_a_survey_from_the_cache_equals_one_without(block, tmp_path):
    """The first survey computes and fills the cache, the second reads every image and every pair from it: the
    same files (computing with a cache is computing without one: the cache only keeps a copy)."""
    root, args = block
    cache = tmp_path / "cache"
    assert main(["survey", str(root / "images"), "-o", str(tmp_path / "fill"), *args, "--cache", str(cache)]) == 0
    assert main(["survey", str(root / "images"), "-o", str(tmp_path / "read"), *args, "--cache", str(cache)]) == 0
    fill, read = _outputs(tmp_path / "fill"), _outputs(tmp_path / "read")
    assert fill["survey"]["images_oriented"] == len(FRAMES)
    assert read == fill
    (f0, p0), tried = _from_cache(tmp_path / "fill")
    assert (f0, p0) == (0, 0) and tried[1] > 0
    assert _from_cache(tmp_path / "read")[0] == tried  # every image and every pair read back
    assert len(list((cache / "features").glob("*.npz"))) == len(FRAMES)
    assert len(list((cache / "matches").glob("*.npz"))) == tried[1]


def test_what_changes_the_ties_changes_the_key():
    """A frame, a feature option, either image's features, a starting camera or a matching option each give
    another key; equal inputs the same key."""
    from dataclasses import replace

    from thermogrammetry.camera import Camera
    from thermogrammetry.pipeline.survey.cache import TieCache
    from thermogrammetry.sfm.features import FeatureOptions
    from thermogrammetry.sfm.matching import MatchOptions

    rng = np.random.default_rng(0)
    frame = rng.normal(300, 1, (24, 32)).astype(np.float32)
    fo = FeatureOptions()
    k = TieCache.features_key(frame, fo)
    assert TieCache.features_key(frame.copy(), FeatureOptions()) == k
    other = frame.copy()
    other[5, 7] += 0.01
    assert TieCache.features_key(other, fo) != k
    assert TieCache.features_key(frame.astype(np.float64), fo) != k
    assert TieCache.features_key(frame, replace(fo, max_features=fo.max_features - 1)) != k
    fi = {"xy": rng.random((10, 2)), "descriptors": rng.random((10, 128)).astype(np.float32)}
    fj = {"xy": rng.random((12, 2)), "descriptors": rng.random((12, 128)).astype(np.float32)}
    cam = Camera("opencv", (32, 24), dict(fx=30.0, fy=30.0, cx=15.5, cy=11.5))
    mo = MatchOptions()
    m = TieCache.matches_key(fi, fj, cam, cam, mo)
    assert TieCache.matches_key({k_: v.copy() for k_, v in fi.items()}, fj, cam, Camera.from_dict(cam.to_dict()), mo) == m
    assert TieCache.matches_key(fj, fi, cam, cam, mo) != m
    moved = {**fi, "xy": fi["xy"] + np.r_[1e-9, 0.0]}
    assert TieCache.matches_key(moved, fj, cam, cam, mo) != m
    assert TieCache.matches_key(fi, fj, cam, cam.replace(fx=30.001), mo) != m
    assert TieCache.matches_key(fi, fj, None, None, mo) != m
    assert TieCache.matches_key(fi, fj, cam, cam, replace(mo, ratio=mo.ratio - 0.01)) != m


def test_a_cache_path_that_is_a_file_is_refused(block, tmp_path, capsys):
    root, args = block
    bad = tmp_path / "cache.txt"
    bad.write_text("mine")
    code = main(["survey", str(root / "images"), "-o", str(tmp_path / "out"), *args, "--cache", str(bad)])
    assert code == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "is a file" in err
    assert bad.read_text() == "mine" and not (tmp_path / "out").exists()


def test_a_tracked_sequence_comes_back_from_the_cache_as_tracked(tmp_path):
    """The low-texture tracker's result (4 frames of the synthetic plain-wall walk, tracked by
    ``sfm.lowtexture.track_sequence``) is kept under a key of its frames, pattern, cameras and options, and read back
    equal array for array; the key changes with a frame, the pattern, a camera and an option."""
    from dataclasses import replace

    from thermogrammetry.camera import Camera
    from thermogrammetry.pipeline.survey.cache import TieCache
    from thermogrammetry.sfm.lowtexture import TrackingOptions, track_sequence
    from thermogrammetry.synthetic.lowtexture_facade import (LowTextureFacadeConfig, make_lowtexture_facade,
                                                             render_lowtexture_frame)

    sc = make_lowtexture_facade(LowTextureFacadeConfig(n_frames=4))
    frames = [render_lowtexture_frame(sc, k) for k in range(4)]
    cams = [sc.camera] * 4
    st = track_sequence(lambda k: frames[k], 4, cameras=cams)
    assert st.matches, st.reasons  # something to keep
    cache = TieCache(tmp_path / "cache")
    opt = TrackingOptions()
    key = cache.tracks_key(iter(frames), None, cams, opt)
    assert cache.get_tracks(key) is None
    cache.put_tracks(key, st)
    back = cache.get_tracks(key)
    assert len(back.xy) == 4 and all(np.array_equal(a, b) for a, b in zip(st.xy, back.xy))
    assert back.matches.keys() == st.matches.keys()
    assert all(np.array_equal(st.matches[k], back.matches[k]) for k in st.matches)
    assert back.reasons == st.reasons and back.n_putative == st.n_putative
    other = frames[:3] + [frames[3] + np.float32(0.001)]
    cam2 = Camera("opencv", sc.camera.image_size, {**sc.camera.param_dict, "fx": sc.camera.param_dict["fx"] + 1.0})
    keys = {key, cache.tracks_key(iter(other), None, cams, opt),
            cache.tracks_key(iter(frames), np.zeros_like(frames[0]), cams, opt),
            cache.tracks_key(iter(frames), None, cams[:3] + [cam2], opt),
            cache.tracks_key(iter(frames), None, cams, replace(opt, window_px=opt.window_px + 2))}
    assert len(keys) == 5
