"""The random standard deviation of every orthophoto cell, split into independent parts (``ortho_sigma.tif``).

The model uses only what the user has (``cameras.json``, the frames, the DSM, the correction's options), no
truth. Per cell, whose value is the chosen frame's value at the cell's projection ``(u, v)`` (one frame per
cell, no blending: :mod:`.ortho`):

**sensor**
    σ_s = NETD · √(Σ wᵢ²): NETD in the frames' unit, ``wᵢ`` the sampling weights (nearest: one weight 1, so
    σ_s = NETD; bilinear: the four bilinear weights, which average the noise of four pixels). The NETD is
    estimated from the frames themselves (:func:`estimate_netd`): pairs of overlapping frames sampled at
    the same ground points, the difference after the pair's own offset (its median), robust scatter (1.4826
    MAD) divided by the difference's noise factor (√2 for two single pixels), on the flattest tenth of the
    points, less the geometry model's own variance of the difference there (misregistration × gradient).
**geometry**
    the pixel position's 2 × 2 covariance Σ_uv = J diag(σ²) Jᵀ, J the finite-difference Jacobian of the
    projection with respect to the camera centre (3, σ = ``center_std``, m), the rotation's left increment
    about the camera axes (3, σ = ``rotation_std_deg``) and the ground height (σ = ``dsm_sigma_m``); then
    bilinear: σ_g² = ∇Iᵀ Σ_uv ∇I with ∇I the frame's gradient at (u, v) (unit/px); nearest: per image axis,
    the variance of the value when the position moves across a pixel border, p₊ d₊² + p₋ d₋² − (p₊ d₊ +
    p₋ d₋)², p± the normal probabilities of crossing (from the sub-pixel position and σ_u), d± the steps to
    the neighbour pixels (the sampling's own term). Squared differences are de-biased by their noise (2 NETD²).
**correction** (``--correct``)
    finite differences of the same correction function (seed 000's eq. 7–8 and the transmission) with
    respect to the emissivity (σ ``emissivity_sigma``), the viewing angle (σ ``angle_sigma_deg``), the
    distance (from ``dsm_sigma_m``), the reflected temperature (σ ``ambient_sigma_k``) and, with the
    transmission, the relative humidity (σ ``humidity_sigma``); the sensor and geometry parts are carried
    through ∂T_c/∂T₀.

Total random σ = √(σ_s² + σ_g² + σ_c²). The radiometric calibration's error is common to every cell of a
frame (systematic): it is reported separately in the raster's metadata (the camera's stated accuracy where
known; otherwise recorded as unknown). Correlations between the pose's parameters are not in
``cameras.json`` and are ignored; the intrinsics' σ is not propagated (common to all images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SigmaConfig", "estimate_netd", "pixel_covariance", "sample_sigma", "correction_sigma", "summarise",
           "BAND_NAMES"]

BAND_NAMES = ("total random", "sensor", "geometry", "correction")


@dataclass(frozen=True)
class SigmaConfig:
    """Inputs of the σ model that ``cameras.json`` and the frames do not give.

    Attributes
    ----------
    netd : sensor noise in the frames' unit; None = estimated from the overlapping frames
    dsm_sigma_m : σ of the surface height (m); None = one DSM cell (a documented conservative value for a
        dense-matching DSM; 0 for a surveyed, exact DSM)
    emissivity_sigma, angle_sigma_deg, ambient_sigma_k, humidity_sigma : σ of the correction's inputs
    """

    netd: float | None = None
    dsm_sigma_m: float | None = None
    emissivity_sigma: float = 0.01
    angle_sigma_deg: float = 2.0
    ambient_sigma_k: float = 1.0
    humidity_sigma: float = 0.1


def _rot(w):
    """Rotation matrix of the rotation vector ``w`` (3,) (Rodrigues)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = np.asarray(w, float) / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def _uv(cam, R, t, P):
    Xc = P @ R.T + t
    out = np.full((len(P), 2), np.nan)
    ok = np.isfinite(Xc).all(axis=1) & (Xc[:, 2] > 1e-9)
    if ok.any():
        out[ok] = np.asarray(cam.project(Xc[ok]), float)
    return out


