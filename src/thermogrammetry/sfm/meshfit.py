"""Camera poses fitted to a given mesh: the survey's tie points made to lie on the surface being textured.

Why. A survey's GNSS (or GCP) datum fixes the block as a whole, not every mode of it. Terrestrial stations at one
height around a building leave one mode nearly free: every camera turned by the same small angle about a
horizontal axis, in place (the centres stay on their GNSS positions), with the structure sheared so that each
facade's points follow their cameras. Only wide-baseline ties resist it, within the noise of the tie points. On
the 48-station ring of ``synthetic.building`` (seed 3, RTK 3/5 cm, the true camera file) the survey's rotations
are 0.5 deg off about one horizontal world axis in common (0.78 deg RMS in all): projected through those poses,
the true mesh lands ~2.5 px from where the images show it, and texels near a temperature edge take the wrong
pixel. A mesh from a laser scanner, a CAD model or an RGB photogrammetry project in the survey's coordinate system
fixes the structure: the tie points must lie on its surface.

Model (one bundle adjustment on the engine, :mod:`thermogrammetry.adjustment`):

- the survey's tie points (tracks and their image observations, σ ``tie_sigma_px``, Huber), free;
- the poses, free; the intrinsics held (the survey's cameras);
- the survey's camera centres as priors, σ = their reported σ (at least ``min_center_sigma_m``; 1 % of the
  centres' extent where none is reported): the datum stays the survey's;
- one condition per tie point near the mesh: its distance to the plane of its nearest triangle is 0 with σ
  ``surface_sigma_m`` (by default 1.4826 × the median distance of those points before the fit: the mesh's and
  the survey's disagreement, at least ``min_surface_sigma_m``). Points farther than ``gate_sigmas`` such σ, or
  farther than ``max_distance_rel`` × their distance to the nearest camera that sees them, are not tied to the
  surface (window reveals and ledges missing from a coarse model, points on objects that are not in the mesh).

The fit is used only when the mesh and the tie points meet (at least ``min_points`` tie points and
``min_share`` of them near the surface: otherwise the mesh is in another coordinate system or shows another
object), when the adjustment converges, and when it brings the points closer to the surface without bending the
block (median tie residual at most ``max(1.25 ×, + 0.1 px)`` of the survey's). Otherwise a :class:`MeshFitResult` says why and
the survey's poses stay.

Measured (``benchmarks/texture_ring.py``, ``tests/test_texture_meshfit_ring.py``: the ring above; texture from
noise-free renderings at the estimated poses, clean wall texels against the scene's apparent temperature): rotations
0.78 -> 0.59 deg RMS; texels within 0.2 K 91.3 -> 97.1 %, median 0.051 -> 0.026 K, 99th percentile 0.44 -> 0.28 K;
visible faces textured 97.4 -> 97.7 % (true poses: 100 %, 0.001 K, 98.4 %). What remains is each camera's own
rotation error (0.3-0.4 deg): the GNSS noise of its centre traded against its rotation, which the surface does not
resolve (loosening the centre priors lets the centres drift: 0.61 deg with a 5 cm floor, 0.82 deg with 20 cm).

References
----------
Ericson, C. (2005). Real-Time Collision Detection, §5.1.5 (closest point on a triangle).
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §15.4 (bundle adjustment with control
surfaces).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._validate import config_keys
from ..errors import ConfigError

__all__ = ["MeshFitOptions", "MeshFitResult", "TiePoints", "closest_point_on_triangles", "closest_faces",
           "fit_poses_to_mesh"]


@dataclass(frozen=True)
class MeshFitOptions:
    """What the fit uses and when it is kept (typed; unknown keys refused by :meth:`from_dict`).

    Attributes
    ----------
    surface_sigma_m : float or None
        σ of a tie point's distance to the mesh (m); None: 1.4826 × the median distance of the points near the
        surface before the fit, at least ``min_surface_sigma_m``.
    min_surface_sigma_m : float
    gate_sigmas : float
        Points farther from the mesh than this many surface σ are not tied to it.
    max_distance_rel : float
        ... nor those farther than this share of their distance to the nearest camera that sees them.
    min_points, min_share : int, float
        The fit runs only with this many tie points near the surface, and this share of all tie points.
    tie_sigma_px : float
        σ of the tie observations (px), Huber at 2 σ.
    min_center_sigma_m : float
        Floor of the camera-centre priors' σ (m).
    max_iterations : int
    """

    surface_sigma_m: float | None = None
    min_surface_sigma_m: float = 0.005
    gate_sigmas: float = 4.0
    max_distance_rel: float = 0.02
    min_points: int = 30
    min_share: float = 0.5
    tie_sigma_px: float = 1.0
    min_center_sigma_m: float = 0.005
    max_iterations: int = 100

    def __post_init__(self):
        if self.surface_sigma_m is not None and not (np.isfinite(self.surface_sigma_m) and self.surface_sigma_m > 0):
            raise ConfigError(f"MeshFitOptions.surface_sigma_m={self.surface_sigma_m!r}: expected a number > 0 (m) or None")
        for k in ("min_surface_sigma_m", "gate_sigmas", "max_distance_rel", "tie_sigma_px", "min_center_sigma_m"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"MeshFitOptions.{k}={v!r}: expected a number > 0")
        if not 0 < self.min_share <= 1:
            raise ConfigError(f"MeshFitOptions.min_share={self.min_share!r}: expected a number in (0, 1]")
        if self.min_points < 3:
            raise ConfigError(f"MeshFitOptions.min_points={self.min_points!r}: expected >= 3")

    @classmethod
    def from_dict(cls, d: dict) -> "MeshFitOptions":
        return cls(**config_keys(cls, d))


@dataclass
class TiePoints:
    """A survey's tie points with their observations (e.g. from its COLMAP export).

    Attributes
    ----------
    xyz : (M, 3) float, world coordinates (m)
    obs_point : (K,) int, row of ``xyz`` of each observation
    obs_image : (K,) int, image index (into the ``names`` given with them) of each observation
    obs_xy : (K, 2) float, px, (0, 0) = centre of the top-left pixel
    """

    xyz: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_xy: np.ndarray


@dataclass
class MeshFitResult:
    """Outcome of :func:`fit_poses_to_mesh`.

    Attributes
    ----------
    applied : bool
        Whether the fitted poses should replace the survey's.
    reason : str
        Why not (empty when applied).
    poses : dict
        Image name -> fitted ``(R (3, 3), t (3,))`` cam_from_world (only the images that were fitted).
    figures : dict
        ``points``, ``points_on_surface``, ``surface_sigma_m``, ``median_distance_m`` before/after,
        ``tie_rms_px`` and ``tie_median_px`` before/after, ``rotation_change_deg`` / ``center_change_m`` (median, max), ``images_fitted``,
        ``images_held`` (too few tie points on the surface), ``termination``.
    """

    applied: bool
    reason: str = ""
    poses: dict = field(default_factory=dict)
    figures: dict = field(default_factory=dict)


def closest_point_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest point of each triangle ``(A, B, C)`` to ``P`` (row by row).

    Parameters
    ----------
    P, A, B, C : (N, 3) float

    Returns
    -------
    (N, 3) float

    References
    ----------
    Ericson (2005), §5.1.5: the Voronoi regions of the vertices, the edges and the face, tested in that order.
    """
    P, A, B, C = (np.asarray(x, dtype=float) for x in (P, A, B, C))
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = P - B
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = P - C
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        out = A + ab * v[:, None] + ac * w[:, None]  # inside the face
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        t_ac = d2 / (d2 - d6)
        t_ab = d1 / (d1 - d3)
    out = np.where(~np.all(np.isfinite(out), axis=1)[:, None], A, out)  # degenerate triangle: a vertex
    # regions in reverse order of precedence, so that the first test of Ericson's order wins
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out[m] = B[m] + t_bc[m, None] * (C - B)[m]
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out[m] = A[m] + t_ac[m, None] * ac[m]
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = C[m]
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out[m] = A[m] + t_ab[m, None] * ab[m]
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = B[m]
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = A[m]
    return out


