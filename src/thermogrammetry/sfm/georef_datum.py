"""The start of georeferencing: a similarity from the model to the CRS, on GNSS centres, attitudes or GCPs.

A similarity (Umeyama 1991) from the model's projection centres to the GNSS positions (>= 3 images, not
collinear: :func:`collinear`), robust to a few far positions; GNSS positions on one straight line take
the rotation about the line from the cameras' attitudes (:func:`attitude_images`); else the triangulated
GCPs to their coordinates (>= 3 GCPs) (:func:`similarity_start`). :func:`apply_similarity` moves a
block's poses and points by it.

References
----------
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point patterns.
IEEE PAMI 13(4), 376-380.
Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
thermal imagery (GCPs for absolute orientation).
"""

from __future__ import annotations

import numpy as np

from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle
from .georef_control import ControlInputs, Datum, DatumSource

__all__ = ["MIN_ATTITUDE_IMAGES", "ATTITUDE_MAX_DISAGREEMENT_DEG", "attitude_images", "COLLINEAR_SIGMA", "collinear", "similarity_start", "apply_similarity"]


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
#: are taken as one straight line (:func:`collinear`): their spread across it is noise, which cannot fix the
#: rotation about the line
COLLINEAR_SIGMA = 1.5


def collinear(P: np.ndarray, sigma_xyz=None) -> bool:
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


def similarity_start(rec, images, ctrl: ControlInputs, *, attitude_line: bool = False):
    """Similarity model -> CRS from GNSS centres or GCPs.

    GNSS positions on one straight line (:func:`collinear`) with camera attitudes (``ctrl.attitude``) give the
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
    line = have.sum() >= 3 and collinear(g[have], sig)
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
        if len(Xm) >= 3 and not collinear(np.array(Xw)):
            return umeyama(np.array(Xm), np.array(Xw)), Datum(DatumSource.GCPS, n_gcps=len(Xm)), notes
    why = ("no GNSS" if have.sum() == 0 else f"GNSS of {int(have.sum())} image(s) that does not fix the rotation (fewer than 3, "
           "or on one straight line without camera attitudes in the files)")
    return None, Datum(DatumSource.NONE), notes + [f"{why} and fewer than 3 usable GCPs: the block stays in a local frame of arbitrary scale"]


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
