"""Georeferencing and the final adjustment of an oriented block: GNSS, GCPs, check points.

1. **Start**: a similarity (Umeyama 1991) from the model's projection centres to the GNSS positions
   (>= 3 images, not collinear), else from the triangulated GCPs to their coordinates (>= 3 GCPs).
2. **Final bundle adjustment** on the engine with GNSS camera-centre priors (σ per image, lever arm in the
   camera frame) and weighted GCPs (σ per coordinate, their image measurements with σ in px); the camera
   is self-calibrated (the named parameters free) unless a calibrated camera was given. A first robust
   (Huber) solve finds blunders: tie observations above ``max_error_px`` and GCP measurements above
   ``max(gcp_reject_px, 5 σ)`` are removed (a GCP measured in an image where it cannot be seen ends
   here, reported by image and id); the second, unweighted-loss solve gives σ0, the a-posteriori
   covariance of every camera parameter and pose, and the residuals.
3. **Check points never enter the adjustment**: each is intersected afterwards from its image
   measurements with the adjusted cameras, and its covariance is the propagation of both the measurement
   noise and the a-posteriori covariance of the poses and intrinsics involved::

       Σ_X = N⁻¹ + G Σ_θ Gᵀ,   N = J_Xᵀ W J_X,   G = N⁻¹ J_Xᵀ W J_θ

   (J by central differences in the engine's parameterisation: left rotation increment about the
   camera axes, projection centre, camera parameters).

References
----------
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point patterns.
IEEE PAMI 13(4), 376-380.
Khodaei, M., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2019?). 3D surface generation from aerial
thermal imagery (seed 003: GCPs for absolute orientation, check points, Table 3 accuracy layout).
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §4.2.4 (propagation), §15.4.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._memory import release_free_heap
from ..enums import StrChoice
from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle

__all__ = ["Datum", "DatumSource", "GnssOffset", "gnss_offset", "ControlInputs", "FinalAdjustment", "similarity_start", "apply_similarity", "final_adjustment",
           "intersect_check_points", "axis_statistics"]


@dataclass
class ControlInputs:
    """What fixes the datum, per image index of the block.

    Attributes
    ----------
    gnss_xyz : (n, 3) m in the CRS, NaN rows where an image has none
    gnss_sigma : (n, 3) m
    lever_arm_m : (3,) antenna offset in the camera frame
    gcp_ids : list of str; gcp_xyz (G, 3); gcp_sigma (G, 3)
    gcp_obs : list of (image index, gcp index, (2,) xy px, sigma px)
    check_ids, check_xyz, check_obs : the same for check points (never adjusted)
    attitude : (n, 3, 3) cam_from_world rotations in the CRS observed by the camera's gimbal/IMU (NaN where an image has
        none; :mod:`.attitude`), or None. Used only for a block whose GNSS positions lie on one straight line or
        otherwise leave its rotation undetermined (:func:`similarity_start`).
    """

    gnss_xyz: np.ndarray
    gnss_sigma: np.ndarray
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gcp_ids: list = field(default_factory=list)
    gcp_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_obs: list = field(default_factory=list)
    check_ids: list = field(default_factory=list)
    check_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    check_obs: list = field(default_factory=list)
    attitude: np.ndarray | None = None


#: the rotation about a straight GNSS line is taken from the images' attitudes when at least this many of the block's
#: images have one
MIN_ATTITUDE_IMAGES = 3
#: ... and when, turned about the line to them, the block's cameras agree with them within this angle (degrees, median
#: over the frames): the other two axes are fixed by the GNSS line and the tie points, so a larger disagreement means
#: attitudes that do not describe these cameras (a payload that writes zeros, another mounting). The M3T flight: 1.4°
ATTITUDE_MAX_DISAGREEMENT_DEG = 10.0


def attitude_images(ctrl, images) -> np.ndarray:
    """The images of ``images`` with an observed attitude."""
    if ctrl.attitude is None:
        return np.zeros(0, np.int64)
    images = np.asarray(images, np.int64)
    return images[np.all(np.isfinite(ctrl.attitude[images]), axis=(1, 2))]


def _roll_from_attitude(rec, images, g, S, ctrl, lead: str):
    """``S`` (a similarity to GNSS positions ``g`` that lie on one line) turned about that line so that the block's
    cameras agree with their observed attitudes (:func:`.attitude.rotation_about_axis`). Returns (S', note), (None, "")
    without enough attitudes, or (None, why) when the attitudes disagree with the block
    (:data:`ATTITUDE_MAX_DISAGREEMENT_DEG`)."""
    from ..geometry import Similarity
    from .attitude import ATTITUDE_SIGMA_DEG, rotation_about_axis

    att = attitude_images(ctrl, images)
    if len(att) < MIN_ATTITUDE_IMAGES:
        return None, ""
    c = g.mean(axis=0)
    axis = np.linalg.svd(g - c, full_matrices=False)[2][0]
    R_est = rec.R[att] @ S.R.T
    alpha, al = rotation_about_axis(R_est, ctrl.attitude[att], axis)
    Q = matrix_from_axis_angle(alpha * axis)
    S2 = Similarity(S.scale, Q @ S.R, Q @ (S.translation - c) + c)
    off = np.degrees(np.linalg.norm(axis_angle_from_matrix(rec.R[att] @ S2.R.T @ np.swapaxes(ctrl.attitude[att], 1, 2)),
                                    axis=1))
    if float(np.median(off)) > ATTITUDE_MAX_DISAGREEMENT_DEG:
        return None, (f"the camera attitudes in the files disagree with the block by {float(np.median(off)):.1f}° (median "
                      f"over {len(att)} images, > {ATTITUDE_MAX_DISAGREEMENT_DEG:g}°) in the axes its GNSS fixes: not used")
    spread = float(np.degrees(np.median(np.abs(np.angle(np.exp(1j * (al - alpha)))))))
    return S2, (f"{lead}: the rotation about it is taken from the camera attitude of "
                f"{len(att)} image(s) (turned {np.degrees(alpha):+.1f}°, their median deviation {spread:.2f}°) and "
                f"enters the final adjustment as attitude priors (one {ATTITUDE_SIGMA_DEG:g}° observation of the "
                "block's rotation: gimbal errors are correlated from frame to frame)")


#: positions whose RMS distance from their best-fitting line is below this multiple of the GNSS σ in that direction
#: are taken as one straight line (:func:`_collinear`): their spread across it is noise, which cannot fix the
#: rotation about the line
COLLINEAR_SIGMA = 1.5


def _collinear(P: np.ndarray, sigma_xyz=None) -> bool:
    """Whether the points (N, 3) lie on one straight line: their second singular value below 2 % of the first, or,
    with ``sigma_xyz`` ((3,) positional σ per axis, metres), their RMS distance along the second principal direction
    ``u`` below :data:`COLLINEAR_SIGMA` × ``sqrt(Σ u_i² σ_i²)`` (the noise alone gives ~1 there).

    A hand-held walk along a facade (19 m, 30 frames) with 3 m GNSS (4.5 m vertical): 0.8-1.25 of that σ over 200
    noise draws -- a line; rotated about it by the noise, the block was rejected (datum undetermined). A 40 x 25 m
    grid of 30 positions with the same GNSS: 2.5-3.1 (not a line, georeferenced as before); 40 x 12 m: 1.4-1.9."""
    if len(P) < 3:
        return True
    _, s, vt = np.linalg.svd(P - P.mean(0), full_matrices=False)
    if s[1] < 0.02 * s[0]:
        return True
    if sigma_xyz is None:
        return False
    su = float(np.sqrt(np.sum(vt[1] ** 2 * np.asarray(sigma_xyz, float) ** 2)))
    return bool(s[1] / np.sqrt(len(P)) < COLLINEAR_SIGMA * su)


class DatumSource(StrChoice):
    """What placed a block in the CRS (:class:`Datum`)."""

    GNSS = "gnss"
    GNSS_ATTITUDE = "gnss+attitude"
    GCPS = "gcps"
    NONE = "none"


@dataclass(frozen=True)
class Datum:
    """What a block's start (:func:`similarity_start`) was placed on, as a value rather than a sentence.

    Attributes
    ----------
    source : DatumSource
        ``GNSS`` (camera positions), ``GNSS_ATTITUDE`` (positions on one line, the rotation about it from the
        camera attitudes), ``GCPS`` (GCPs triangulated in the model) or ``NONE`` (a local frame of arbitrary scale).
    n_gnss, n_attitude, n_gcps : int
        Images with GNSS, images with an attitude, GCPs used.

    ``str(datum)`` is the sentence written to survey.json (``blocks[].datum``) and the report.
    """

    source: DatumSource
    n_gnss: int = 0
    n_attitude: int = 0
    n_gcps: int = 0

    @property
    def georeferenced(self) -> bool:
        return self.source is not DatumSource.NONE

    @property
    def from_gnss(self) -> bool:
        """Placed on GNSS positions (with or without attitudes)."""
        return self.source in (DatumSource.GNSS, DatumSource.GNSS_ATTITUDE)

    @property
    def from_attitude(self) -> bool:
        """The rotation about the GNSS line comes from the camera attitudes."""
        return self.source is DatumSource.GNSS_ATTITUDE

    def __str__(self) -> str:
        if self.source is DatumSource.GNSS:
            return f"GNSS of {self.n_gnss} images"
        if self.source is DatumSource.GNSS_ATTITUDE:
            return f"GNSS of {self.n_gnss} images + attitude of {self.n_attitude}"
        if self.source is DatumSource.GCPS:
            return f"{self.n_gcps} GCPs"
        return "none"


def similarity_start(rec, images, ctrl: ControlInputs, *, attitude_line: bool = False):
    """Similarity model -> CRS from GNSS centres or GCPs.

    GNSS positions on one straight line (:func:`_collinear`) with camera attitudes (``ctrl.attitude``) give the
    rotation about the line from the attitudes; ``attitude_line`` does so for positions that are not collinear by
    that test but whose adjustment left the block's rotation undetermined (the survey's rotation-σ gate).

    Returns
    -------
    (Similarity or None, Datum, notes: list of str)
    """
    from ..geometry import umeyama

    notes = []
    images = np.asarray(images)
    C = rec.centers()[images]
    g = ctrl.gnss_xyz[images]
    have = np.all(np.isfinite(g), axis=1)
    sig = np.median(ctrl.gnss_sigma[images][have], axis=0) if have.any() else None
    line = have.sum() >= 3 and _collinear(g[have], sig)
    if (line or (attitude_line and have.sum() >= 3)) and len(ctrl.gcp_ids) < 3 and np.ptp(g[have], axis=0).max() > 0:
        lead = ("GNSS positions on one straight line" if line else
                "GNSS positions nearly on one line (they did not fix the block's rotation)")
        S2, why = _roll_from_attitude(rec, images[have], g[have], umeyama(C[have], g[have]), ctrl, lead)
        notes += [why] if why else []
        if S2 is not None:
            return S2, Datum(DatumSource.GNSS_ATTITUDE, int(have.sum()), len(attitude_images(ctrl, images))), notes
    if have.sum() >= 3 and not line:
        S = umeyama(C[have], g[have])
        # robust: drop GNSS positions far from the fit (another flight, a wrong tag) and refit once
        r = np.linalg.norm(S(C[have]) - g[have], axis=1)
        med = np.median(r)
        keep = r <= max(5 * med, 3 * float(np.median(ctrl.gnss_sigma[images][have])) + 1e-3, 0.5)
        if keep.sum() >= 3 and (~keep).any():
            S = umeyama(C[have][keep], g[have][keep])
            notes.append(f"{int((~keep).sum())} GNSS position(s) far from the block's fit left out of the start")
        return S, Datum(DatumSource.GNSS, int(have.sum())), notes
    if have.sum() >= 3:
        notes.append("GNSS positions are nearly collinear (one straight line within their σ): the roll about the line is "
                     "taken from GCPs if any" + ("" if len(attitude_images(ctrl, images)) else
                                                 " (the files carry no camera attitude: DJI gimbal angles would fix it)"))
    # GCPs triangulated in the model frame
    if len(ctrl.gcp_ids) >= 3:
        from .reconstruction import triangulate_tracks

        Xm, Xw = [], []
        for g_i in range(len(ctrl.gcp_ids)):
            obs = [(i, xy) for (i, gi, xy, s) in ctrl.gcp_obs if gi == g_i and rec.registered[i] and i in set(images.tolist())]
            if len(obs) < 2:
                continue
            ii = np.array([o[0] for o in obs])
            rays = np.concatenate([rec.cameras[rec.image_camera[i]].unproject(np.atleast_2d(xy))[:, :2] for i, xy in obs])
            X, ang = triangulate_tracks(np.array([0]), np.zeros(len(ii), int), rec.R[ii], rec.t[ii], rays)
            if np.isfinite(X).all():
                Xm.append(X[0])
                Xw.append(ctrl.gcp_xyz[g_i])
        if len(Xm) >= 3 and not _collinear(np.array(Xw)):
            return umeyama(np.array(Xm), np.array(Xw)), Datum(DatumSource.GCPS, n_gcps=len(Xm)), notes
    why = ("no GNSS" if have.sum() == 0 else f"GNSS of {int(have.sum())} image(s) that does not fix the rotation (fewer than 3, "
           "or on one straight line without camera attitudes in the files)")
    return None, Datum(DatumSource.NONE), notes + [f"{why} and fewer than 3 usable GCPs: the block stays in a local frame of arbitrary scale"]


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


def gnss_offset(centers_m, center_std_m, gnss_xyz, gnss_sigma) -> GnssOffset | None:
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

    Parameters
    ----------
    centers_m, center_std_m, gnss_xyz, gnss_sigma : (n, 3) arrays, metres; NaN rows are skipped

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
    g_sig = np.median(GS[ok], axis=0) if np.isfinite(GS[ok]).all() else np.full(3, np.inf)
    significant = (np.abs(med) > 5 * std) & (np.abs(med) > 3 * g_sig)
    return GnssOffset(med, std, int(ok.sum()), significant)


def apply_similarity(rec, images, S) -> None:
    """Transform the poses of ``images`` and the points they observe by ``S`` in place.

    Only the block's points move: another block's points stay in the frame of that block's poses. (Moving every
    point with each block's similarity left the second and later blocks of a survey with their points in another
    frame than their cameras: their final adjustments diverged; a 40-station building ring, seed 2, lost a right
    13-image block so.)
    """
    images = np.asarray(images)
    C = rec.centers()[images]
    Cn = S(C)
    Rn = rec.R[images] @ S.R.T
    rec.R[images] = Rn
    rec.t[images] = -np.einsum("nij,nj->ni", Rn, Cn)
    tr = rec.tracks
    mine = np.zeros(len(rec.points), bool)
    mine[tr.track[rec.obs_valid & np.isin(tr.image, images)]] = True
    ok = mine & np.isfinite(rec.points).all(1)
    rec.points[ok] = S(rec.points[ok])


@dataclass
class FinalAdjustment:
    """Outcome of :func:`final_adjustment` (the engine's result plus the bookkeeping of the survey)."""

    result: object  # AdjustmentResult of the last solve
    images: np.ndarray
    view_of_image: dict
    tie_residuals: np.ndarray  # (K, 2) px of the used tie observations
    tie_obs_image: np.ndarray  # (K,) image index
    gcp_residuals_m: np.ndarray  # (G, 3) adjusted - given, NaN for unused GCPs
    gcp_used: np.ndarray  # (G,) bool
    gcp_rejected: list  # (image index, gcp id, residual px)
    gnss_residuals_m: np.ndarray  # (n_images_with_gnss, 3)
    covariance: np.ndarray | None
    param_names: list
    center_std: np.ndarray  # (n, 3) m, NaN where unknown
    rotation_std_deg: np.ndarray  # (n, 3)
    notes: list
    manual_ties: list = field(default_factory=list)  # dicts: id index, xyz, n_images, residuals px
    gnss_rejected: list = field(default_factory=list)  # image indices whose GNSS prior was left out (blunders)
    gnss_images: list = field(default_factory=list)  # image indices with a GNSS prior (used or rejected)


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
        if _collinear(Gh[s]) or _collinear(Ch[s]):
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


#: Huber's k (in σ of the tie points) of the robust final adjustment (95 % efficiency under Gaussian errors)
HUBER_K = 1.345


def _gnss_conflicts(rec, images, ctrl) -> list:
    """Images whose adjusted antenna position is more than :data:`GNSS_REJECT_SIGMA` σ from their GNSS."""
    return sorted(i for i, (d, z) in gnss_misfit(rec, images, ctrl).items() if np.max(z) > GNSS_REJECT_SIGMA)


def _apply_solution(rec, p, cam_block, view, pts, pidx, rig) -> None:
    """Copy a solved problem's cameras, poses, points (and rig) into ``rec``."""
    for c, b in cam_block.items():
        rec.cameras[c] = p.cameras[b]
    for i, v in view.items():
        rec.R[i], rec.t[i] = p.view_transform(v)
    rec.points[pts] = p.points[pidx]
    if rig is not None:
        rig.R, rig.t = p.rig_R[0].copy(), p.rig_t[0].copy()


def _state(rec, rig) -> tuple:
    """What an adjustment changes in ``rec`` (and the rig), to go back to it with :func:`_set_state`."""
    return (rec.R.copy(), rec.t.copy(), rec.points.copy(), rec.obs_valid.copy(), list(rec.cameras),
            None if rig is None else (np.copy(rig.R), np.copy(rig.t)))


def _set_state(rec, rig, st) -> None:
    rec.R[:], rec.t[:], rec.points[:], rec.obs_valid[:] = st[0], st[1], st[2], st[3]
    rec.cameras[:] = st[4]
    if st[5] is not None:
        rig.R, rig.t = np.copy(st[5][0]), np.copy(st[5][1])


def final_adjustment(rec, xy_by_image, images, ctrl: ControlInputs, *, robust_ties_on_conflict: bool = True,
                     **kw) -> FinalAdjustment:
    """Joint adjustment of the block with GNSS priors and weighted GCPs (see the module docstring).

    Least squares after a robust round (:func:`_final_adjustment`). When least squares leaves images more than
    :data:`GNSS_REJECT_SIGMA` σ from GNSS positions that passed the blunder test, tie observations with
    systematic errors that passed the blunder test (features on occluding edges — T-junctions —, repeated
    structure) outweigh those images' GNSS: the block is adjusted again from the same start with the ties under
    a robust loss to the end (Huber, k = :data:`HUBER_K` σ), and that solution is kept when it resolves the
    conflict (fewer such images, none new) without bending the block (median tie residual within 10 % of least
    squares'); otherwise the least-squares solution stays and the survey names the images. Only for a few such
    images (<= 10 % of those with GNSS): many mean a GNSS σ or datum that is wrong for the whole flight.
    Measured on the 64-station ring around the synthetic building (occluder in front of the south wall): the
    two stations facing the occluder 0.41 / 0.44 m (13 σ) from their RTK GNSS and 3.0° / 2.5° off under least
    squares; see ``tests/test_texture_survey_poses.py`` for the robust figures.
    Keyword arguments: those of :func:`_final_adjustment`.
    """
    rig = kw.get("rig")
    start = _state(rec, rig) if robust_ties_on_conflict else None
    fa = _final_adjustment(rec, xy_by_image, images, ctrl, **kw)
    if start is None or not kw.get("georeferenced", True) or len(fa.gnss_images) < 4:
        return fa
    used = [i for i in fa.gnss_images if i not in fa.gnss_rejected]
    before = _gnss_conflicts(rec, used, ctrl)
    if not before or len(before) > 0.1 * len(used):
        # none, or many: then the GNSS σ or datum is wrong for the whole flight, not a few images' tie points
        return fa
    ls = _state(rec, rig)
    _set_state(rec, rig, start)
    fa_r = _final_adjustment(rec, xy_by_image, images, ctrl, final_loss="huber", **kw)
    used_r = [i for i in fa_r.gnss_images if i not in fa_r.gnss_rejected]
    after = _gnss_conflicts(rec, used_r, ctrl)
    # the robust solution must not buy the GNSS fit by bending the block: the bulk of the tie points (median
    # residual) fits as well as under least squares (within 10 %)
    med = lambda v: float(np.nanmedian(np.linalg.norm(v, axis=1))) if len(v) else np.nan  # noqa: E731
    bulk_ok = med(fa_r.tie_residuals) <= 1.1 * med(fa.tie_residuals)
    if fa_r.result.success and bulk_ok and len(after) < len(before) and set(after) <= set(before):
        fa_r.notes.append(f"{len(before)} camera centre(s) more than {GNSS_REJECT_SIGMA:g} σ from their GNSS under least "
                          f"squares ({len(after)} after): the tie points were weighted by a robust loss (Huber, "
                          f"k = {HUBER_K:g} σ) to the end of the final adjustment")
        return fa_r
    _set_state(rec, rig, ls)
    return fa


#: when a solve of the final adjustment stops on a singular point block -- or on an undetermined camera side: one such
#: point's huge depth and tiny parallax leave the reduced camera system numerically singular (the held-out 48-station
#: building ring with ``--refine-ties lsm``: "condition 4.77e+300" on a 29-image block, rejected whole; one point
#: removed and it solves) --, the tie points whose rays meet at less than this angle (degrees) are left out and the
#: round is solved again: their depth is undetermined. The orientation creates points at >= 1.5°
#: (``min_tri_angle_deg``); points drift towards infinity in an adjustment (a block matched on noise: walk seed 4 had
#: 25 below 0.01°; the 64-station ring one at 0.0002°, which its solves carry). Only after such a stop, so that
#: blocks that solve keep every point.
MIN_FINAL_TRI_ANGLE_DEG = 0.1


def _parallel_ray_points(rec, obs) -> np.ndarray:
    """Tracks (point indices) of ``rec`` whose observations ``obs`` (bool over ``rec.tracks``) have rays that meet at
    less than :data:`MIN_FINAL_TRI_ANGLE_DEG`: twice :func:`~thermogrammetry.sfm.reconstruction.ray_spread_deg`, as
    the orientation measures a track's intersection angle."""
    from .reconstruction import ray_spread_deg

    tr = rec.tracks
    o = np.flatnonzero(obs)
    if not len(o):
        return np.zeros(0, np.int64)
    t, i = tr.track[o], tr.image[o]
    C = -np.einsum("kji,kj->ki", rec.R[i], rec.t[i])
    amax = ray_spread_deg(t, len(rec.points), C, rec.points[t])
    seen = np.zeros(len(rec.points), bool)
    seen[t] = True
    # seen from one projection centre only (an RGB image and its thermal partner through a rig of zero base): the
    # adjustment moves such a point onto the centre, where its "rays" point anywhere
    lo = np.full((len(rec.points), 3), np.inf)
    hi = np.full((len(rec.points), 3), -np.inf)
    np.minimum.at(lo, t, C)
    np.maximum.at(hi, t, C)
    one_centre = seen & (np.max(hi - lo, axis=1) <= 1e-7 * max(float(np.ptp(C, axis=0).max()), 1e-300))
    return np.flatnonzero(seen & ((2.0 * amax < MIN_FINAL_TRI_ANGLE_DEG) | one_centre))


def _final_adjustment(rec, xy_by_image, images, ctrl: ControlInputs, *, self_calibrate=(), tie_sigma_px: float = 1.0,
                      max_error_px: float = 4.0, gcp_reject_px: float = 5.0, compute_covariance: bool = True,
                      georeferenced: bool = True, max_iterations: int = 50, rig=None, manual_ties=None,
                      final_loss: str = "trivial", attitude_priors: bool = False) -> FinalAdjustment:
    """One pass of :func:`final_adjustment`: a robust round, then ``final_loss`` rounds (least squares by default).

    ``rec`` is updated in place (cameras, poses, points).

    ``self_calibrate`` is a tuple of parameter names for every camera, or a dict camera index -> names.
    ``rig`` (:class:`~thermogrammetry.sfm.rig.RigViews`): its slave images of the block are rig views of
    their masters (seed 002 eq. 4-5); the rig is fixed or estimated (``rig.R, rig.t, rig.std`` updated).
    ``manual_ties``: list of (image index, tie index, (2,) xy px, σ px) -- points measured by hand in
    several images (RGB and thermal), unknown 3D points of the adjustment (at least 2 images of the block).
    ``attitude_priors``: the images' observed attitudes (``ctrl.attitude``) enter as priors, each with σ
    :data:`~.attitude.ATTITUDE_SIGMA_DEG` · sqrt(n) (together one observation of the block's rotation): the datum of a
    block whose GNSS positions lie on one line (:func:`similarity_start`).
    """
    from ..adjustment import BundleProblem, SolverOptions, solve

    images = np.asarray(images)
    notes: list[str] = []
    tr = rec.tracks
    in_block = np.zeros(len(rec.registered), bool)
    in_block[images] = True
    gcp_active = [True] * len(ctrl.gcp_obs)
    rejected = []
    if georeferenced and ctrl.gcp_obs:
        # gross errors first: a GCP "measured" in an image where it cannot be (wrong identification) is
        # found by projecting its coordinates with the georeferenced start, before it can bend the block
        res_px = np.full(len(ctrl.gcp_obs), np.nan)
        for k, (i, gi, xy, s_) in enumerate(ctrl.gcp_obs):
            if not in_block[i]:
                continue
            Xc = rec.R[i] @ ctrl.gcp_xyz[gi] + rec.t[i]
            if Xc[2] <= 0:
                res_px[k] = np.inf
                continue
            with np.errstate(all="ignore"):
                pr = rec.cameras[rec.image_camera[i]].project(Xc[None, :])[0]
            res_px[k] = float(np.linalg.norm(pr - np.asarray(xy, float))) if np.all(np.isfinite(pr)) else np.inf
        fin = res_px[np.isfinite(res_px)]
        if len(fin):
            gate = max(gcp_reject_px * 5.0, 5.0 * float(np.median(fin)))
            for k in np.nonzero(res_px > gate)[0]:
                i, gi = ctrl.gcp_obs[k][0], ctrl.gcp_obs[k][1]
                gcp_active[k] = False
                rejected.append((int(i), ctrl.gcp_ids[gi], float(res_px[k])))
    res = None
    gnss_active = np.ones(len(rec.registered), bool)
    gnss_rejected: list[int] = []
    gnss_screened = False
    start = _state(rec, rig)
    drop_parallel = False  # set when a solve stops on a singular point block: such points are left out, once
    for round_ in range(5):
        # the previous round's result (its problem, residuals) is released before the next problem is built
        res = p = v_img = pb = None
        release_free_heap()
        obs = rec.obs_valid & in_block[tr.image] & np.isfinite(rec.points[tr.track]).all(1)
        cnt = np.bincount(tr.track[obs], minlength=len(rec.points))
        obs &= cnt[tr.track] >= 2
        weak = _parallel_ray_points(rec, obs) if drop_parallel else ()
        if len(weak):
            # points whose rays have become (nearly) parallel carry no depth and made the adjustment singular
            rec.obs_valid[np.isin(tr.track, weak) & obs] = False
            obs &= ~np.isin(tr.track, weak)
            notes.append(f"{len(weak)} tie point(s) with rays within {MIN_FINAL_TRI_ANGLE_DEG:g}° of parallel left out "
                          f"(round {round_ + 1})")
        pts = np.unique(tr.track[obs])
        have_gnss = np.all(np.isfinite(ctrl.gnss_xyz[images]), axis=1)
        use_gcp = [k for k, (i, gi, xy, s) in enumerate(ctrl.gcp_obs) if in_block[i] and gcp_active[k]]
        gcps_in = sorted({ctrl.gcp_obs[k][1] for k in use_gcp})
        control = georeferenced and (have_gnss.sum() >= 3 or len(gcps_in) >= 3)
        pb = BundleProblem(gauge="control" if control else "inner")
        cam_block = {}
        for c in np.unique(rec.image_camera[images]):
            cam = rec.cameras[c]
            sc = self_calibrate.get(int(c), ()) if isinstance(self_calibrate, dict) else self_calibrate
            free = {n.lower() for n in sc}
            fixed = [n for n in cam.param_names if n.lower() not in free]
            cam_block[int(c)] = pb.add_camera(cam, fixed=fixed if fixed else False, name=f"camera{c}")
        slaves = {} if rig is None else {int(s): int(m) for s, m in rig.master.items() if in_block[s] and in_block[m]}
        view = {int(i): pb.add_pose((rec.R[i], rec.t[i]), name=f"image{i}") for i in images if int(i) not in slaves}
        if slaves:
            rig_block = pb.add_rig((rig.R, rig.t), fixed=rig.fixed)
            for s_, m_ in slaves.items():
                view[s_] = pb.add_rig_view(rig_block, view[m_])
        pidx = pb.add_points(rec.points[pts]) if len(pts) else np.zeros(0, np.int64)
        pmap = np.full(len(rec.points), -1, np.int64)
        pmap[pts] = pidx
        order = np.nonzero(obs)[0]
        tie_rows = []  # (image index, its observation indices) in the order they enter the problem
        for i in images:
            o = order[tr.image[order] == i]
            if len(o) == 0:
                continue
            pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], pmap[tr.track[o]],
                                xy_by_image[i][tr.feature[o]], sigma_px=tie_sigma_px)
            tie_rows.append((int(i), o))
        n_tie = int(sum(len(o) for _, o in tie_rows))
        # GCPs: weighted control points with their image measurements
        gcp_point = {}
        if gcps_in:
            gp = pb.add_points(ctrl.gcp_xyz[gcps_in])
            gcp_point = dict(zip(gcps_in, gp.tolist()))
            pb.add_control(gp, ctrl.gcp_xyz[gcps_in], ctrl.gcp_sigma[gcps_in])
            for k in use_gcp:
                i, gi, xy, s = ctrl.gcp_obs[k]
                pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], np.array([gcp_point[gi]]),
                                    np.atleast_2d(xy), sigma_px=s)
        tie_pts = _add_manual_ties(pb, rec, manual_ties, in_block, view, cam_block) if manual_ties else {}
        have_gnss = have_gnss & ~np.isin(images, list(slaves)) & gnss_active[images]  # plain pose views only
        gnss_views = [view[int(i)] for i, h in zip(images, have_gnss) if h]
        if georeferenced and gnss_views:
            sel = images[have_gnss]
            pb.add_gnss(np.array(gnss_views), ctrl.gnss_xyz[sel], ctrl.gnss_sigma[sel], ctrl.lever_arm_m)
        att = [int(i) for i in attitude_images(ctrl, images) if int(i) not in slaves] if attitude_priors else []
        if georeferenced and att:
            from .attitude import ATTITUDE_SIGMA_DEG

            pb.add_attitude(np.array([view[i] for i in att]), ctrl.attitude[att],
                            np.radians(ATTITUDE_SIGMA_DEG) * np.sqrt(len(att)))
        robust = round_ == 0 or (round_ == 1 and bool(gnss_rejected))
        opt = SolverOptions(loss="huber" if robust else final_loss, loss_scale=2.0 if robust else HUBER_K,
                            max_iterations=max_iterations,
                            compute_covariance=(not robust) and compute_covariance, compute_redundancy=False,
                            function_tolerance=1e-8 if not robust else 1e-3)
        res = solve(pb, opt)
        if (not res.success and not drop_parallel and round_ < 4
                and any(w in str(res.reason) for w in ("point's normal block is singular", "undetermined",
                                                       # a singular point block seen only by the precision step: a
                                                       # point observed from one centre (rig of zero base)
                                                       "precision step failed"))):
            notes.append(f"final adjustment (round {round_ + 1}) stopped: {res.reason}; solved again without the points "
                         f"whose rays meet at less than {MIN_FINAL_TRI_ANGLE_DEG:g}°")
            drop_parallel = True
            continue
        if not res.success:
            notes.append(f"final adjustment (round {round_ + 1}) stopped: {res.reason}")
            if res.problem is None:
                break
        p = res.problem
        _apply_solution(rec, p, cam_block, view, pts, pidx, rig if slaves else None)
        v_img = res.image_residuals
        changed = False
        if robust and not gnss_screened:
            gnss_screened = True
            # GNSS blunders (a wrong tag, another flight's position): few positions far from the robust solution are
            # left out, never many (then the GNSS σ is wrong, which the survey reports instead); the robust round is
            # then repeated from the start without them, so that they bend neither the block nor its tie rejection
            if georeferenced and len(gnss_views) >= 4:
                mis = gnss_misfit(rec, sel, ctrl)
                far = [i for i, (d, z) in mis.items() if np.max(z) > GNSS_REJECT_SIGMA]
                if far and len(far) <= 0.1 * len(mis) and len(mis) - len(far) >= 3:
                    gnss_active[far] = False
                    gnss_rejected += far
                    notes.append(f"{len(far)} GNSS position(s) more than {GNSS_REJECT_SIGMA:g} σ from the robust "
                                 "solution left out of the final adjustment (see gnss_flagged)")
                    _set_state(rec, rig, start)
                    continue
        if robust:
            # tie blunders
            tie_v = v_img[:n_tie]
            big = np.linalg.norm(tie_v, axis=1) > max_error_px
            # variance component of the tie points (Helmert, one step): their a-priori σ is replaced by
            # the estimate from their residuals and redundancy, so that GNSS and GCP weights stay in
            # proportion and σ0 of the final solve tests the whole model
            good = ~big
            n_obs = 2 * int(good.sum())
            n_unk = 3 * len(pts) + 6 * len(pb.pose_R) + int(sum((~np.asarray(f)).sum() for f in pb.camera_fixed))
            if n_obs > n_unk + 10:
                sig_hat = float(np.sqrt(np.sum(tie_v[good] ** 2) / (n_obs - n_unk)))
                notes.append(f"tie-point σ estimated from the residuals: {sig_hat:.3f} px (a priori {tie_sigma_px:g} px)")
                tie_sigma_px = float(np.clip(sig_hat, 0.02, 10.0))
            if big.any():
                rec.obs_valid[order[big]] = False
                changed = True
            # GCP measurements: the worst one per GCP above the threshold is rejected
            gv = v_img[n_tie:]
            worst = {}
            for r, k in enumerate(use_gcp):
                i, gi, xy, s = ctrl.gcp_obs[k]
                e = float(np.linalg.norm(gv[r]))
                if e > max(gcp_reject_px, 5.0 * float(np.max(s))) and (gi not in worst or e > worst[gi][1]):
                    worst[gi] = (k, e)
            for gi, (k, e) in worst.items():
                gcp_active[k] = False
                rejected.append((int(ctrl.gcp_obs[k][0]), ctrl.gcp_ids[gi], e))
                changed = True
            continue  # always a second, non-robust solve
        if not changed:
            break
    # bookkeeping of the last solve
    p = res.problem
    gcp_res = np.full((len(ctrl.gcp_ids), 3), np.nan)
    for gi, pi in gcp_point.items():
        gcp_res[gi] = p.points[pi] - ctrl.gcp_xyz[gi]
    used = np.zeros(len(ctrl.gcp_ids), bool)
    used[list(gcp_point)] = True
    n = len(rec.registered)
    cstd = np.full((n, 3), np.nan)
    rstd = np.full((n, 3), np.nan)
    if res.pose_std is not None:
        for i, v in view.items():
            if p.view_rig[v] >= 0:  # rig views: propagated below from the master pose and the rig
                continue
            pi = p.view_pose[v]
            cstd[i] = res.pose_std[pi, 3:]
            rstd[i] = np.degrees(res.pose_std[pi, :3])
    tie_obs_image = np.concatenate([np.full(len(o), i) for i, o in tie_rows]) if tie_rows else np.zeros(0, int)
    if res.image_residuals is not None:
        tie_v = res.image_residuals[:n_tie]
    else:  # the solve stopped without residuals: they are recomputed from the last state, not dropped
        tie_v = np.full((n_tie, 2), np.nan)
        k0 = 0
        for i, o in tie_rows:
            Xc = rec.points[tr.track[o]] @ rec.R[i].T + rec.t[i]
            with np.errstate(all="ignore"):
                tie_v[k0:k0 + len(o)] = rec.cameras[rec.image_camera[i]].project(Xc) - xy_by_image[i][tr.feature[o]]
            k0 += len(o)
    fa = FinalAdjustment(res, images, view, tie_v, tie_obs_image, gcp_res, used, rejected,
                         res.gnss_residuals if res.gnss_residuals is not None else np.zeros((0, 3)),
                         res.covariance, list(res.param_names or []), cstd, rstd, notes, gnss_rejected=gnss_rejected,
                         gnss_images=[int(i) for i in images[have_gnss | np.isin(images, gnss_rejected)]] if georeferenced else [])
    if tie_pts:
        fa.manual_ties = _manual_tie_results(res, p, tie_pts, n_tie + sum(1 for k in use_gcp), manual_ties, in_block)
    if slaves:
        from .rig import slave_std

        names_ = list(res.param_names or [])
        if res.std is not None and "rig0.wx" in names_ and not rig.fixed:
            k0 = names_.index("rig0.wx")
            rig.std = np.asarray(res.std[k0:k0 + 6], float)
            if res.covariance is not None:
                rig.covariance = np.asarray(res.covariance[k0:k0 + 6, k0:k0 + 6], float)
        for s_ in slaves:
            cstd[s_], rstd[s_] = slave_std(rig, rec, fa, s_)
    return fa


