"""Real data: the Balbianello Bundler reconstruction (shared data ``balbianello``, gtsam, BSD).

The reference is a bundle-adjustment optimum. At that optimum the normal equations of each camera
with the points held fixed (space resection) and of each point with the cameras held fixed
(triangulation) are satisfied, so our resection and triangulation must return the reference
values up to the file's 11 significant digits and Bundler's own convergence tolerance — far
below the estimates' standard deviations. Bundler's camera looks down −z with y up; our frame
is diag(1, −1, −1) of it, image coordinates are relative to the image centre with y up.
"""

import numpy as np
import pytest

from conftest import data_path
from thermogrammetry import Camera
from thermogrammetry.geometry import Pose, resection, triangulate
from thermogrammetry.geometry import rotations as rot
from thermogrammetry.results import Termination

pytestmark = pytest.mark.realdata

W, H = 640, 427
FLIP = np.diag([1.0, -1.0, -1.0])


def _read_bundler(path):
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# Bundle file v0.3")
    tok = iter(" ".join(lines[1:]).split())
    nc, npts = int(next(tok)), int(next(tok))
    cams, poses = [], []
    for _ in range(nc):
        f, k1, k2 = (float(next(tok)) for _ in range(3))
        R = np.array([float(next(tok)) for _ in range(9)]).reshape(3, 3)
        t = np.array([float(next(tok)) for _ in range(3)])
        cams.append(Camera("opencv", (W, H), dict(fx=f, fy=f, cx=(W - 1) / 2, cy=(H - 1) / 2, k1=k1, k2=k2)))
        poses.append(Pose(FLIP @ R, FLIP @ t))
    pts = np.zeros((npts, 3))
    xy = np.full((nc, npts, 2), np.nan)
    mask = np.zeros((nc, npts), bool)
    for j in range(npts):
        pts[j] = [float(next(tok)) for _ in range(3)]
        for _ in range(3):
            next(tok)  # colour
        for _ in range(int(next(tok))):
            c, _key, x, y = int(next(tok)), next(tok), float(next(tok)), float(next(tok))
            xy[c, j] = [x + (W - 1) / 2, -y + (H - 1) / 2]
            mask[c, j] = True
    return cams, poses, pts, xy, mask


@pytest.fixture(scope="module")
def balbianello():
    return _read_bundler(data_path("balbianello", "Balbianello.out"))


def test_resection_reproduces_bundler_cameras(balbianello):
    cams, poses, pts, xy, mask = balbianello
    for c, (cam, ref) in enumerate(zip(cams, poses)):
        sel = mask[c]
        r = resection(cam, pts[sel], xy[c, sel])
        assert r.termination is Termination.CONVERGED and r.init_method == "dlt"
        assert 0.2 < r.rms_px < 0.4  # Bundler's image residuals are ≈ 0.24–0.34 px RMS
        zC = np.abs(r.center - ref.center) / r.center_std
        dR = rot.axis_angle_from_matrix(ref.R.T @ r.pose.R)  # same increment as covariance_increment
        zR = np.abs(dR) / np.sqrt(np.diag(r.covariance_increment)[:3])
        # measured: ≤ 0.06 σ (camera 5, 100 points); 0.15 σ leaves room for rounding, not for a wrong model
        assert zC.max() < 0.15 and zR.max() < 0.15, (c, zC, zR)


def test_triangulation_reproduces_bundler_points(balbianello):
    cams, poses, pts, xy, mask = balbianello
    r = triangulate(cams, poses, xy, mask=mask, sigma_px=0.3)  # σ from the residual RMS above
    assert r.outcome.termination is Termination.CONVERGED
    assert r.n_views.min() >= 2 and r.points.shape == (544, 3)
    z = np.abs(r.points - pts) / r.std
    assert np.max(z) < 0.1, np.max(z)
