"""The pixel rays of a view (``products.texture_visibility._pixel_grid_rays``) computed once per camera: the shared
array holds what a new ``unproject`` of the same pixels gives, bit for bit, for both camera models."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry.camera import Camera
from thermogrammetry.products.texture_visibility import _pixel_grid_rays


@pytest.mark.parametrize("camera", [
    Camera("opencv", (64, 48), dict(fx=60.0, fy=60.5, cx=31.7, cy=23.2, k1=-0.3, k2=0.1, p1=1e-3, p2=-2e-3, k3=0.01)),
    Camera("photogrammetric", (64, 48), dict(c_mm=2.0, x0_mm=0.01, y0_mm=-0.02, K1=1e-3, K2=-1e-6, P1=1e-5),
           pixel_pitch_um=17),
], ids=["opencv", "photogrammetric"])
def test_shared_rays_equal_a_new_unprojection(camera):
    w, h = camera.image_size
    gy, gx = np.mgrid[0:h, 0:w].astype(float)
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    rays = _pixel_grid_rays(camera)
    assert rays.shape == (w * h, 3) and not rays.flags.writeable
    # in pieces and in reverse order: each ray depends on its own pixel only
    assert np.array_equal(rays, np.concatenate([camera.unproject(xy[a:a + 777]) for a in range(0, len(xy), 777)]))
    assert np.array_equal(rays, camera.unproject(xy[::-1])[::-1])
    assert _pixel_grid_rays(Camera.from_dict(camera.to_dict())) is rays  # an equal camera shares them
    other = camera.replace(**{camera.param_names[0]: camera.params[0] * 1.01})
    assert not np.array_equal(_pixel_grid_rays(other), rays)
