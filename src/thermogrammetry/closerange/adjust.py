"""Joint least-squares adjustment of the close-range network (optional step after the sequential chain).

All cameras (optical and thermal) and all pass points are estimated together from every image
measurement; control points are fixed (they define the datum), or — when the observations carry
control coordinates with σ (``solve_network(..., control_sigma_m=...)``) — adjusted as weighted
observations. Optical DLT cameras may carry the
additional parameters of seed 000 eq. 2 (``dx, dy``: systematic image errors), in the correction form
evaluated at the measured coordinates (Karara's iterative DLT; Brown 1971; Fraser 1997)::

    x + dx(x) = (L1 X̃ + L2 Ỹ + L3 Z̃ + L4) / (L9 X̃ + L10 Ỹ + L11 Z̃ + 1)        (and y alike)
    ū = (x − x_c) / s,   r² = ū² + v̄²          (x_c, s: centroid and RMS radius of the image's measurements)
    dx / s = ū (k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2ū²) + 2 p2 ū v̄ + b1 ū + b2 v̄
    dy / s = v̄ (k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 ū v̄ + p2 (r² + 2 v̄²)

(the normalisation by ``s`` makes the coefficients unitless; the principal point is not separable
from the DLT's own affine terms, so the image centroid serves as the distortion centre). Cameras
with a known interior orientation keep it and adjust only their 6 pose parameters. The thermal
camera, when positioned by DLT, gets no additional parameters: its distortion belongs in a
``camera.json`` from calibration.

The result is a :class:`~.solve.NetworkResult` like the sequential one, with Jacobians with respect
to the same observation vector, so planes, angles and the per-pixel uncertainty use the joint
covariance unchanged.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from ..errors import ConfigError
from ..results import Outcome
from . import network as nw
from .solve import NetworkResult, OrientedCamera, _undistort_with_jacobian, single_threaded_blas

__all__ = ["ADDITIONAL_PARAMETERS", "distortion_basis", "adjust_network"]

ADDITIONAL_PARAMETERS = ("k1", "k2", "k3", "p1", "p2", "b1", "b2")


def distortion_basis(xy, names: Sequence[str], center, scale) -> np.ndarray:
    """(N, 2, P) basis ``B`` with ``(dx, dy) = B @ a`` (px) for the additional parameters ``names``."""
    u = (np.asarray(xy, float) - center) / scale
    u0, u1 = u[:, 0], u[:, 1]
    r2 = u0**2 + u1**2
    cols = []
    for n in names:
        if n == "k1":
            cols.append((u0 * r2, u1 * r2))
        elif n == "k2":
            cols.append((u0 * r2**2, u1 * r2**2))
        elif n == "k3":
            cols.append((u0 * r2**3, u1 * r2**3))
        elif n == "p1":
            cols.append((r2 + 2 * u0**2, 2 * u0 * u1))
        elif n == "p2":
            cols.append((2 * u0 * u1, r2 + 2 * u1**2))
        elif n == "b1":
            cols.append((u0, np.zeros_like(u0)))
        elif n == "b2":
            cols.append((u1, np.zeros_like(u0)))
        else:
            raise ConfigError(f"additional parameter {n!r}: expected some of {ADDITIONAL_PARAMETERS}")
    B = np.zeros((len(u), 2, len(names)))
    for j, (a, b) in enumerate(cols):
        B[:, 0, j] = a
        B[:, 1, j] = b
    return B * scale


@single_threaded_blas
def adjust_network(
    net: NetworkResult,
    *,
    additional: Sequence[str] = (),
    max_iterations: int = 50,
) -> NetworkResult:
    """Adjust every camera and pass point of ``net`` jointly (see module docstring).

    Parameters
    ----------
    net : the sequential solution (start values, observations, frame, known cameras)
    additional : names from :data:`ADDITIONAL_PARAMETERS` estimated for every optical DLT camera

    Returns
    -------
    NetworkResult with adjusted cameras and points; each adjusted camera's ``outcome`` carries the
    joint termination and its ``extra`` the additional parameters with σ.
    """
    additional = tuple(additional)
    for n in additional:
        if n not in ADDITIONAL_PARAMETERS:
            raise ConfigError(f"additional parameter {n!r}: expected some of {ADDITIONAL_PARAMETERS}")
    obs = net.obs
    frame = net.frame
    names = list(net.cameras)
    pass_index = {pid: i for i, pid in enumerate(net.pass_ids)}
    # rows used: a camera in the network and a point with coordinates
    rows = [k for k, (im, pid) in enumerate(zip(obs.images, obs.ids))
            if im in net.cameras and (pid in pass_index or pid in net.control)]
    # ideal (undistorted) coordinates for known cameras, and their derivative
    ideal = obs.xy.copy()
    D = np.repeat(np.eye(2)[None], len(obs.ids), axis=0)
    for im, cam_k in net.known.items():
        rr = obs.on(im)
        ideal[rr], Dk = _undistort_with_jacobian(cam_k, obs.xy[rr])
        D[rr] = np.array([Dk[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(len(rr))])
    # image normalisation for the additional parameters
    centers, scales = {}, {}
    for im in names:
        xy = obs.xy[obs.on(im)]
        centers[im] = xy.mean(axis=0)
        scales[im] = float(np.sqrt(((xy - centers[im]) ** 2).sum(axis=1).mean())) or 1.0
    # parameter layout
    blocks = {}
    start = []
    pos = 0
    pose0 = {}
    for im in names:
        cam = net.cameras[im]
        if im in net.known:
            K = np.asarray(net.known[im].K, float)
            _, R0, C0 = nw.decompose_projection(nw.dlt_matrix(cam.L) @ frame.world_matrix())
            pose0[im] = (K, R0, C0)
            blocks[im] = ("pose", pos, 6, 0)
            start.append(np.zeros(6))
            pos += 6
        else:
            na = len(additional) if cam.kind == "optical" else 0
            blocks[im] = ("dlt", pos, 11, na)
            start.append(np.concatenate([cam.L, np.zeros(na)]))
            pos += 11 + na
    p0 = pos
    start.append(frame.to_norm(net.points_world).ravel() if len(net.pass_ids) else np.zeros(0))
    # weighted control points are parameters too, with their given coordinates as observations
    wc_ids = tuple(obs.control_ids)
    c0 = p0 + 3 * len(net.pass_ids)
    given = np.array([net.control[i] for i in wc_ids]).reshape(-1, 3)
    start.append(frame.to_norm(given).ravel() if wc_ids else np.zeros(0))
    theta = np.concatenate(start)
    n_par = theta.size

    def cam_L(im, th):
        kind, o, m, na = blocks[im]
        if kind == "pose":
            K, R0, C0 = pose0[im]
            p = th[o:o + 6]
            return nw.L_from_pose(K, nw._rot(p[:3]) @ R0, C0 + p[3:], frame)
        return th[o:o + 11]

    def dL_dpose(im, th):
        G = np.zeros((11, 6))
        for k in range(6):
            e = np.zeros_like(th)
            e[blocks[im][1] + k] = 1e-7
            G[:, k] = (cam_L(im, th + e) - cam_L(im, th - e)) / 2e-7
        return G

    def point(pid, th):
        if pid in wc_ids:
            j = wc_ids.index(pid)
            return th[c0 + 3 * j:c0 + 3 * j + 3]
        if pid in net.control:
            return frame.to_norm(net.control[pid])
        i = pass_index[pid]
        return th[p0 + 3 * i:p0 + 3 * i + 3]

    def residuals(th, *, jac=True):
        m = 2 * len(rows)
        r = np.zeros(m)
        J = np.zeros((m, n_par)) if jac else None
        Ro = np.zeros((len(rows), 2, 2)) if jac else None  # ∂r/∂ideal, one 2×2 block per row
        for im in names:
            kind, o, size, na = blocks[im]
            sel = [j for j, k in enumerate(rows) if obs.images[k] == im]
            if not sel:
                continue
            ks = [rows[j] for j in sel]
            L = cam_L(im, th)
            X = np.array([point(obs.ids[k], th) for k in ks])
            proj, JL, JX = nw.dlt_jacobians(L, X)
            xy = ideal[ks]
            if na:
                a = th[o + 11:o + 11 + na]
                B = distortion_basis(xy, additional, centers[im], scales[im])
                dxy = B @ a
            else:
                dxy = np.zeros_like(xy)
            res = proj - xy - dxy
            idx = np.array([[2 * j, 2 * j + 1] for j in sel]).ravel()
            r[idx] = res.ravel()
            if not jac:
                continue
            if kind == "pose":
                JLp = JL.reshape(-1, 11) @ dL_dpose(im, th)
                J[idx, o:o + 6] = JLp
            else:
                J[idx, o:o + 11] = JL.reshape(-1, 11)
                if na:
                    J[idx, o + 11:o + 11 + na] = -B.reshape(-1, na)
            for jj, k in enumerate(ks):
                i = pass_index.get(obs.ids[k])
                if i is not None:
                    J[2 * sel[jj]:2 * sel[jj] + 2, p0 + 3 * i:p0 + 3 * i + 3] = JX[jj]
                elif obs.ids[k] in wc_ids:
                    c = c0 + 3 * wc_ids.index(obs.ids[k])
                    J[2 * sel[jj]:2 * sel[jj] + 2, c:c + 3] = JX[jj]
            # ∂r/∂x_ideal = −(I + ∂dx/∂x)
            if na:
                h = 1e-4
                dd = np.zeros((len(ks), 2, 2))
                for c in range(2):
                    e = np.zeros(2)
                    e[c] = h
                    dd[:, :, c] = ((distortion_basis(xy + e, additional, centers[im], scales[im]) @ a)
                                   - (distortion_basis(xy - e, additional, centers[im], scales[im]) @ a)) / (2 * h)
            else:
                dd = np.zeros((len(ks), 2, 2))
            Ro[sel] = -(np.eye(2)[None] + dd)
        return r, J, Ro

    def control_residuals(th):
        """Given control coordinates as observations: r = X(θ) − X_given (m), J = ∂r/∂θ."""
        rc = (frame.to_world(th[c0:c0 + 3 * len(wc_ids)].reshape(-1, 3)) - given).ravel()
        Jc = np.zeros((rc.size, n_par))
        Jc[:, c0:c0 + rc.size] = np.eye(rc.size) * frame.scale
        return rc, Jc

    w_img = 1.0 / np.repeat(obs.sigma_px[rows], 2) ** 2
    w = np.concatenate([w_img, 1.0 / np.repeat(obs.control_sigma_m, 3) ** 2])

    def residuals_all(th):
        r, J, Ro = residuals(th)
        if wc_ids:
            rc, Jc = control_residuals(th)
            r, J = np.concatenate([r, rc]), np.vstack([J, Jc])
        return r, J, Ro

    # the project's dense least-squares kernel (Gauss–Newton / Levenberg–Marquardt) does the iterations
    from ..adjustment.dense import DenseOptions, solve_dense

    def fun(th):
        r, J, _ = residuals_all(th)
        return r, J

    sol = solve_dense(fun, theta, cov=1.0 / w, options=DenseOptions(max_iterations=max_iterations))
    theta = np.asarray(sol.x, float)
    term, reason = sol.outcome.termination, sol.outcome.reason
    r, J, Ro = residuals_all(theta)
    Nm = (J * w[:, None]).T @ J
    col = np.sqrt(np.diag(Nm))
    col[col == 0] = 1.0
    Ninv = np.linalg.pinv(Nm / np.outer(col, col)) / np.outer(col, col)
    # dθ/d(measured) = −N⁻¹ Jᵀ W (∂r/∂ideal) (∂ideal/∂measured); for given control ∂r/∂given = −I
    NJW = Ninv @ (J.T * w)
    m_img = 2 * len(rows)
    G = -NJW[:, :m_img].reshape(n_par, len(rows), 2)  # then × ∂r/∂ideal × ∂ideal/∂measured per row
    Gm = np.einsum("pna,nab,nbc->pnc", G, Ro, D[rows]).reshape(n_par, -1)
    dtheta = np.zeros((n_par, obs.n))
    dtheta[:, obs.cols(rows)] = Gm
    if wc_ids:
        dtheta[:, 2 * len(obs.ids):] = NJW[:, m_img:]
    vtpv = float((w * r**2).sum())
    r = r[:m_img]
    red = 2 * len(rows) + 3 * len(wc_ids) - n_par
    s0 = float(np.sqrt(vtpv / red)) if red > 0 else float("nan")
    outcome = Outcome(term, reason)
    cams = {}
    for im in names:
        kind, o, size, na = blocks[im]
        L = cam_L(im, theta)
        if kind == "pose":
            JL = dL_dpose(im, theta) @ dtheta[o:o + 6]
        else:
            JL = dtheta[o:o + 11]
        sel = [j for j, k in enumerate(rows) if obs.images[k] == im]
        res = r.reshape(-1, 2)[sel]
        extra = {}
        if na:
            cov_a = net.cov(dtheta[o + 11:o + 11 + na])
            extra = {"additional_parameters": {n: float(theta[o + 11 + j]) for j, n in enumerate(additional)},
                     "additional_std": {n: float(np.sqrt(cov_a[j, j])) for j, n in enumerate(additional)},
                     "distortion_center_px": centers[im].tolist(), "distortion_scale_px": scales[im]}
        old = net.cameras[im]
        cams[im] = OrientedCamera(im, old.kind, L, JL, tuple(obs.ids[rows[j]] for j in sel), res, s0, outcome,
                                  extra=extra)
    Xn = theta[p0:c0].reshape(-1, 3)
    warnings = list(net.warnings)
    if not outcome.success:
        warnings.append(f"joint adjustment: {outcome.termination}: {outcome.reason}")
    control = dict(net.control)
    J_control = {}
    for j, pid in enumerate(wc_ids):
        control[pid] = frame.to_world(theta[c0 + 3 * j:c0 + 3 * j + 3])
        J_control[pid] = dtheta[c0 + 3 * j:c0 + 3 * j + 3] * frame.scale
    return replace(net, cameras=cams, points_world=frame.to_world(Xn) if len(Xn) else net.points_world,
                   J_points=dtheta[p0:c0] * frame.scale, warnings=warnings, adjusted=True, control=control,
                   J_control=J_control)
