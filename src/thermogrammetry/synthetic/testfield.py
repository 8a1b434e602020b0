"""Synthetic 3D test field after seed 001: 77 targets on three depth planes, FLIR A320, four rolls.

Seed 001 (Yastikli & Guler 2013) calibrates a FLIR A320 (320 × 240 px, 25 µm pitch, 18 mm lens) on a
3D test object with 77 control points distributed over three planes about 70 cm apart, imaged
from several positions with rolls of 0°, 90°, 180° and 270°. The object's exact layout is not
published; this module builds a deterministic field of the same kind:

* world frame: X to the right, Y away from the cameras (depth), Z up; metres;
* front plane Y = 0.0 (6 × 3 = 18 targets, 1.6 m × 0.8 m), middle plane Y = 0.7 (6 × 4 = 24
  targets, 2.0 m × 1.3 m), back plane Y = 1.4 (7 × 5 = 35 targets, 2.6 m × 1.8 m): 77 targets;
  the rows of the planes are staggered so that targets do not hide each other from the stations;
* stations on an arc about 7 m in front of the field (default 4 positions), each with the four rolls;
* camera: correction-form (photogrammetric) model with the values of seed 001 Table 2
  (:func:`flir_a320_table2_params`).

Image measurements are the exact projections plus independent Gaussian noise (default 0.4 px per
coordinate). Observations outside the image are dropped; so are the few where the published
distortion polynomial folds over (``1 + dΔr/dr < fold_guard``): Table 2's K1–K3 make
``r + Δr(r)`` reach its maximum at r ≈ 5.5 mm, just beyond the image corners (≈ 5.35 mm from the
principal point), where a measurement could not be interpreted uniquely.

References
----------
Yastikli, N., Guler, E., 2013. Performance evaluation of thermographic cameras for photogrammetric
measurements. ISPRS Arch. XL-1/W1 (seed 001), Tables 1, 2 and 4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera.models import PARAM_NAMES as _MODEL_PARAM_NAMES
from ..camera.models import CameraModel, photogrammetric_correction_jacobian, photogrammetric_project_solve

PARAM_NAMES = _MODEL_PARAM_NAMES[CameraModel.PHOTOGRAMMETRIC]

__all__ = [
    "FLIR_A320_IMAGE_SIZE",
    "FLIR_A320_PIXEL_PITCH_UM",
    "FLIR_A320_NOMINAL_FOCAL_MM",
    "flir_a320_table2_params",
    "testfield_points",
    "TestFieldTruth",
    "TestField",
    "make_testfield",
    "resample_noise",
    "look_at_pose",
]

FLIR_A320_IMAGE_SIZE = (320, 240)
FLIR_A320_PIXEL_PITCH_UM = 25.0
FLIR_A320_NOMINAL_FOCAL_MM = 18.0


def flir_a320_table2_params() -> dict[str, float]:
    """Seed 001 Table 2 (FLIR A320), correction form, units of the table (mm, mm⁻², ...).

    The table prints e.g. ``K1 = -30.6381 * 10^-4``; the values below are those numbers with
    their scale applied. B1, B2, K4, K5 were not estimated in seed 001 and are zero.
    """
    return {
        "c_mm": 17.2262,
        "x0_mm": 0.2883,
        "y0_mm": -0.1995,
        "K1": -30.6381e-4,
        "K2": 2599.4545e-7,
        "K3": -98791.5437e-10,
        "K4": 0.0,
        "K5": 0.0,
        "P1": -22.6353e-5,
        "P2": 28.1114e-5,
        "B1": 0.0,
        "B2": 0.0,
    }


def testfield_points() -> tuple[np.ndarray, np.ndarray]:
    """The 77 target IDs (``"T01"`` ...) and coordinates (77, 3) in metres (see module docstring)."""
    planes = [  # (Y depth, ncols, nrows, width, height, x stagger)
        (0.0, 6, 3, 1.6, 0.8, 0.0),
        (0.7, 6, 4, 2.0, 1.3, 0.09),
        (1.4, 7, 5, 2.6, 1.8, -0.05),
    ]
    pts = []
    for y, nc, nr, wd, ht, sx in planes:
        xs = np.linspace(-wd / 2, wd / 2, nc) + sx
        zs = np.linspace(-ht / 2, ht / 2, nr) + (0.06 if y == 0.7 else 0.0)
        for j, z in enumerate(zs):
            for i, x in enumerate(xs):
                # small deterministic irregularity, as on a welded frame
                dx = 0.013 * np.sin(3.1 * i + 1.7 * j + y)
                dz = 0.011 * np.cos(2.3 * i - 1.1 * j + 2 * y)
                pts.append((x + dx, y, z + dz))
    xyz = np.asarray(pts, dtype=float)
    ids = np.array([f"T{k + 1:02d}" for k in range(len(xyz))])
    return ids, xyz


def look_at_pose(center: np.ndarray, target: np.ndarray, roll_deg: float = 0.0, up=(0.0, 0.0, 1.0)):
    """``cam_from_world`` (R, t) of a camera at ``center`` looking at ``target`` (x right, y down,
    z forward), rotated by ``roll_deg`` about its optical axis."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    a = np.deg2rad(roll_deg)
    Rz = np.array([[np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ R
    t = -R @ np.asarray(center, float)
    return R, t


@dataclass(frozen=True)
class TestFieldTruth:
    """Exact values behind a synthetic test-field calibration."""

    params: np.ndarray  # (12,) correction-form parameters, layout camera.models.PARAM_NAMES['photogrammetric']
    image_size: tuple[int, int]
    pixel_pitch_um: float
    point_ids: np.ndarray  # (77,) str
    points: np.ndarray  # (77,3) m
    image_names: tuple[str, ...]
    R: np.ndarray  # (F,3,3) cam_from_world
    t: np.ndarray  # (F,3)
    roll_deg: np.ndarray  # (F,)
    noise_px: float

    @property
    def param_dict(self) -> dict[str, float]:
        return dict(zip(PARAM_NAMES, map(float, self.params)))


@dataclass(frozen=True)
class TestField:
    """Measurements of one synthetic test-field session, with the truth."""

    truth: TestFieldTruth
    obs_image: np.ndarray  # (N,) int index into truth.image_names
    obs_point: np.ndarray  # (N,) int index into truth.points
    xy_true_px: np.ndarray  # (N,2) exact projections (OpenCV pixel convention)
    xy_px: np.ndarray  # (N,2) noisy measurements

    def control_csv(self) -> str:
        """Control file text ``id,X,Y,Z`` (metres)."""
        lines = ["id,X,Y,Z"]
        for i, p in zip(self.truth.point_ids, self.truth.points):
            lines.append(f"{i},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}")
        return "\n".join(lines) + "\n"

    def measurements_csv(self) -> str:
        """Measurement file text ``image,id,x,y`` (pixels)."""
        lines = ["image,id,x,y"]
        for f, m, xy in zip(self.obs_image, self.obs_point, self.xy_px):
            lines.append(f"{self.truth.image_names[f]},{self.truth.point_ids[m]},{xy[0]:.5f},{xy[1]:.5f}")
        return "\n".join(lines) + "\n"


def make_testfield(
    rng: np.random.Generator,
    *,
    noise_px: float = 0.4,
    rolls_deg=(0.0, 90.0, 180.0, 270.0),
    n_positions: int = 4,
    distance_m: float = 7.0,
    params: dict[str, float] | None = None,
    fold_guard: float = 0.5,
) -> TestField:
    """Simulate a seed-001-like calibration session.

    Parameters
    ----------
    rng : numpy Generator (seeded by the caller).
    noise_px : standard deviation of the Gaussian noise added to each image coordinate (px).
    rolls_deg : rolls applied at every position (seed 001: 0, 90, 180, 270).
    n_positions : number of camera positions on an arc in front of the field (azimuths spread
        over ±35°, heights alternating ±0.8 m).
    distance_m : distance of the positions from the field centre.
    params : correction-form parameters (default :func:`flir_a320_table2_params`).
    fold_guard : drop observations where ``det(I + ∂Δ/∂x̄)`` is below this value (see module doc).

    Returns
    -------
    TestField with noisy measurements and the exact truth.
    """
    p = flir_a320_table2_params()
    if params:
        unknown = set(params) - set(p)
        if unknown:
            from ..errors import ConfigError

            raise ConfigError(f"unknown camera parameter(s) {sorted(unknown)}; expected names from {list(p)}")
        p.update(params)
    pvec = np.array([p[k] for k in PARAM_NAMES])
    ids, xyz = testfield_points()
    target = np.array([0.0, 0.7, 0.0])
    az = np.deg2rad(np.linspace(-35.0, 35.0, n_positions)) if n_positions > 1 else np.zeros(1)
    Rs, ts, names, rolls = [], [], [], []
    for k, a in enumerate(az):
        hz = 0.8 if k % 2 == 0 else -0.8
        C = target + np.array([distance_m * np.sin(a), -distance_m * np.cos(a), hz])
        for roll in rolls_deg:
            R, t = look_at_pose(C, target, roll)
            Rs.append(R)
            ts.append(t)
            names.append(f"P{k + 1}_R{int(round(roll)):03d}")
            rolls.append(roll)
    R = np.asarray(Rs)
    t = np.asarray(ts)
    pitch_mm = (FLIR_A320_PIXEL_PITCH_UM * 1e-3,) * 2
    w, h = FLIR_A320_IMAGE_SIZE
    oi, op, xyt = [], [], []
    for f in range(R.shape[0]):
        Xc = xyz @ R[f].T + t[f]
        front = Xc[:, 2] > 1e-12
        xy, ok = photogrammetric_project_solve(pvec, np.where(front[:, None], Xc, 1.0), FLIR_A320_IMAGE_SIZE,
                                               (FLIR_A320_PIXEL_PITCH_UM,) * 2)
        ok = ok & front
        xb = (xy[:, 0] - (w - 1) / 2) * pitch_mm[0] - pvec[1]
        yb = -(xy[:, 1] - (h - 1) / 2) * pitch_mm[1] - pvec[2]
        # Js = I + d(correction)/d(xb, yb): its determinant guards against the fold of the polynomial
        _, Js, _ = photogrammetric_correction_jacobian(pvec, np.stack([xb, yb], axis=1))
        det = Js[:, 0, 0] * Js[:, 1, 1] - Js[:, 0, 1] * Js[:, 1, 0]
        inside = (xy[:, 0] >= 1) & (xy[:, 0] <= w - 2) & (xy[:, 1] >= 1) & (xy[:, 1] <= h - 2)
        keep = ok & inside & (det > fold_guard)
        idx = np.nonzero(keep)[0]
        oi.append(np.full(idx.size, f))
        op.append(idx)
        xyt.append(xy[idx])
    obs_image = np.concatenate(oi)
    obs_point = np.concatenate(op)
    xy_true = np.concatenate(xyt)
    truth = TestFieldTruth(pvec, FLIR_A320_IMAGE_SIZE, FLIR_A320_PIXEL_PITCH_UM, ids, xyz, tuple(names), R, t,
                           np.asarray(rolls), float(noise_px))
    xy = xy_true + rng.normal(0.0, noise_px, size=xy_true.shape)
    return TestField(truth, obs_image, obs_point, xy_true, xy)


def resample_noise(field: TestField, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """New noisy measurements of the same observations: (N,2), or (n,N,2) when ``n`` is given."""
    shape = field.xy_true_px.shape if n is None else (n,) + field.xy_true_px.shape
    return field.xy_true_px + rng.normal(0.0, field.truth.noise_px, size=shape)