def pixel_covariance(cam, R, t, P, center_std, rotation_std_deg, z_std: float) -> tuple[np.ndarray, np.ndarray]:
    """The projected position (N, 2) px and its covariance (N, 2, 2) px² from the pose's and the height's σ.

    Parameters
    ----------
    cam : Camera; R, t : cam_from_world; P : (N, 3) world points (m)
    center_std : (3,) m or None (0); rotation_std_deg : (3,) deg about the camera axes or None (0)
    z_std : σ of the points' height (m)
    """
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    C = -R.T @ t
    uv0 = _uv(cam, R, t, P)
    cs = np.nan_to_num(np.asarray(center_std if center_std is not None else np.zeros(3), float))
    rs = np.radians(np.nan_to_num(np.asarray(rotation_std_deg if rotation_std_deg is not None else np.zeros(3), float)))
    cov = np.zeros((len(P), 2, 2))
    hc, hr, hz = 1e-3, 1e-5, 1e-3
    for i in range(3):
        for kind, s, h in (("c", cs[i], hc), ("r", rs[i], hr)):
            if s <= 0:
                continue
            if kind == "c":
                Ci = C.copy()
                Ci[i] += h
                Ri, ti = R, -R @ Ci
            else:
                w = np.zeros(3)
                w[i] = h
                Ri = _rot(w) @ R
                ti = -Ri @ C
            J = (_uv(cam, Ri, ti, P) - uv0) / h
            cov += s * s * J[:, :, None] * J[:, None, :]
    if z_std > 0:
        Pz = P.copy()
        Pz[:, 2] += hz
        J = (_uv(cam, R, t, Pz) - uv0) / hz
        cov += z_std * z_std * J[:, :, None] * J[:, None, :]
    return uv0, cov


def _q(x):
    """Upper normal tail probability."""
    from scipy.special import ndtr

    return ndtr(-x)


def sample_sigma(frame, uv, cov, netd: float, sampling: str) -> tuple[np.ndarray, np.ndarray]:
    """Sensor and geometry σ (N,) of values sampled from ``frame`` at ``uv`` (N, 2) px with covariance ``cov``.

    ``sampling``: "nearest" or "bilinear" (as the ortho samples). Units: the frame's (K for kelvin)."""
    a = np.asarray(frame, float)
    if a.ndim == 3:
        a = a[..., 0]
    H, W = a.shape
    u, v = uv[:, 0], uv[:, 1]
    n2 = 2.0 * netd * netd
    if str(sampling) == "bilinear":
        x0 = np.clip(np.floor(u).astype(int), 0, W - 2)
        y0 = np.clip(np.floor(v).astype(int), 0, H - 2)
        fx = np.clip(u - x0, 0, 1)
        fy = np.clip(v - y0, 0, 1)
        a00, a01, a10, a11 = a[y0, x0], a[y0, x0 + 1], a[y0 + 1, x0], a[y0 + 1, x0 + 1]
        w2 = ((1 - fx) * (1 - fy)) ** 2 + (fx * (1 - fy)) ** 2 + ((1 - fx) * fy) ** 2 + (fx * fy) ** 2
        sens = netd * np.sqrt(w2)
        gx = (1 - fy) * (a01 - a00) + fy * (a11 - a10)
        gy = (1 - fx) * (a10 - a00) + fx * (a11 - a01)
        gx2 = np.maximum(gx * gx - n2 * ((1 - fy) ** 2 + fy ** 2), 0.0)
        gy2 = np.maximum(gy * gy - n2 * ((1 - fx) ** 2 + fx ** 2), 0.0)
        var = gx2 * cov[:, 0, 0] + gy2 * cov[:, 1, 1] + 2 * gx * gy * cov[:, 0, 1]
        return sens, np.sqrt(np.maximum(var, 0.0))
    r = np.clip(np.rint(v).astype(int), 0, H - 1)
    c = np.clip(np.rint(u).astype(int), 0, W - 1)
    a0 = a[r, c]
    var = np.zeros(len(u))
    for f, s2, step in ((u - c, cov[:, 0, 0], lambda d: a[r, np.clip(c + d, 0, W - 1)]),
                        (v - r, cov[:, 1, 1], lambda d: a[np.clip(r + d, 0, H - 1), c])):
        s = np.sqrt(np.maximum(s2, 1e-30))
        pp, pm = _q((0.5 - f) / s), _q((0.5 + f) / s)
        dp, dm = step(1) - a0, step(-1) - a0
        dp2, dm2 = np.maximum(dp * dp - n2, 0.0), np.maximum(dm * dm - n2, 0.0)
        var += pp * dp2 + pm * dm2 - (pp * dp + pm * dm) ** 2
    return np.full(len(u), float(netd)), np.sqrt(np.maximum(var, 0.0))