def _add_manual_ties(pb, rec, manual_ties, in_block, view, cam_block) -> dict:
    """Manual tie points (measured by hand in RGB and thermal images) as unknown points of ``pb``.

    Returns tie index -> (problem point index, list of manual_ties rows used); ties seen in fewer than 2
    images of the block, from one projection centre only, or whose rays do not intersect in front of the
    cameras, are left out.
    """
    from .reconstruction import triangulate_tracks

    by_id: dict[int, list] = {}
    for r, (i, ti, xy, s) in enumerate(manual_ties):
        if in_block[i] and int(i) in view:
            by_id.setdefault(int(ti), []).append(r)
    out = {}
    for ti, rows in sorted(by_id.items()):
        if len({manual_ties[r][0] for r in rows}) < 2:
            continue
        ii = np.array([manual_ties[r][0] for r in rows])
        xy = np.array([np.asarray(manual_ties[r][2], float) for r in rows])
        Rs = np.array([pb.view_transform(view[int(i)])[0] for i in ii])
        ts = np.array([pb.view_transform(view[int(i)])[1] for i in ii])
        rays = np.concatenate([rec.cameras[rec.image_camera[i]].unproject(xy[k:k + 1])[:, :2] for k, i in enumerate(ii)])
        X, _ = triangulate_tracks(np.array([0]), np.zeros(len(ii), int), Rs, ts, rays)
        X = X[0]
        if not np.isfinite(X).all() or np.any(np.einsum("kij,j->ki", Rs, X)[:, 2] + ts[:, 2] <= 0):
            continue
        # seen from one projection centre only (an RGB image and its thermal partner through a rig of zero base):
        # no intersection, a singular point block
        C = -np.einsum("kji,kj->ki", Rs, ts)
        if np.ptp(C, axis=0).max() <= 1e-6 * float(np.linalg.norm(X - C[0])):
            continue
        pi = int(pb.add_points(X[None, :])[0])
        for r, i in zip(rows, ii):
            pb.add_image_points(cam_block[int(rec.image_camera[i])], view[int(i)], np.array([pi]),
                                np.atleast_2d(xy[rows.index(r)]), sigma_px=manual_ties[r][3])
        out[ti] = (pi, rows)
    return out


