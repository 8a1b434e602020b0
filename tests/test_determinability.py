"""The determinability figures of a block (sfm.determinability) from a covariance with known structure."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.camera import Camera
from thermogrammetry.sfm.determinability import block_determinability


def _camera():
    return Camera("opencv", (320, 256), {"fx": 380.0, "fy": 380.0, "cx": 160.0, "cy": 128.0, "k1": -0.2, "k2": 0.05,
                                         "k3": 0.0, "p1": 0.0, "p2": 0.0})


def _names(n):
    return (["camera0.fx", "camera0.k1", "camera0.k2", "camera0.k3"]
            + [f"image{j}.{a}" for j in range(n) for a in ("wx", "wy", "wz", "X0", "Y0", "Z0")])


def test_focal_length_and_flying_height_as_one_unknown_and_the_corner_displacement():
    """Over flat ground f and the heights move together: Z0_j = H f / f0 + independent noise. With σ(f) = 19 px
    (5 %), H = 50 m and 0.05 m of independent noise per camera, corr(f, Z̄) is σ_a / sqrt(σ_a² + 0.05²/n) with
    σ_a = 50 · 0.05 = 2.5 m (closed form); the corner displacement's σ is checked against sampling."""
    rng = np.random.default_rng(0)
    n = 20
    names = _names(n)
    P = len(names)
    f0, H, sf = 380.0, 50.0, 19.0
    A = np.zeros((P, 5))  # factors: f, k1, k2, k3, and per-camera noise added below
    A[0, 0] = sf
    z = [k for k, nm in enumerate(names) if nm.endswith(".Z0")]
    A[z, 0] = H * sf / f0
    Lk = np.linalg.cholesky(np.array([[4e-4, -2e-4, 0.0], [-2e-4, 3e-4, 1e-5], [0.0, 1e-5, 1e-4]]))
    A[1:4, 1:4] = Lk
    cov = A @ A.T + np.diag(np.r_[np.zeros(4), np.tile([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 0.05**2], n)])
    d = block_determinability(cov, names, {"camera0": ("thermal", _camera())})["thermal"]
    assert d["focal_sigma_rel"] == pytest.approx(sf / f0, rel=1e-12)
    sa = H * sf / f0
    assert d["focal_height_correlation"] == pytest.approx(sa / np.sqrt(sa**2 + 0.05**2 / n), rel=1e-9)
    assert d["mean_height_sigma_m"] == pytest.approx(np.sqrt(sa**2 + 0.05**2 / n), rel=1e-9)
    # the radial displacement at the corner, sampled from the k's covariance: its scatter is the reported σ
    cam = _camera()
    r2 = (160 / 380.0) ** 2 + (128 / 380.0) ** 2
    k = rng.multivariate_normal(np.zeros(3), cov[1:4, 1:4], 200_000)
    disp = 380.0 * np.sqrt(r2) * (k[:, 0] * r2 + k[:, 1] * r2**2 + k[:, 2] * r2**3)
    # 200 000 samples: the sample σ's relative standard error is 1/sqrt(2 · 2e5) = 0.16 %; 1 % is 6 of those
    assert d["distortion_corner_sigma_px"] == pytest.approx(float(np.std(disp)), rel=0.01)
    assert cam.image_size == (320, 256)
    # a block where the heights do not move with f: no correlation
    cov2 = cov.copy()
    cov2[0, z] = cov2[z, 0] = 0.0
    assert abs(block_determinability(cov2, names, {"camera0": ("thermal", cam)})["thermal"]["focal_height_correlation"]) < 1e-12


def test_held_cameras_and_missing_covariances_give_nothing():
    names = [f"image0.{a}" for a in ("wx", "wy", "wz", "X0", "Y0", "Z0")]
    assert block_determinability(np.eye(6), names, {"camera0": ("thermal", _camera())}) == {}
    assert block_determinability(None, names, {"camera0": ("thermal", _camera())}) == {}
    assert block_determinability(np.eye(5), names, {"camera0": ("thermal", _camera())}) == {}