def closest_faces(V: np.ndarray, F: np.ndarray, P: np.ndarray, *, k: int = 12, max_samples: int = 1_000_000,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Nearest triangle of a mesh to each point.

    Candidates are the triangles of the ``k`` nearest of the face centroids and of area-weighted random samples on
    the surface (a KD-tree; at most ``max_samples`` random samples, seeded); the exact point-triangle distance
    (:func:`closest_point_on_triangles`) picks among them. Exact wherever the nearest triangle owns one of the
    ``k`` samples nearest to the point (always, for points close to a surface sampled finer than their distance).

    Parameters
    ----------
    V : (n_v, 3) float, F : (n_f, 3) int
    P : (N, 3) float

    Returns
    -------
    face : (N,) int64
    distance_m : (N,) float
    """
    from scipy.spatial import cKDTree

    V = np.asarray(V, dtype=float)
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(P, dtype=float).reshape(-1, 3)
    if len(F) == 0 or len(P) == 0:
        return np.zeros(len(P), np.int64), np.full(len(P), np.inf)
    T = V[F]
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    n_rand = int(min(max_samples, 20 * len(F)))
    if area.sum() > 0 and n_rand > 0:
        fi = rng.choice(len(F), n_rand, p=area / area.sum())
        u, v = rng.random(n_rand), rng.random(n_rand)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        S = T[fi, 0] + u[:, None] * (T[fi, 1] - T[fi, 0]) + v[:, None] * (T[fi, 2] - T[fi, 0])
    else:
        fi, S = np.zeros(0, np.int64), np.zeros((0, 3))
    owner = np.concatenate([np.arange(len(F)), fi])
    tree = cKDTree(np.concatenate([T.mean(axis=1), S]))
    kk = int(min(k, len(owner)))
    _, idx = tree.query(P, k=kk)
    cand = owner[np.asarray(idx).reshape(len(P), kk)]
    best_d = np.full(len(P), np.inf)
    best_f = np.zeros(len(P), np.int64)
    for j in range(kk):
        f = cand[:, j]
        q = closest_point_on_triangles(P, T[f, 0], T[f, 1], T[f, 2])
        d = np.linalg.norm(P - q, axis=1)
        better = d < best_d
        best_d[better], best_f[better] = d[better], f[better]
    return best_f, best_d


def _tie_stats(v) -> dict:
    """RMS and median of the residual vectors' lengths (px)."""
    e = np.linalg.norm(np.asarray(v, float).reshape(-1, 2), axis=1)
    return {"rms": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
            "median": float(np.median(e)) if len(e) else float("nan")}


def fit_poses_to_mesh(names, cameras, image_camera, poses, centers_std, ties: TiePoints, V, F,
                      options: MeshFitOptions | None = None) -> MeshFitResult:
    """Refine the poses of an oriented survey so that its tie points lie on a given mesh (see the module docstring).

    Parameters
    ----------
    names : list of str, the images (``ties.obs_image`` indexes them)
    cameras : dict or list of Camera, held fixed; ``image_camera[i]`` is the key of image ``i``
    image_camera : list
    poses : list of (R (3, 3), t (3,)), cam_from_world of each image (m)
    centers_std : list of (3,) arrays or None, the survey's σ of each camera centre (m)
    ties : TiePoints
    V, F : the mesh in the survey's coordinate system, (n_v, 3) float (m) and (n_f, 3) int
    options : MeshFitOptions

    Returns
    -------
    MeshFitResult
        ``applied`` False with a ``reason`` when the mesh and the tie points do not meet, when the adjustment does
        not converge, or when it would not bring the points onto the surface without bending the block.
    """
    from ..adjustment import BundleProblem, SolverOptions, solve
    from ..geometry import Pose

    opt = options or MeshFitOptions()
    n = len(names)
    P = np.asarray(ties.xyz, dtype=float).reshape(-1, 3)
    op = np.asarray(ties.obs_point, dtype=np.int64)
    oi = np.asarray(ties.obs_image, dtype=np.int64)
    oxy = np.asarray(ties.obs_xy, dtype=float).reshape(-1, 2)
    fig: dict = {"points": int(len(P))}
    if len(P) < opt.min_points:
        return MeshFitResult(False, f"{len(P)} tie points < {opt.min_points}: too few to fit the poses to the mesh", figures=fig)
    C = np.array([-np.asarray(R).T @ np.asarray(t) for R, t in poses]).reshape(n, 3)
    face, dist = closest_faces(V, F, P)
    # each point's distance to the nearest camera that sees it: the scale of its own uncertainty
    rng_m = np.full(len(P), np.inf)
    np.minimum.at(rng_m, op, np.linalg.norm(P[op] - C[oi], axis=1))
    near = dist <= opt.max_distance_rel * rng_m
    if near.sum() < max(opt.min_points, opt.min_share * len(P)):
        med = float(np.median(dist))
        return MeshFitResult(False, (
            f"only {int(near.sum())} of the {len(P)} tie points lie within {100 * opt.max_distance_rel:g} % of their "
            f"distance to the cameras from the mesh (median distance {med:.3g} m; expected >= "
            f"{max(opt.min_points, int(np.ceil(opt.min_share * len(P))))}): the mesh does not show what the images "
            "show in their coordinate system (another frame or CRS, or another object)"), figures={**fig, "median_distance_m": med})
    sig = opt.surface_sigma_m
    if sig is None:
        sig = max(opt.min_surface_sigma_m, 1.4826 * float(np.median(dist[near])))
    use = near & (dist <= opt.gate_sigmas * sig)
    if use.sum() < opt.min_points:
        return MeshFitResult(False, f"{int(use.sum())} tie points within {opt.gate_sigmas:g} σ ({sig:.3g} m) of the mesh "
                                    f"< {opt.min_points}", figures=fig)
    fig.update({"points_on_surface": int(use.sum()), "surface_sigma_m": float(sig),
                "median_distance_m": {"before": float(np.median(dist[use]))}})
    # images with too few observations of points tied to the surface keep the survey's pose
    n_obs_use = np.bincount(oi[use[op]], minlength=n)
    fit = n_obs_use >= 6
    if not fit.any():
        return MeshFitResult(False, "no image sees 6 tie points on the mesh", figures=fig)
    pb = BundleProblem()
    keys = list(dict.fromkeys(image_camera))
    cam_of = {key: pb.add_camera(cameras[key], fixed=True) for key in keys}
    views = [pb.add_pose(Pose(np.asarray(R), np.asarray(t)), fixed=not bool(fit[i])) for i, (R, t) in enumerate(poses)]
    pid = pb.add_points(P)
    for i, o in _by_image(oi):
        pb.add_image_points(cam_of[image_camera[i]], views[i], pid[op[o]], oxy[o], sigma_px=opt.tie_sigma_px)
    # the datum: the survey's camera centres with their σ
    extent = float(np.max(np.ptp(C, axis=0))) if n > 1 else 1.0
    std = np.array([np.maximum(np.nan_to_num(np.asarray(s, float), nan=0.01 * extent), opt.min_center_sigma_m)
                    if s is not None else np.full(3, max(0.01 * extent, opt.min_center_sigma_m)) for s in centers_std])
    fi = np.flatnonzero(fit)
    pb.add_gnss(np.array([views[i] for i in fi]), C[fi], std[fi])
    T = np.asarray(V, float)[np.asarray(F, np.int64)]
    N = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
    D = np.einsum("ij,ij->i", N, T[:, 0])
    rows = np.flatnonzero(use)
    for f in np.unique(face[rows]):
        sel = rows[face[rows] == f]
        pb.add_plane(pid[sel], sig, normal=N[f], offset_m=float(D[f]), fixed=True)
    before = _tie_stats(_reprojection(cameras, image_camera, poses, P, op, oi, oxy))
    res = solve(pb, SolverOptions(loss="huber", loss_scale=2.0, max_iterations=opt.max_iterations,
                                  compute_covariance=False, compute_redundancy=False))
    fig["termination"] = res.termination.value
    if res.termination.value != "converged":
        return MeshFitResult(False, f"the adjustment to the mesh did not converge ({res.reason})", figures=fig)
    newp = [(np.asarray(res.problem.pose_R[v]), np.asarray(res.problem.pose_t[v])) for v in views]
    Pn = np.asarray(res.problem.points)[pid]
    after = _tie_stats(_reprojection(cameras, image_camera, newp, Pn, op, oi, oxy))
    d_after = np.abs(np.einsum("ij,ij->i", N[face[rows]], Pn[rows]) - D[face[rows]])
    d_before = np.abs(np.einsum("ij,ij->i", N[face[rows]], P[rows]) - D[face[rows]])
    from ..geometry.rotations import axis_angle_from_matrix

    rot = np.array([np.degrees(np.linalg.norm(axis_angle_from_matrix(newp[i][0] @ np.asarray(poses[i][0]).T))) for i in fi])
    Cn = np.array([-newp[i][0].T @ newp[i][1] for i in fi])
    dc = np.linalg.norm(Cn - C[fi], axis=1)
    fig.update({"median_distance_m": {"before": float(np.median(d_before)), "after": float(np.median(d_after))},
                "tie_rms_px": {"before": before["rms"], "after": after["rms"]},
                "tie_median_px": {"before": before["median"], "after": after["median"]},
                "rotation_change_deg": {"median": float(np.median(rot)), "max": float(rot.max())},
                "center_change_m": {"median": float(np.median(dc)), "max": float(dc.max())},
                "images_fitted": [names[i] for i in fi], "images_held": [names[i] for i in np.flatnonzero(~fit)]})
    # the bulk of the tie points (median residual; the Huber fit may let a few outliers grow) must fit as before
    if not after["median"] <= max(1.25 * before["median"], before["median"] + 0.1):
        return MeshFitResult(False, f"fitting the tie points to the mesh would bend the block: median tie residual "
                                    f"{before['median']:.3f} -> {after['median']:.3f} px", figures=fig)
    if not np.median(d_after) < np.median(d_before):
        return MeshFitResult(False, "the fit did not bring the tie points closer to the mesh", figures=fig)
    return MeshFitResult(True, "", {names[i]: newp[i] for i in fi}, fig)


def _reprojection(cameras, image_camera, poses, P, op, oi, oxy) -> np.ndarray:
    """Reprojection residuals (px) of the tie observations with the given poses and points."""
    out = np.zeros((len(op), 2))
    for i, o in _by_image(oi):
        R, t = poses[i]
        Xc = P[op[o]] @ np.asarray(R).T + np.asarray(t)
        out[o] = cameras[image_camera[i]].project(Xc) - oxy[o]
    return out


def _by_image(oi):
    """``(image, observation indices)`` for each image that has observations, by one stable sort (not a scan of all
    observations per image)."""
    order = np.argsort(oi, kind="stable")
    cuts = np.flatnonzero(np.diff(oi[order])) + 1
    return [(int(oi[g[0]]), g) for g in np.split(order, cuts) if len(g)]
