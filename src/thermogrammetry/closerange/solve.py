"""Seed 000's orientation chain on arrays: optical DLTs → pass points → thermal camera, with precision.

:func:`solve_network` runs the chain of seed 000 §2 (Fig. 2):

1. every optical image with ≥ 6 control points is positioned by DLT + least-squares refinement;
2. pass points (ids without control coordinates) seen in ≥ 2 optical images are intersected;
3. the thermal camera is positioned by DLT from the points it sees that now have coordinates
   (pass points; control points too if they were measured there — none are needed).

Each estimate carries its Jacobian with respect to the global observation vector (see
:mod:`.network`), so the covariance of every derived quantity includes the error of every step
before it. Covariances use the a-priori image σ (``sigma_px``) — with 6 control points a DLT has one
redundant observation and its σ0 is no estimate of anything; σ0 is reported beside it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ..errors import DegenerateInputError, InvalidInputError, TooFewPointsError
from ..results import Outcome
from . import network as nw

__all__ = ["Observations", "OrientedCamera", "NetworkResult", "solve_network", "single_threaded_blas"]


def single_threaded_blas(fn):
    """Run ``fn`` with one BLAS thread: the matrices here are tiny (≤ 100 × 100) and a threaded BLAS
    only adds overhead — up to 10× on a loaded machine."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - threadpoolctl is a dependency
            return fn(*args, **kwargs)
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


@dataclass(frozen=True)
class Observations:
    """Image measurements ``(image, id, x, y)`` in px with their a-priori σ (px) per image."""

    images: tuple[str, ...]
    ids: tuple[str, ...]
    xy: np.ndarray  # (K, 2)
    sigma_px: np.ndarray  # (K,)
    #: control points whose coordinates are observations too (weighted control), appended to the
    #: observation vector after the 2K image coordinates as X, Y, Z per point
    control_ids: tuple[str, ...] = ()
    control_sigma_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,)

    def with_control(self, ids: Sequence[str], sigma_m: float | Mapping[str, float]) -> "Observations":
        """The same measurements plus control coordinates as observations with σ (m)."""
        ids = tuple(str(i) for i in ids)
        if isinstance(sigma_m, Mapping):
            sig = np.array([float(sigma_m[i]) for i in ids])
        else:
            sig = np.full(len(ids), float(sigma_m))
        if np.any(~(sig > 0)):
            raise InvalidInputError(f"control_sigma_m: expected positive values, got {sorted(set(sig.tolist()))}")
        return Observations(self.images, self.ids, self.xy, self.sigma_px, ids, sig)

    def control_cols(self, pid: str) -> np.ndarray | None:
        """Columns of control point ``pid``'s X, Y, Z in the observation vector (None when fixed)."""
        if pid not in self.control_ids:
            return None
        k = 2 * len(self.ids) + 3 * self.control_ids.index(pid)
        return np.arange(k, k + 3)

    @classmethod
    def from_rows(cls, rows: Sequence[tuple[str, str, float, float]], sigma_px: float | Mapping[str, float] = 0.5):
        images = tuple(str(r[0]) for r in rows)
        ids = tuple(str(r[1]) for r in rows)
        xy = np.array([[float(r[2]), float(r[3])] for r in rows], float).reshape(-1, 2)
        if isinstance(sigma_px, Mapping):
            sig = np.array([float(sigma_px.get(im, sigma_px.get("*", 0.5))) for im in images])
        else:
            sig = np.full(len(rows), float(sigma_px))
        if np.any(sig <= 0):
            raise InvalidInputError(f"sigma_px: expected positive values, got {sorted(set(sig.tolist()))}")
        seen = set()
        for im, i in zip(images, ids):
            if (im, i) in seen:
                raise InvalidInputError(f"point {i!r} is measured twice on image {im!r}; expected one row per point")
            seen.add((im, i))
        return cls(images, ids, xy, sig)

    @property
    def n(self) -> int:
        return 2 * len(self.ids) + 3 * len(self.control_ids)

    def on(self, image: str) -> list[int]:
        return [k for k, im in enumerate(self.images) if im == image]

    def cols(self, rows: Sequence[int]) -> np.ndarray:
        rows = np.asarray(rows, int)
        return np.column_stack([2 * rows, 2 * rows + 1]).ravel()

    def cov_diag(self) -> np.ndarray:
        """(n,) variances of the observation vector (px² for image coordinates, m² for control)."""
        return np.concatenate([np.repeat(self.sigma_px**2, 2), np.repeat(self.control_sigma_m**2, 3)])


