"""sfm.meshfit: the survey's poses fitted to the mesh being textured (tie points on the surface)."""

from __future__ import annotations

import numpy as np
import pytest

from thermogrammetry import Camera
from thermogrammetry.sfm.meshfit import (MeshFitOptions, TiePoints, closest_faces, closest_point_on_triangles,
                                         fit_poses_to_mesh)


def _rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _angle_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_closest_point_on_triangles_matches_dense_sampling():
    rng = np.random.default_rng(0)
    n = 200
    A, B, C = (rng.normal(size=(n, 3)) for _ in range(3))
    C[:5] = A[:5] + 0.5 * (B[:5] - A[:5])  # degenerate (collinear) triangles
    P = rng.normal(size=(n, 3)) * 2
    q = closest_point_on_triangles(P, A, B, C)
    d = np.linalg.norm(P - q, axis=1)
    # dense barycentric sampling (step 1/400) of every triangle: its best distance is at most one sample spacing
    # above the exact one, never below it
    s = np.linspace(0, 1, 401)
    u, v = np.meshgrid(s, s)
    m = (u + v) <= 1
    u, v = u[m], v[m]
    for k in range(n):
        S = A[k] + u[:, None] * (B[k] - A[k]) + v[:, None] * (C[k] - A[k])
        ds = np.linalg.norm(S - P[k], axis=1).min()
        edge = max(np.linalg.norm(B[k] - A[k]), np.linalg.norm(C[k] - A[k]))
        assert d[k] <= ds + 1e-9
        assert ds - d[k] <= 2 * edge / 400 + 1e-9


def test_closest_faces_matches_exhaustive_search():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(300, 3))
    P = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(4.5, 5.5, (300, 1))
    face, dist = closest_faces(V, F, P)
    T = V[F]
    exact = np.array([np.linalg.norm(p - closest_point_on_triangles(np.repeat(p[None], len(F), 0), T[:, 0], T[:, 1], T[:, 2]),
                                     axis=1).min() for p in P])
    np.testing.assert_allclose(dist, exact, rtol=0, atol=1e-12)


def _box_ring(n_st=24, noise_px=0.3, seed=0):
    """A 10 x 8 x 6 m box (walls as two triangles each, roof) and stations at 1.7 m height around it, looking at
    its centre; tie points on the walls, seen with ``noise_px`` noise."""
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1, h = 0.0, 10.0, 0.0, 8.0, 6.0
    V = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0], [x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]], float)
    F = np.array([[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7], [4, 5, 6], [4, 6, 7]])
    cam = Camera("opencv", (640, 480), dict(fx=500.0, fy=500.0, cx=319.5, cy=239.5), name="thermal")
    centre = np.array([5.0, 4.0, 3.0])
    poses, C = [], []
    for a in np.linspace(0, 2 * np.pi, n_st, endpoint=False):
        c = np.array([5 + 13 * np.cos(a), 4 + 12 * np.sin(a), 1.7])
        z = centre - c
        z /= np.linalg.norm(z)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        poses.append((R, -R @ c))
        C.append(c)
    # points on the four walls
    walls = [((x0, y0), (x1, y0), (0, -1)), ((x1, y0), (x1, y1), (1, 0)), ((x1, y1), (x0, y1), (0, 1)), ((x0, y1), (x0, y0), (-1, 0))]
    P = []
    for (a, b, nrm) in walls:
        t = rng.uniform(0.05, 0.95, 250)
        zz = rng.uniform(0.3, 5.7, 250)
        P.append(np.column_stack([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), zz]))
    P = np.concatenate(P)
    normals = np.concatenate([np.repeat([[*nrm, 0.0]], 250, 0) for *_, nrm in walls])
    op, oi, oxy = [], [], []
    for i, (R, t) in enumerate(poses):
        Xc = P @ R.T + t
        xy = cam.project(Xc)
        facing = np.einsum("ij,ij->i", normals, np.asarray(C[i]) - P) > 0.3 * np.linalg.norm(np.asarray(C[i]) - P, axis=1)
        ok = facing & (Xc[:, 2] > 0) & np.all((xy >= 0) & (xy <= [639, 479]), axis=1)
        k = np.flatnonzero(ok)
        op.append(k)
        oi.append(np.full(len(k), i))
        oxy.append(xy[k] + rng.normal(0, noise_px, (len(k), 2)))
    op, oi, oxy = np.concatenate(op), np.concatenate(oi), np.concatenate(oxy)
    seen = np.bincount(op, minlength=len(P)) >= 2
    keep = seen[op]
    return V, F, cam, poses, np.array(C), P, op[keep], oi[keep], oxy[keep]