def correction_sigma(t0, angle_rad, distance_m, on, config, sig: SigmaConfig, dist_sigma_m):
    """(∂T_c/∂T₀, σ_c) of the correction (:func:`~.correction.apply_correction`) by central differences.

    σ_c combines the emissivity, angle, distance, reflected temperature and (with the transmission)
    humidity terms; arrays of the shape of ``t0`` (K)."""
    from dataclasses import replace

    from .correction import apply_correction, as_correction_config, correct_temperature

    cfg = as_correction_config(config)
    T0 = np.asarray(t0, float)

    def f(T=T0, a=angle_rad, d=distance_m, c=cfg):
        return apply_correction(T, a, d, on, c)[0]

    dT = 0.05
    dTc = (f(T=T0 + dT) - f(T=T0 - dT)) / (2 * dT)
    var = np.zeros_like(T0)
    ha = np.radians(0.1)
    var += ((f(a=angle_rad + ha) - f(a=np.maximum(angle_rad - ha, 0))) / (2 * ha) * np.radians(sig.angle_sigma_deg)) ** 2
    if cfg.transmission:
        hd = 0.5
        var += ((f(d=distance_m + hd) - f(d=np.maximum(distance_m - hd, 0))) / (2 * hd) * dist_sigma_m) ** 2
        hh = 0.01
        up = replace(cfg, relative_humidity=min(1.0, cfg.relative_humidity + hh))
        dn = replace(cfg, relative_humidity=max(0.0, cfg.relative_humidity - hh))
        var += ((f(c=up) - f(c=dn)) / (up.relative_humidity - dn.relative_humidity) * sig.humidity_sigma) ** 2
    hk = 0.1
    var += ((f(c=replace(cfg, ambient_c=cfg.ambient_c + hk)) - f(c=replace(cfg, ambient_c=cfg.ambient_c - hk)))
            / (2 * hk) * sig.ambient_sigma_k) ** 2
    # emissivity: the same inversion with ε ± h at the cell's own ε, τ
    _, eps, tau, _ = apply_correction(T0, angle_rad, distance_m, on, cfg)
    he = 1e-3
    tau1 = np.where(on, tau, 1.0)

    def inv(e):
        return correct_temperature(T0, e, cfg.ambient_k, transmission=tau1, atmosphere_k=cfg.air_k)

    var += ((inv(np.clip(eps + he, 1e-3, 1)) - inv(np.clip(eps - he, 1e-3, 1))) / (2 * he) * sig.emissivity_sigma) ** 2
    return dTc, np.sqrt(var)