@dataclass
class OrientedCamera:
    """A camera positioned by DLT: coefficients in the normalised frame + derivatives."""

    name: str
    kind: str  # "optical" | "thermal"
    L: np.ndarray  # (11,)
    J: np.ndarray  # (11, n_obs) dL/dobs
    ids: tuple[str, ...]  # points used
    residuals: np.ndarray  # (N, 2) px
    sigma0_px: float
    outcome: Outcome
    extra: dict = field(default_factory=dict)  # e.g. additional parameters of a joint adjustment

    def P_world(self, frame: nw.Frame) -> np.ndarray:
        """3×4 projection matrix in world coordinates (px, m)."""
        return nw.dlt_matrix(self.L) @ frame.world_matrix()


@dataclass
class NetworkResult:
    frame: nw.Frame
    obs: Observations
    cameras: dict[str, OrientedCamera]
    thermal: str
    control: dict[str, np.ndarray]
    pass_ids: tuple[str, ...]
    points_world: np.ndarray  # (n_pass, 3)
    J_points: np.ndarray  # (3 n_pass, n_obs), world metres per px
    warnings: list[str] = field(default_factory=list)
    known: dict = field(default_factory=dict)  # image → camera with a known interior orientation
    adjusted: bool = False  # True after the joint adjustment (adjust.adjust_network)
    J_control: dict = field(default_factory=dict)  # control id → (3, n_obs) when control is weighted

    # -- covariance helpers --------------------------------------------------------------------
    def cov(self, J: np.ndarray) -> np.ndarray:
        """``J Σ_obs Jᵀ`` for any (m, n_obs) Jacobian."""
        return (J * self.obs.cov_diag()) @ J.T

    def point(self, pid: str) -> np.ndarray:
        """World coordinates (m) of a control or pass point."""
        if pid in self.control:
            return self.control[pid]
        return self.points_world[self.pass_ids.index(pid)]

    def point_jacobian(self, pid: str) -> np.ndarray:
        """(3, n_obs) derivative of a point's world coordinates w.r.t. the observations
        (zero for fixed control points)."""
        if pid in self.control:
            return self.J_control.get(pid, np.zeros((3, self.obs.n)))
        i = self.pass_ids.index(pid)
        return self.J_points[3 * i:3 * i + 3]

    @property
    def point_sigmas(self) -> np.ndarray:
        """(n_pass, 3) σX σY σZ (m)."""
        return np.sqrt(np.diag(self.cov(self.J_points))).reshape(-1, 3)

    def thermal_center(self) -> tuple[np.ndarray, np.ndarray]:
        """Thermal projection centre (m) and its 3×3 covariance."""
        cam = self.cameras[self.thermal]
        C, J = _center_and_jacobian(cam, self.frame)
        return C, self.cov(J)


def _center_and_jacobian(cam: OrientedCamera, frame: nw.Frame) -> tuple[np.ndarray, np.ndarray]:
    def center(L):
        return frame.to_world(nw.camera_axis_center(nw.dlt_matrix(L))[1])

    C = center(cam.L)
    G = np.zeros((3, 11))
    for k in range(11):
        h = 1e-6 * max(1.0, abs(cam.L[k]))
        e = np.zeros(11)
        e[k] = h
        G[:, k] = (center(cam.L + e) - center(cam.L - e)) / (2 * h)
    return C, G @ cam.J


def _undistort_with_jacobian(camera, xy) -> tuple[np.ndarray, np.ndarray]:
    """Ideal (undistorted) px and the (2N, 2N) block-diagonal derivative d ideal / d measured."""
    xy = np.asarray(xy, float)
    ideal = np.asarray(camera.undistort(xy), float)
    N = len(xy)
    D = np.zeros((2 * N, 2 * N))
    h = 1e-4
    for c in range(2):
        e = np.zeros(2)
        e[c] = h
        d = (np.asarray(camera.undistort(xy + e), float) - np.asarray(camera.undistort(xy - e), float)) / (2 * h)
        for i in range(N):
            D[2 * i:2 * i + 2, 2 * i + c] = d[i]
    return ideal, D


def _orient(image, camera, Xn, xy, frame, what, ids):
    """DLT + refinement, or resection when the interior orientation is known (``xy`` already ideal)."""
    if camera is None:
        nw.check_dlt_geometry(Xn, what=what, ids=ids, image=image)
        L0 = nw.dlt_linear(Xn, xy)
        return nw.refine_dlt(L0, Xn, xy)
    if len(Xn) < 4:
        raise TooFewPointsError(
            f"{len(Xn)} {what} on image {image!r} ({', '.join(ids)}): a resection with known interior "
            "orientation needs at least 4"
        )
    rc, _ = nw.resect_known_interior(np.asarray(camera.K, float), Xn, xy, frame)
    return rc


