"""A camera's display burned into 8-bit thermal renderings: found from the frames (``sfm.features.static_overlay``) and
kept out of the tie points (``survey``'s features step).

The frames: a camera moving over a textured plane (crops of one smooth random field shifted 40 px a frame, 320x256),
rendered as a camera exports them (per-frame stretch) with the display of ``synthetic.display`` burned in: the maker's
name, a spot reading, a cross-hair, a colour bar with the frame's range (readings change from frame to frame), the date.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from thermogrammetry.sfm.features import static_overlay
from thermogrammetry.synthetic.display import display_mask, render_8bit

H, W = 256, 320


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    fine = cv2.GaussianBlur(rng.normal(0, 1, (700, 1200)).astype(np.float32), (0, 0), 3.0)
    coarse = cv2.GaussianBlur(rng.normal(0, 1, (700, 1200)).astype(np.float32), (0, 0), 25.0)
    field = 290.0 + 2.0 * fine / fine.std() + 30.0 * coarse
    return [field[100 + int(20 * np.sin(k)):, 20 + 40 * k:][:H, :W] for k in range(20)]


def _drawn(frames, mode="grey"):
    """Pixels where the display changed a rendering by more than 20 grey levels in at least one frame."""
    out = np.zeros((H, W), bool)
    for f in frames:
        a, b = (render_8bit(f, mode=mode, display=d) for d in (False, True))
        if a.ndim == 3:
            a, b = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (a, b))
        out |= np.abs(a.astype(int) - b) > 20
    return out


def _near_display(extra_px: int) -> np.ndarray:
    r = extra_px
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(display_mask(H, W).astype(np.uint8), k).astype(bool)


@pytest.mark.parametrize("mode", ["grey", "palette"])
def test_display_is_found_and_nothing_else(frames, mode):
    """Measured: the mask covers 99.7 % (grey) / 100 % (palette, as luminance) of the pixels the display changes by
    > 20 grey levels, 8.8 % / 8.7 % of the frame, every masked pixel within the dilation (4 px at 320 px) + 2 px of
    the display. Bounds: >= 98 % covered (the digits of readings change from frame to frame), all masked pixels near the
    display, 6-12 % of the frame."""
    imgs = [render_8bit(f, mode=mode, display=True) for f in frames]
    if mode == "palette":
        imgs = [cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in imgs]  # what the survey's decoding makes of a palette
    m = static_overlay(imgs)
    assert m is not None and m.shape == (H, W)
    drawn = _drawn(frames, mode)
    assert (m & drawn).sum() / drawn.sum() >= 0.98
    assert not (m & ~_near_display(4 + 2)).any()
    assert 0.06 < m.mean() < 0.12


def test_no_display_no_mask(frames):
    """The same frames without the display, and the float frames themselves: nothing found. Fewer than 8 frames: too
    few to tell a display from the scene."""
    assert static_overlay([render_8bit(f) for f in frames]) is None
    assert static_overlay(frames) is None
    assert static_overlay([render_8bit(f, display=True) for f in frames[:7]]) is None


def test_display_mask_covers_what_is_drawn(frames):
    """``display_mask`` (the test's truth) holds every pixel the display changes."""
    assert not (_drawn(frames) & ~display_mask(H, W)).any()


def test_survey_features_avoid_the_display(tmp_path, frames):
    """The features step finds the display in 8-bit frames (``work/overlay.json``) and puts no tie point inside its
    mask; the same frames without the display: nothing found, features everywhere."""
    from PIL import Image

    from thermogrammetry.pipeline import MemoryProject
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, step_features, step_inputs

    truth = display_mask(H, W)
    for display in (True, False):
        d = tmp_path / f"d{int(display)}"
        d.mkdir()
        for k, f in enumerate(frames[:12]):
            Image.fromarray(render_8bit(f, mode="palette", display=display)).save(d / f"F{k:03d}.jpg", quality=92)
        proj = MemoryProject()
        opt = SurveyOptions(gnss="none", workers=0)
        step_inputs(proj, SurveyInput([str(d)]), opt)
        step_features(proj, opt)
        ov = proj.read_json("work/overlay.json")
        xy = np.concatenate([np.load(__import__("io").BytesIO(proj.read_bytes(f"features/F{k:03d}.npz")))["xy"]
                             for k in range(12)])
        ij = np.clip(np.round(xy).astype(int), 0, [W - 1, H - 1])
        in_display = int(truth[ij[:, 1], ij[:, 0]].sum())
        if display:
            assert ov["found"] and ov["images"] == 12 and ov["frames"] == 12 and ov["size"] == [W, H]
            assert 0.06 < ov["share"] < 0.12
            assert in_display == 0, in_display
        else:
            assert ov == {"found": False}
            assert in_display > 50  # the display's area is textured scene like the rest: features there


def test_survey_reports_the_display(tmp_path):
    """A 10-frame low-texture walk (``synthetic.lowtexture_facade``) exported as 8-bit palette JPEGs with the display
    burned in, through ``run_survey`` with the defaults: the display is found in all 10 frames and reported in
    ``survey.json`` (``overlay``), its notes and the report; the walk is oriented (measured 10/10 in one block, 8.8 %
    of the frame masked, 8 s). No accuracy bound: without an EXIF focal length the walk's rotations are several degrees
    off (benchmarks/README.md, "What the tracked walk needs")."""
    from PIL import Image

    from thermogrammetry.pipeline import MemoryProject
    from thermogrammetry.pipeline.survey import SurveyInput, SurveyOptions, run_survey
    from thermogrammetry.synthetic.lowtexture_facade import (LowTextureFacadeConfig, make_lowtexture_facade,
                                                             render_lowtexture_frame)

    sc = make_lowtexture_facade(LowTextureFacadeConfig(n_frames=10))
    for k in range(10):
        img = render_8bit(render_lowtexture_frame(sc, k), mode="palette", display=True)
        Image.fromarray(img).save(tmp_path / f"F{k:03d}.jpg", quality=92)
    p = MemoryProject()
    run_survey(p, SurveyInput([str(tmp_path)]), SurveyOptions(gnss="none", workers=0))
    s = p.read_json("survey.json")
    ov = s["overlay"]
    assert ov["frames"] == 10 and ov["images"] == 10 and ov["size"] == [640, 512]
    assert 0.06 < ov["share"] < 0.12
    note = [n for n in s["notes"] if "display burned into the 8-bit frames" in n]
    assert len(note) == 1 and f"{100 * ov['share']:.1f} %" in note[0]
    assert "display burned into the 8-bit frames" in p.read_text("report.html")
    assert s["components"] and s["components"][0] >= 8
    # no focal length in the JPEGs: the user is told that the walk determines it only weakly
    assert sum("focal length of thermal is not known" in n for n in s["notes"]) == 1