def _triangulate(poses, cam, op, oi, oxy, n_points):
    """Linear triangulation of every point from its observations with the given poses."""
    rays = cam.unproject(oxy)[:, :2]
    X = np.full((n_points, 3), np.nan)
    for p in np.unique(op):
        o = np.flatnonzero(op == p)
        A = []
        for k in o:
            R, t = poses[oi[k]]
            Pm = np.c_[R, t]
            A += [rays[k, 0] * Pm[2] - Pm[0], rays[k, 1] * Pm[2] - Pm[1]]
        _, _, vt = np.linalg.svd(np.array(A))
        X[p] = vt[-1, :3] / vt[-1, 3]
    return X


def test_fit_brings_a_block_off_the_mesh_back_onto_it():
    V, F, cam, poses, C, P, op, oi, oxy = _box_ring()
    # the block as a survey with a loose datum may give it: the whole block (poses and points) moved by a similarity
    # (0.5 deg about a horizontal axis through the box's centre, scale 1.005, 6 cm) -- the tie points cannot tell (the
    # images are unchanged), the centre priors are loose (σ 1 m); only the mesh can
    Q, s, m = _rot_y(0.5), 1.005, np.array([5.0, 4.0, 3.0])
    d = np.array([0.06, -0.04, 0.03])
    move = lambda X: s * (X - m) @ Q.T + m + d  # noqa: E731
    start = [(R @ Q.T, -(R @ Q.T) @ move(c)) for (R, _), c in zip(poses, C)]
    X0 = move(P)
    names = [f"S{i:02d}" for i in range(len(poses))]
    res = fit_poses_to_mesh(names, {"thermal": cam}, ["thermal"] * len(names), start, [np.full(3, 1.0)] * len(names),
                            TiePoints(X0, op, oi, oxy), V, F, MeshFitOptions(tie_sigma_px=0.3))
    assert res.applied, res.reason
    before = np.array([_angle_deg(Rs @ R.T) for (Rs, _), (R, _) in zip(start, poses)])
    after = np.array([_angle_deg(res.poses[n][0] @ R.T) for n, (R, _) in zip(names, poses)])
    dc = np.array([-res.poses[n][0].T @ res.poses[n][1] - c for n, c in zip(names, C)])
    assert np.allclose(before, 0.5, atol=1e-9)
    # 0.3 px noise, 250-500 tie points per image at 500 px focal length, ~1000 points on four walls: the block comes
    # back to a few hundredths of a degree and a few mm across (measured rotation RMS 0.036 deg, max 0.090; centres
    # 2.6 / 2.8 mm RMS in X / Y)
    assert np.sqrt(np.mean(after**2)) < 0.06 and after.max() < 0.15
    assert np.all(np.sqrt(np.mean(dc[:, :2] ** 2, axis=0)) < 0.008)
    # vertical walls only: a common height shift keeps every point on its wall, so the block's height stays where the
    # priors put it on average (the start's tilt, +-13 cm around the ring, is gone; its mean shift stays: 3 cm less
    # the scale's 0.5 % of the stations' 1.3 m below the centre, 2.35 cm)
    start_dz = np.array([move(c)[2] - c[2] for c in C])
    assert np.ptp(start_dz) > 0.2 and np.ptp(dc[:, 2]) < 0.03  # measured 2.1 cm
    assert abs(np.mean(dc[:, 2]) - np.mean(start_dz)) < 0.005  # measured 2.40 against 2.35 cm
    f = res.figures
    assert f["median_distance_m"]["after"] < 0.1 * f["median_distance_m"]["before"]  # measured 58 -> 1.9 mm
    assert f["tie_median_px"]["after"] <= 1.25 * f["tie_median_px"]["before"]


def test_a_mesh_in_another_frame_is_refused_with_the_reason():
    V, F, cam, poses, C, P, op, oi, oxy = _box_ring()
    names = [f"S{i:02d}" for i in range(len(poses))]
    res = fit_poses_to_mesh(names, {"thermal": cam}, ["thermal"] * len(names), poses, [None] * len(names),
                            TiePoints(P, op, oi, oxy), V + [3.0, -2.0, 0.5], F)
    assert not res.applied and res.poses == {}
    assert "does not show what the images show" in res.reason and "median distance" in res.reason


def test_too_few_tie_points_is_a_result():
    V, F, cam, poses, C, P, op, oi, oxy = _box_ring()
    keep = op < 10
    res = fit_poses_to_mesh([f"S{i}" for i in range(len(poses))], {"thermal": cam}, ["thermal"] * len(poses),
                            poses, [None] * len(poses), TiePoints(P[:10], op[keep], oi[keep], oxy[keep]), V, F)
    assert not res.applied and "too few" in res.reason


def test_options_are_checked():
    from thermogrammetry.errors import ConfigError

    with pytest.raises(ConfigError, match="surface_sigma_m"):
        MeshFitOptions(surface_sigma_m=-1.0)
    with pytest.raises(ConfigError, match="min_share"):
        MeshFitOptions(min_share=0.0)
    with pytest.raises(ConfigError):
        MeshFitOptions.from_dict({"surface_sigma": 0.1})
