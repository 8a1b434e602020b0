"""GNSS positions against a block: a constant datum offset, per-image misfits, and the images that agree.

- :func:`gnss_offset`: the constant difference between the GNSS heights/positions and the GCPs' datum,
  from centres adjusted on the GCPs alone;
- :func:`gnss_misfit`: adjusted antenna position minus the given GNSS position per image
  (:data:`GNSS_REJECT_SIGMA` flags blunders);
- :func:`gnss_consensus`: the images whose relative positions agree with their GNSS (RANSAC over
  triplets of Umeyama similarities).

References
----------
Fischler, M. A., Bolles, R. C. (1981). Random sample consensus. Comm. ACM 24(6), 381-395.
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point patterns.
IEEE TPAMI 13(4), 376-380.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .georef_control import ControlInputs
from .georef_datum import collinear

__all__ = ["GnssOffset", "GNSS_OFFSET_MIN_GCPS", "gnss_offset", "GNSS_REJECT_SIGMA", "gnss_misfit", "GNSS_CONSENSUS_SPREAD", "GNSS_CONSENSUS_SIGMA", "GnssConsensus", "gnss_consensus"]


@dataclass
class GnssOffset:
    """A constant difference between the GNSS positions and the GCPs' datum (:func:`gnss_offset`).

    Attributes
    ----------
    offset_m : (3,) GCP datum minus GNSS datum (median of centre − GNSS), metres (X, Y, Z of the CRS)
    std_m : (3,) σ of the offset
    n_images : int, images with GNSS that entered the estimate
    significant : (3,) bool, axes where the offset is both > 5 σ and > 3 × the GNSS σ
    """

    offset_m: np.ndarray
    std_m: np.ndarray
    n_images: int
    significant: np.ndarray


#: GNSS offsets are only looked for with at least this many GCPs in the block
GNSS_OFFSET_MIN_GCPS = 3


def gnss_offset(centers_m, center_std_m, gnss_xyz, gnss_sigma, extra_std_m=None) -> GnssOffset | None:
    """Constant offset of the GNSS positions against camera centres adjusted on the GCPs alone.

    GNSS heights of drones are ellipsoidal, above the EGM96 geoid or above the take-off point, depending on
    the model and its RTK setting; GCPs are surveyed in a national frame with its own heights (e.g. LV95 /
    LN02, EPSG:2056, where geoid and ellipsoid are ~50 m apart). A block adjusted on both with centimetre σ
    is torn between them. The survey therefore adjusts the block once on its GCPs (GNSS σ × 1000: the
    GNSS only holds what the GCPs leave free) and passes the adjusted centres here: the offset is the
    median of (centre − GNSS) over the images, and its σ the median σ of the centres (their errors from a
    few GCPs are common to the block, so no 1/sqrt(n)). The offset can only be separated from the camera
    constant (nadir blocks: a focal error moves every centre's height alike) because the GCPs fix the
    height of the ground; that is why it is not estimated from the GNSS-placed block before the adjustment.
    An axis is *significant* when its offset exceeds 5 σ and 3 × the median GNSS σ.

    That separation needs ground of varied height: over a flat field the GCPs fix the ground but not the flying
    height (f -> s f with every camera at s times its height above the ground leaves every image point in place), so
    the Z offset is then as uncertain as the focal length. ``extra_std_m`` (3,) is added in quadrature to the σ for
    that (the survey passes the lens's relative focal-length σ times the flying height when the focal length is not
    a user's calibration).

    Parameters
    ----------
    centers_m, center_std_m, gnss_xyz, gnss_sigma : (n, 3) arrays, metres; NaN rows are skipped
    extra_std_m : (3,) array, metres, optional

    Returns
    -------
    GnssOffset or None (fewer than 3 images with GNSS, centre and σ)
    """
    C, S, G, GS = (np.asarray(a, float) for a in (centers_m, center_std_m, gnss_xyz, gnss_sigma))
    ok = np.all(np.isfinite(C), 1) & np.all(np.isfinite(S), 1) & np.all(np.isfinite(G), 1)
    if ok.sum() < 3:
        return None
    d = C[ok] - G[ok]
    med = np.median(d, axis=0)
    std = np.median(S[ok], axis=0)
    if extra_std_m is not None:
        std = np.hypot(std, np.asarray(extra_std_m, float))
    g_sig = np.median(GS[ok], axis=0) if np.isfinite(GS[ok]).all() else np.full(3, np.inf)
    significant = (np.abs(med) > 5 * std) & (np.abs(med) > 3 * g_sig)
    return GnssOffset(med, std, int(ok.sum()), significant)


#: after the robust round, a GNSS position more than this many σ (any axis) from the adjusted antenna position is
#: left out of the following rounds when such positions are few (<= 10 % of the block's GNSS images)
GNSS_REJECT_SIGMA = 5.0


def gnss_misfit(rec, images, ctrl: "ControlInputs") -> dict:
    """Adjusted antenna position minus the given GNSS position of every image of ``images`` that has one.

    The antenna is at ``C + Rᵀ l`` (``C`` the projection centre, ``R`` = ``cam_from_world`` rotation, ``l`` the
    lever arm in the camera frame, metres).

    Returns
    -------
    dict image index -> (d (3,) metres, adjusted − given in X, Y, Z of the CRS; z (3,) |d| / σ per axis)
    """
    images = np.asarray(images, np.int64)
    g = ctrl.gnss_xyz[images]
    have = np.all(np.isfinite(g), axis=1)
    ii = images[have]
    A = rec.centers()[ii] + np.einsum("kji,j->ki", rec.R[ii], np.asarray(ctrl.lever_arm_m, float))
    d = A - ctrl.gnss_xyz[ii]
    z = np.abs(d) / ctrl.gnss_sigma[ii]
    return {int(i): (d[k], z[k]) for k, i in enumerate(ii)}


#: :func:`gnss_consensus`: an image is consistent with the block's similarity to the GNSS when its centre lands
#: within this share of the GNSS positions' RMS spread (or GNSS_CONSENSUS_SIGMA σ, whichever is larger) of its GNSS
#: position. On a 40-station building ring (seed 0: a 20-image block before its final adjustment) the right images
#: landed within 0.01-0.24 m (2 % of the 6.4 m spread at most), the three wrongly resected ones 1.2-7.3 m away
GNSS_CONSENSUS_SPREAD = 0.06
GNSS_CONSENSUS_SIGMA = 5.0


@dataclass
class GnssConsensus:
    """Outcome of :func:`gnss_consensus`.

    Attributes
    ----------
    inliers : (n,) bool, images whose centre the consensus similarity puts within ``tolerance_m`` of their GNSS
    residuals_m : (n,) float, |S(C) − G| after the similarity refitted on the inliers (metres)
    tolerance_m : float
    """

    inliers: np.ndarray
    residuals_m: np.ndarray
    tolerance_m: float


def gnss_consensus(centers, gnss_xyz, gnss_sigma, *, max_samples: int = 600, seed: int = 0) -> GnssConsensus | None:
    """Images of a block whose relative positions agree with their GNSS positions: RANSAC over triplets.

    A block can hold a few wrongly resected images (weak tie geometry, e.g. stations at a building's corner): their
    centres sit metres from where their GNSS says, and with them the block contradicts its GNSS as a whole. Every
    triplet of images (or ``max_samples`` seeded random triplets when there are more) gives a similarity model ->
    CRS (Umeyama); the one that puts the most centres within the tolerance of their GNSS wins (ties: the smaller
    sum of residuals), and is refitted on its inliers.

    Parameters
    ----------
    centers : (n, 3) model-frame camera centres
    gnss_xyz, gnss_sigma : (n, 3) metres in the CRS (rows with NaN are never inliers)
    max_samples : int
    seed : int, of the triplet sampling (deterministic)

    Returns
    -------
    GnssConsensus, or None with fewer than 4 images with GNSS or no triplet that is not a straight line.
    The tolerance is max(:data:`GNSS_CONSENSUS_SPREAD` x the RMS spread of the GNSS positions about their mean,
    :data:`GNSS_CONSENSUS_SIGMA` x the median horizontal GNSS σ).

    References
    ----------
    Fischler, M. A., Bolles, R. C. (1981). Random sample consensus. Comm. ACM 24(6), 381-395.
    Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point patterns.
    IEEE TPAMI 13(4), 376-380.
    """
    from itertools import combinations

    from ..geometry import umeyama

    C = np.asarray(centers, float)
    G = np.asarray(gnss_xyz, float)
    S_ = np.asarray(gnss_sigma, float)
    have = np.all(np.isfinite(G), axis=1) & np.all(np.isfinite(C), axis=1)
    idx = np.nonzero(have)[0]
    if len(idx) < 4:
        return None
    Gh, Ch = G[idx], C[idx]
    spread = float(np.sqrt(np.mean(np.sum((Gh - Gh.mean(0)) ** 2, axis=1))))
    sig_h = float(np.median(S_[idx][:, :2])) if np.all(np.isfinite(S_[idx][:, :2])) else 0.0
    tol = max(GNSS_CONSENSUS_SPREAD * spread, GNSS_CONSENSUS_SIGMA * sig_h)
    m = len(idx)
    if m * (m - 1) * (m - 2) // 6 <= max_samples:
        samples = list(combinations(range(m), 3))
    else:
        rng = np.random.default_rng(seed)
        samples = [tuple(rng.choice(m, 3, replace=False)) for _ in range(max_samples)]
    best = None
    for s in samples:
        s = list(s)
        if collinear(Gh[s]) or collinear(Ch[s]):
            continue
        try:
            T = umeyama(Ch[s], Gh[s])
        except (ValueError, np.linalg.LinAlgError):
            continue
        r = np.linalg.norm(T(Ch) - Gh, axis=1)
        ok = r <= tol
        key = (int(ok.sum()), -float(np.sum(np.minimum(r, tol))))
        if best is None or key > best[0]:
            best = (key, ok)
    if best is None or best[0][0] < 3:
        return None
    ok = best[1]
    T = umeyama(Ch[ok], Gh[ok])
    r = np.linalg.norm(T(Ch) - Gh, axis=1)
    res = np.full(len(C), np.inf)
    res[idx] = r
    return GnssConsensus(res <= tol, res, tol)
