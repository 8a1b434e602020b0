"""The trust region: Levenberg-Marquardt (Ceres-style, see :mod:`thermogrammetry.adjustment.bal`) on the
whitened residuals, over the full-Jacobian or the chunked normal equations."""

from __future__ import annotations

import numpy as np

from .._memory import release_free_heap
from ..errors import InvalidInputError
from ..results import Termination
from .linalg import cho_factor
from .normal import Normal
from .normal_chunked import ChunkedNormal
from .options import SolverOptions
from .residuals import evaluate, robust

__all__ = ["lm"]


def lm(pb, lay, st, data, opt: SolverOptions):
    """Levenberg-Marquardt from state ``st``: returns (state, cost0, cost, iterations, termination, reason); the
    last full-path linearisation is left in ``data.linearisation`` (for the precision step)."""
    r = evaluate(pb, lay, st, data, False)
    w, cost = robust(r, data.K, opt)
    cost0 = cost
    if not np.isfinite(cost):
        return st, cost0, cost, 0, Termination.NUMERICAL_FAILURE, "initial residuals are not finite"
    radius = opt.initial_trust_region_radius
    decrease = 2.0
    it = 0
    need = True
    chunked = data.K >= opt.chunked_min_observations
    while True:
        if need:
            # the previous linearisation (and the factor of its reduced matrix) is released before the next is built
            ne = cf = Vinv = rhs = None
            data.linearisation = None
            if chunked:
                release_free_heap()  # (the previous linearisation's pages)
                # r, w, cost: of the current state (from the start or the accepted trial step)
                ne = ChunkedNormal(pb, lay, st, data, r, w, 1.0 / radius)
            else:
                r, *jac, pslot = evaluate(pb, lay, st, data, True)
                w, cost = robust(r, data.K, opt)
                ne = Normal(r, jac, pslot, lay, w, opt.num_threads)  # takes the Jacobian over (weighted, sparse)
                data.linearisation = (st, r, w, ne)
            need = False
            if ne.grad_max <= opt.gradient_tolerance:
                return st, cost0, cost, it, Termination.CONVERGED, f"gradient tolerance reached (max|g| = {ne.grad_max:.3g})"
        if it >= opt.max_iterations:
            return st, cost0, cost, it, Termination.MAX_ITERATIONS, f"stopped after {it} iterations"
        it += 1
        lam = 1.0 / radius
        cf = Vinv = rhs = None  # (a rejected step's factor: released before the next reduced matrix is built)
        sch = ne.schur(lam)
        ok = sch is not None
        if ok:
            S, rhs, Vinv, _ = sch
            del sch
            cf = cho_factor(S)  # overwrites S
            del S
            ok = cf is not None
        if ok:
            D = np.concatenate([ne.dU, ne.dV.ravel()])
            g = np.concatenate([ne.gc, ne.gp.ravel()])
            if chunked:
                d = ne.step(cf, Vinv, rhs, lam)
            else:
                d = ne.solve_with(cf, Vinv, ne.gc, ne.gp, rhs)
                # one step of iterative refinement against the exact operator J^T J + lam D: forming
                # S = U - W V^-1 W^T cancels digits when parameters are nearly dependent
                Jd = ne.Jc @ d[: lay.nc] + ne.Jp @ d[lay.nc :] if lay.nc else ne.Jp @ d
                Ad = np.concatenate([ne.Jc.T @ Jd, ne.Jp.T @ Jd]) + lam * D * d
                res = -g - Ad
                if np.all(np.isfinite(res)) and np.linalg.norm(res) > 1e-14 * np.linalg.norm(g):
                    d = d + ne.solve_with(cf, Vinv, -res[: lay.nc], -res[lay.nc :].reshape(-1, 3))
            ok = bool(np.all(np.isfinite(d)))
        if ok:
            dc, dp = d[: lay.nc], d[lay.nc :]
            model = 0.5 * (-(g @ d) + lam * float(D @ (d * d)))
            if 0 <= model <= opt.function_tolerance * cost:
                return st, cost0, cost, it, Termination.CONVERGED, "predicted decrease below the function tolerance"
            xn = np.sqrt(sum(float(p @ p) for p in st.cam_params) + float(np.sum(st.t**2)) + float(np.sum(st.X**2)))
            dn = float(np.sqrt(d @ d))
            if dn <= opt.parameter_tolerance * (xn + opt.parameter_tolerance):
                return st, cost0, cost, it, Termination.CONVERGED, f"parameter tolerance reached (|dx| = {dn:.3g})"
            st_new = st.plus(lay, dc, dp)
            try:
                r_new = evaluate(pb, lay, st_new, data, False)
            except InvalidInputError:
                # the step left the camera model's domain (e.g. a focal length <= 0): rejected like a step
                # that increases the cost, so the trust region shrinks
                r_new = None
            if r_new is None:
                cost_new, rho, ok = float("inf"), -1.0, False
            else:
                _, cost_new = robust(r_new, data.K, opt, weights=False)  # (weights only if accepted)
                rho = (cost - cost_new) / model if model > 0 else -1.0
                ok = bool(np.isfinite(cost_new)) and rho > 1e-3
        if ok:
            change = cost - cost_new
            st, cost = st_new, cost_new
            r = r_new
            del r_new
            if chunked:
                # the accepted step's linearisation is rebuilt below: the old one (its residuals, weights, point
                # blocks) and the factor are released before the new weights are computed
                ne = cf = Vinv = rhs = sch = None
                d = dc = dp = st_new = None
            # the chunked path linearises at these residuals; the full path re-evaluates them with the Jacobian
            w = robust(r, data.K, opt)[0] if chunked else None
            radius = min(1e16, radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
            decrease = 2.0
            need = True
            if abs(change) <= opt.function_tolerance * (cost + change):
                return st, cost0, cost, it, Termination.CONVERGED, "function tolerance reached"
        else:
            radius /= decrease
            decrease *= 2.0
            if radius < 1e-32:
                return st, cost0, cost, it, Termination.CONVERGED, "trust region collapsed: no further decrease possible"