def _manual_tie_results(res, p, tie_pts, offset, manual_ties, in_block) -> list:
    """Per manual tie point: adjusted coordinates, images and residuals (px), in the order they entered."""
    out = []
    k = offset
    v = res.image_residuals
    for ti, (pi, rows) in sorted(tie_pts.items()):
        r = v[k:k + len(rows)] if v is not None else np.full((len(rows), 2), np.nan)
        k += len(rows)
        out.append({"tie": ti, "xyz": p.points[pi].copy(), "images": [int(manual_ties[q][0]) for q in rows],
                    "residuals_px": np.asarray(r, float)})
    return out


def _project(cam, R, t, X):
    return cam.project((R @ X + t)[None, :])[0]


def intersect_check_points(rec, fa: FinalAdjustment, ctrl: ControlInputs, *, eps: float = 1e-6):
    """Intersect each check point from its measurements in the adjusted block (never adjusted with it).

    Returns
    -------
    list of dict: ``id``, ``xyz`` (3,), ``std`` (3,) m (measurement + pose/camera covariance), ``error`` (3,)
    (estimate - given), ``n_images``; check points seen in fewer than 2 oriented images are listed with
    ``xyz`` None and a ``reason``.
    """
    from .reconstruction import triangulate_tracks

    out = []
    block = set(fa.images.tolist())
    names = fa.param_names
    index = {nm: k for k, nm in enumerate(names)}
    for ci, cid in enumerate(ctrl.check_ids):
        obs = [(i, np.asarray(xy, float), float(np.max(s))) for (i, gi, xy, s) in ctrl.check_obs if gi == ci and i in block]
        if len(obs) < 2:
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs),
                        "reason": f"measured in {len(obs)} oriented image(s); 2 needed"})
            continue
        ii = np.array([o[0] for o in obs])
        xy = np.array([o[1] for o in obs])
        sig = np.array([o[2] for o in obs])
        rays = np.concatenate([rec.cameras[rec.image_camera[i]].unproject(xy[k:k + 1])[:, :2] for k, i in enumerate(ii)])
        X, _ = triangulate_tracks(np.array([0]), np.zeros(len(ii), int), rec.R[ii], rec.t[ii], rays)
        X = X[0]
        if not np.isfinite(X).all():
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs), "reason": "rays do not intersect"})
            continue
        w = np.repeat(1.0 / sig**2, 2)

        def f(X, Rs, ts, cams):
            return np.concatenate([_project(cams[k], Rs[k], ts[k], X) for k in range(len(ii))])

        # work about a local origin: CRS coordinates (1e6 m) would eat the finite-difference steps
        origin = X.copy()
        Rs = [rec.R[i].copy() for i in ii]
        ts = [rec.t[i] + rec.R[i] @ origin for i in ii]
        cams = [rec.cameras[rec.image_camera[i]] for i in ii]
        X = np.zeros(3)
        for _ in range(10):  # Gauss-Newton on X
            r = xy.ravel() - f(X, Rs, ts, cams)
            J = np.empty((2 * len(ii), 3))
            h = 1e-4
            for a in range(3):
                d = np.zeros(3)
                d[a] = h
                J[:, a] = (f(X + d, Rs, ts, cams) - f(X - d, Rs, ts, cams)) / (2 * h)
            N = J.T @ (w[:, None] * J)
            if not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e12:
                break
            dx = np.linalg.solve(N, J.T @ (w * r))
            X = X + dx
            if np.linalg.norm(dx) < 1e-9 * max(1.0, np.linalg.norm(X)):
                break
        if not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e12:
            out.append({"id": cid, "xyz": None, "std": None, "error": None, "n_images": len(obs),
                        "reason": "intersection undetermined (rays nearly parallel or projections invalid)"})
            continue
        Ninv = np.linalg.inv(N)
        cov = Ninv.copy()
        # propagation of the a-posteriori covariance of the camera-side parameters involved
        if fa.covariance is not None:
            cols, Jt = [], []
            for k, i in enumerate(ii):
                C = -Rs[k].T @ ts[k]
                base = f"image{i}"
                for a, nm in enumerate(("wx", "wy", "wz", "X0", "Y0", "Z0")):
                    key = f"{base}.{nm}"
                    if key not in index:
                        continue
                    col = np.zeros(2 * len(ii))
                    h = 1e-7 if a < 3 else 1e-4
                    vals = []
                    for sgn in (1, -1):
                        Rk, Ck = Rs[k], C.copy()
                        if a < 3:
                            dw = np.zeros(3)
                            dw[a] = sgn * h
                            Rk = matrix_from_axis_angle(dw) @ Rs[k]
                        else:
                            Ck[a - 3] += sgn * h
                        vals.append(_project(cams[k], Rk, -Rk @ Ck, X))
                    col[2 * k:2 * k + 2] = (vals[0] - vals[1]) / (2 * h)
                    cols.append(index[key])
                    Jt.append(col)
            for c in sorted({int(rec.image_camera[i]) for i in ii}):
                cam = rec.cameras[c]
                for pn in cam.param_names:
                    key = f"camera{c}.{pn}"
                    if key not in index:
                        continue
                    h = 1e-6 * max(1.0, abs(cam[pn]))
                    col = np.zeros(2 * len(ii))
                    for k, i in enumerate(ii):
                        if rec.image_camera[i] != c:
                            continue
                        cp = cam.replace(**{pn: cam[pn] + h})
                        cm = cam.replace(**{pn: cam[pn] - h})
                        col[2 * k:2 * k + 2] = (_project(cp, Rs[k], ts[k], X) - _project(cm, Rs[k], ts[k], X)) / (2 * h)
                    cols.append(index[key])
                    Jt.append(col)
            if cols:
                Jt = np.array(Jt).T  # (2k, p): d(projection)/d(theta)
                G = Ninv @ J.T @ (w[:, None] * Jt)  # dX/d(observation shift) applied to -J_theta
                S = fa.covariance[np.ix_(cols, cols)]
                cov = cov + G @ S @ G.T
        std = np.sqrt(np.diag(cov))
        X = X + origin
        out.append({"id": cid, "xyz": X, "std": std, "cov": cov, "error": X - ctrl.check_xyz[ci], "n_images": len(obs), "reason": ""})
    return out


def axis_statistics(errors) -> dict:
    """Seed 003 Table 3 layout: n, min, max, MAE, RMSE per axis (metres); nulls when n = 0."""
    E = np.asarray([e for e in errors if e is not None and np.all(np.isfinite(e))], float).reshape(-1, 3)
    d = {"n": int(len(E))}
    for k, ax in enumerate("xyz"):
        if len(E):
            v = E[:, k]
            d.update({f"rmse_{ax}": float(np.sqrt(np.mean(v**2))), f"mae_{ax}": float(np.mean(np.abs(v))),
                      f"min_{ax}": float(v.min()), f"max_{ax}": float(v.max())})
        else:
            d.update({f"rmse_{ax}": None, f"mae_{ax}": None, f"min_{ax}": None, f"max_{ax}": None})
    return d