def estimate_netd(frames, cameras, poses, points, *, max_pairs: int = 40, pose_std=None,
                  z_std: float = 0.0) -> tuple[float, dict]:
    """The sensor noise (frames' unit) from pairs of overlapping frames at the same ground points.

    Parameters
    ----------
    frames : callable index → (H, W) frame; cameras, poses : per image Camera and (R, t)
    points : (M, 3) ground points (m), e.g. a decimated DSM

    Each image is paired with the image whose centre is nearest. Per pair, both frames are sampled bilinearly
    at the points both see; ``d = I_a − I_b − median`` (the pair's offset); per point the noise factor
    ``√(Σw_a² + Σw_b²)`` (the bilinear weights) normalises ``d``; the points whose larger frame gradient is in
    the lowest tenth are kept; s = 1.4826 · MAD of the normalised differences. The pose's share of them
    (``pose_std(k)`` → (center_std, rotation_std_deg), ``z_std``: the geometry model's variance of ``d`` at
    those points, median) is removed in quadrature: NETD = √(s² − geo) (at least s / 2). Returns
    ``(netd, record)``.
    """
    n = len(poses)
    C = np.array([-np.asarray(R).T @ np.asarray(t) for R, t in poses])
    pairs = set()
    for k in range(n):
        d = np.linalg.norm(C - C[k], axis=1)
        d[k] = np.inf
        j = int(np.argmin(d))
        pairs.add((min(k, j), max(k, j)))
    pairs = sorted(pairs)
    if len(pairs) > max_pairs:
        pairs = [pairs[i] for i in np.linspace(0, len(pairs) - 1, max_pairs).astype(int)]
    P = np.asarray(points, float)
    P = P[np.isfinite(P).all(axis=1)]
    ds, gs, geos = [], [], []
    for a, b in pairs:
        samp = []
        for k in (a, b):
            cam, (R, t) = cameras[k], poses[k]
            cs, rs = pose_std(k) if pose_std is not None else (None, None)
            uv, cov = pixel_covariance(cam, np.asarray(R), np.asarray(t), P, cs, rs, z_std)
            fr = np.asarray(frames(k), float)
            if fr.ndim == 3:
                fr = fr[..., 0]
            samp.append((uv, fr, cov))
        ok = np.ones(len(P), bool)
        for uv, fr, _ in samp:
            H, W = fr.shape
            with np.errstate(invalid="ignore"):
                ok &= (uv[:, 0] >= 1) & (uv[:, 0] < W - 2) & (uv[:, 1] >= 1) & (uv[:, 1] < H - 2)
        if ok.sum() < 50:
            continue
        vals, w2s, grads, geo, tr = [], [], [], 0.0, 0.0
        for uv, fr, cov in samp:
            u, v = uv[ok, 0], uv[ok, 1]
            x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
            fx, fy = u - x0, v - y0
            val = ((fr[y0, x0] * (1 - fx) + fr[y0, x0 + 1] * fx) * (1 - fy) + (fr[y0 + 1, x0] * (1 - fx)
                                                                             + fr[y0 + 1, x0 + 1] * fx) * fy)
            w2s.append(((1 - fx) * (1 - fy)) ** 2 + (fx * (1 - fy)) ** 2 + ((1 - fx) * fy) ** 2 + (fx * fy) ** 2)
            r, c = np.rint(v).astype(int), np.rint(u).astype(int)
            # the gradient over 3 × 5 pixels (its noise NETD²/24 per axis, not NETD²/2: the flattest points are
            # chosen by the signal, not by the noise)
            gx = sum(fr[r + i, np.minimum(c + 2, W - 1)] - fr[r + i, np.maximum(c - 2, 0)] for i in (-1, 0, 1)) / 12
            gy = sum(fr[np.minimum(r + 2, H - 1), c + i] - fr[np.maximum(r - 2, 0), c + i] for i in (-1, 0, 1)) / 12
            grads.append(np.hypot(gx, gy))
            cv = cov[ok]
            geo = geo + gx * gx * cv[:, 0, 0] + gy * gy * cv[:, 1, 1] + 2 * gx * gy * cv[:, 0, 1]
            tr = tr + (cv[:, 0, 0] + cv[:, 1, 1]) / 24  # the gradients' own noise: NETD² / 24 per axis
            vals.append(val)
        d = vals[0] - vals[1]
        fin = np.isfinite(d)
        d = (d - np.median(d[fin])) / np.sqrt(w2s[0] + w2s[1])
        ds.append(d[fin])
        geos.append(np.stack([geo, tr])[:, fin] / (w2s[0] + w2s[1])[fin])
        gs.append(np.maximum(grads[0], grads[1])[fin])
    if not ds:
        return float("nan"), {"method": "no overlapping frames", "pairs": 0, "points": 0}
    d, g, geo = np.concatenate(ds), np.concatenate(gs), np.concatenate(geos, axis=1)
    keep = g <= np.quantile(g, 0.1)
    dk = d[keep]
    raw = float(1.4826 * np.median(np.abs(dk - np.median(dk))))
    # the pose's share of the kept differences (the geometry model's variance of d), removed in quadrature
    netd = raw
    for _ in range(3):  # the squared gradients de-biased by the noise being estimated
        share = float(np.median(np.maximum(geo[0, keep] - netd * netd * geo[1, keep], 0.0)))
        netd = float(np.sqrt(max(raw * raw - share, 0.25 * raw * raw)))
    return netd, {"method": "overlapping frames (robust scatter of the difference at the same ground points, "
                            "flattest tenth, per-pair offset removed, the pose's share removed)", "pairs": len(ds),
                           "points": int(keep.sum()), "raw_scatter": raw}


def summarise(bands: np.ndarray) -> dict:
    """``ortho.json``'s ``sigma`` figures from (4, N) valid-cell σ values (total, sensor, geometry, correction)."""
    out = {}
    for name, b in zip(("total", "sensor", "geometry", "correction"), bands):
        b = b[np.isfinite(b)]
        out[name] = {"median": float(np.median(b)) if b.size else None,
                     "p95": float(np.quantile(b, 0.95)) if b.size else None}
    tot = bands[0][np.isfinite(bands[0])]
    out["share_below"] = {str(x): (float(np.mean(tot < x)) if tot.size else None) for x in (0.1, 0.5, 1.0)}
    return out