@single_threaded_blas
def solve_network(
    control: Mapping[str, Sequence[float]],
    obs: Observations,
    thermal: str,
    *,
    optical: Sequence[str] | None = None,
    known: Mapping[str, object] | None = None,
    control_sigma_m: float | Mapping[str, float] | None = None,
) -> NetworkResult:
    """Run seed 000's orientation chain.

    Parameters
    ----------
    control : mapping id → (X, Y, Z) m
        Control points (fixed).
    obs : Observations
        All image measurements, optical and thermal.
    thermal : str
        Name of the thermal image in ``obs``.
    optical : names, optional
        Optical images to use (default: every image except ``thermal``).
    known : mapping image name → camera, optional
        Known interior orientation (``thermogrammetry.Camera`` or anything with ``.K`` and
        ``.undistort``): that image is positioned by space resection (6 pose parameters) from its
        undistorted measurements instead of the 11-parameter DLT — the remedy for coplanar control.
    control_sigma_m : float or mapping id → σ, optional
        Standard deviation of the control coordinates (m). The control points still fix the datum
        (the chain is sequential), but their uncertainty is propagated into every result; the joint
        adjustment (:mod:`.adjust`) then adjusts them as weighted observations. Default: errorless.

    Raises
    ------
    TooFewPointsError, DegenerateInputError
        Fewer than 2 optical cameras can be positioned (the error of the first image refused: fewer
        than 6 or coplanar control points; with ≥ 2 others positioned such an image is left out with a
        warning);
        fewer than 6 points with coordinates on the thermal image (the message lists those seen).
    """
    control = {str(k): np.asarray(v, float) for k, v in control.items()}
    if thermal not in obs.images:
        raise InvalidInputError(
            f"thermal image {thermal!r} has no measurements; images measured: {sorted(set(obs.images))}"
        )
    if optical is None:
        optical = [im for im in dict.fromkeys(obs.images) if im != thermal]
    if len(control) < 6:
        raise TooFewPointsError(f"{len(control)} control points ({', '.join(control)}): the DLT needs at least 6")
    frame = nw.Frame.from_points(np.array(list(control.values())))
    if control_sigma_m is not None:
        obs = obs.with_control(list(control), control_sigma_m)

    def control_J(ids):  # (3N, n): d X̃ / d obs of control points (selector / scale when weighted)
        out = np.zeros((3 * len(ids), obs.n))
        for j, i in enumerate(ids):
            c = obs.control_cols(i)
            if c is not None:
                out[3 * j + np.arange(3), c] = 1.0 / frame.scale
        return out

    cams: dict[str, OrientedCamera] = {}
    warnings: list[str] = []
    known = dict(known or {})
    unknown_names = sorted(set(known) - set(obs.images))
    if unknown_names:
        raise InvalidInputError(
            f"camera file(s) given for image(s) {unknown_names} that have no measurements; images measured: "
            f"{sorted(set(obs.images))}"
        )
    # measurements of images with a known interior orientation are undistorted once ("ideal" px);
    # D[k] = d ideal / d measured (2×2) chains every derivative back to the measurements
    ideal = obs.xy.copy()
    D = np.repeat(np.eye(2)[None], len(obs.ids), axis=0)
    for im, cam_k in known.items():
        rows = obs.on(im)
        ideal[rows], Dk = _undistort_with_jacobian(cam_k, obs.xy[rows])
        D[rows] = np.array([Dk[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(len(rows))])

    def chain(Jc, rows):  # (m, 2n) w.r.t. ideal of rows → (m, 2n) w.r.t. measured
        m = Jc.shape[0]
        return np.einsum("mna,nab->mnb", Jc.reshape(m, len(rows), 2), D[rows]).reshape(m, -1)

    refused: list[DegenerateInputError] = []
    for im in optical:
        rows = [k for k in obs.on(im) if obs.ids[k] in control]
        ids = [obs.ids[k] for k in rows]
        Xn = frame.to_norm(np.array([control[i] for i in ids]).reshape(-1, 3))
        try:
            rc = _orient(im, known.get(im), Xn, ideal[rows], frame, "control points", ids)
        except DegenerateInputError as exc:  # includes TooFewPointsError
            refused.append(exc)
            continue
        J = np.zeros((11, obs.n))
        J[:, obs.cols(rows)] = chain(rc.dL_dobs, rows)
        J += rc.dL_dX @ control_J(ids)
        cams[im] = OrientedCamera(im, "optical", rc.L, J, tuple(ids), rc.residuals, rc.sigma0_px, rc.outcome)
        if not rc.outcome.success:
            warnings.append(f"DLT of {im!r}: {rc.outcome.termination}: {rc.outcome.reason}")
    if len(cams) < 2 and refused:
        raise refused[0]  # the specific reason (too few / coplanar control points on that image)
    for exc in refused:
        warnings.append(f"optical image left out: {exc}")
    if len(cams) < 2:
        raise TooFewPointsError(
            f"{len(cams)} optical camera(s) ({', '.join(cams)}) could be positioned; intersecting pass points "
            "needs at least 2 optical images with ≥ 6 control points each"
        )
    # -- pass points ---------------------------------------------------------------------------
    index = {(im, i): k for k, (im, i) in enumerate(zip(obs.images, obs.ids))}
    candidates = [i for i in dict.fromkeys(obs.ids) if i not in control]
    pass_ids, Xs, Js = [], [], []
    for pid in candidates:
        seen = [im for im in cams if (im, pid) in index]
        if len(seen) < 2:
            if seen:
                warnings.append(f"pass point {pid!r} is seen only on optical image {seen[0]!r}; not intersected")
            continue
        rows = [index[(im, pid)] for im in seen]
        X, dXo, dXL, _, out = nw.triangulate_point([cams[im].L for im in seen], ideal[rows])
        if not out.success:
            warnings.append(f"pass point {pid!r}: {out.reason}")
            continue
        J = np.zeros((3, obs.n))
        J[:, obs.cols(rows)] += chain(dXo, rows)
        for im, d in zip(seen, dXL):
            J += d @ cams[im].J
        pass_ids.append(pid)
        Xs.append(X)
        Js.append(J)
    Xn_pass = np.array(Xs).reshape(-1, 3)
    J_pass_n = np.vstack(Js) if Js else np.zeros((0, obs.n))
    # -- thermal camera from pass points (no control coordinates needed) ---------------------------
    trows = obs.on(thermal)
    seen_ids = [obs.ids[k] for k in trows]
    use = [k for k in trows if obs.ids[k] in pass_ids or obs.ids[k] in control]
    use_ids = [obs.ids[k] for k in use]
    if len(use) < (4 if thermal in known else 6):
        no_xyz = [i for i in seen_ids if i not in use_ids]
        raise TooFewPointsError(
            f"thermal image {thermal!r}: {len(use)} points with coordinates seen "
            f"({', '.join(use_ids) or 'none'}); the thermal camera needs at least 6 pass points measured on it "
            f"and intersected from ≥ 2 optical images. Measured on the thermal image: {', '.join(seen_ids) or 'none'}"
            + (f"; without 3D coordinates: {', '.join(no_xyz)}" if no_xyz else "")
        )
    Xn_t = np.array([control[i] if i in control else frame.to_world(Xn_pass[pass_ids.index(i)])
                     for i in use_ids])
    Xn_t = frame.to_norm(Xn_t)
    rc = _orient(thermal, known.get(thermal), Xn_t, ideal[use], frame, "pass points", use_ids)
    Jt = np.zeros((11, obs.n))
    Jt[:, obs.cols(use)] += chain(rc.dL_dobs, use)
    JX = np.vstack([control_J([i]) if i in control else J_pass_n[3 * pass_ids.index(i):3 * pass_ids.index(i) + 3]
                    for i in use_ids])
    Jt += rc.dL_dX @ JX
    cams[thermal] = OrientedCamera(thermal, "thermal", rc.L, Jt, tuple(use_ids), rc.residuals, rc.sigma0_px,
                                   rc.outcome)
    if not rc.outcome.success:
        warnings.append(f"DLT of thermal {thermal!r}: {rc.outcome.termination}: {rc.outcome.reason}")
    return NetworkResult(
        frame=frame,
        obs=obs,
        cameras=cams,
        thermal=thermal,
        control=control,
        pass_ids=tuple(pass_ids),
        points_world=frame.to_world(Xn_pass) if len(Xn_pass) else Xn_pass,
        J_points=J_pass_n * frame.scale,
        warnings=warnings,
        known=known,
        J_control={i: control_J([i]) * frame.scale for i in obs.control_ids},
    )