def tile_sigma(res: dict, X, Y, Z, frames, cameras, poses, pose_std, sampling: str, netd: float,
               z_std: float) -> np.ndarray:
    """(3, h, w) sensor, geometry σ of one ortho tile (NaN where no source) and a zero correction band.

    ``res``: :func:`~.ortho.ortho_tile`'s result; ``X, Y, Z`` (h, w) the cells; ``pose_std(k)`` → (center_std,
    rotation_std_deg) of image ``k``; ``frames(k)``, ``cameras[k]``, ``poses[k]`` as for the mosaic."""
    src = res["source"].ravel()
    h, w = res["source"].shape
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    out = np.full((3, h * w), np.nan)
    for k in np.unique(src[src >= 0]):
        sel = np.flatnonzero(src == k)
        R, t = poses[int(k)]
        cs, rs = pose_std(int(k))
        uv, cov = pixel_covariance(cameras[int(k)], R, t, P[sel], cs, rs, z_std)
        s, g = sample_sigma(frames(int(k)), uv, cov, netd, sampling)
        out[0, sel], out[1, sel], out[2, sel] = s, g, 0.0
    return out.reshape(3, h, w)


def dsm_points(dsm_path, max_points: int = 20000) -> tuple[np.ndarray, float]:
    """(M, 3) ground points of a decimated DSM GeoTIFF (at most ~``max_points``) and the DSM's cell size (m)."""
    import rasterio

    with rasterio.open(dsm_path) as src:
        k = max(1, int(np.ceil(np.sqrt(src.width * src.height / max_points))))
        h, w = max(1, src.height // k), max(1, src.width // k)
        z = np.asarray(src.read(1, out_shape=(h, w), masked=True).astype(float).filled(np.nan))
        tr = src.transform
    sx, sy = tr.a * src.width / w, tr.e * src.height / h
    c, r = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    P = np.column_stack([(tr.c + c * sx).ravel(), (tr.f + r * sy).ravel(), z.ravel()])
    return P[np.isfinite(P[:, 2])], float(tr.a)


def prepare_sigma(sv, dsm_path, config: SigmaConfig | None, unit: str) -> tuple[dict, dict]:
    """The per-run inputs of the tiles' σ (``{"netd", "z_std", "config"}``) and their ``ortho.json`` record.

    ``sv``: the survey's frames (callable index → frame, ``cameras``, ``poses``, ``images`` with the pose σ)."""
    cfg = config or SigmaConfig()
    pts, dsm_gsd = dsm_points(dsm_path)
    z_std = float(dsm_gsd if cfg.dsm_sigma_m is None else cfg.dsm_sigma_m)
    if cfg.netd is not None:
        netd, rec = float(cfg.netd), {"method": "given"}
    else:
        netd, rec = estimate_netd(sv, sv.cameras, sv.poses, pts, z_std=z_std,
                                  pose_std=lambda k: (sv.images[k].center_std, sv.images[k].rotation_std_deg))
    notes = []
    if not np.isfinite(netd):
        netd = 0.0
        notes.append("sensor noise not estimated (no overlapping frames): sensor band 0")
    missing = sum(1 for im in sv.images if im.center_std is None or im.rotation_std_deg is None)
    if missing:
        notes.append(f"{missing} image(s) without a pose σ in cameras.json: their pose taken as exact")
    record = {"netd": netd, "netd_unit": unit, "netd_source": rec, "dsm_sigma_m": z_std,
              "dsm_sigma_source": "given" if cfg.dsm_sigma_m is not None else "one DSM cell (default)",
              "correction_inputs": {"emissivity_sigma": cfg.emissivity_sigma, "angle_sigma_deg": cfg.angle_sigma_deg,
                                    "ambient_sigma_k": cfg.ambient_sigma_k, "humidity_sigma": cfg.humidity_sigma},
              "systematic": None, "systematic_note": "radiometric calibration accuracy: not stated for this camera "
                                                      "(not in the frames' metadata); not included in the bands",
              "notes": notes}
    return {"netd": netd, "z_std": z_std, "config": cfg}, record
