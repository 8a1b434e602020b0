"""RGB + thermal rigs in a survey block (Barazzetti et al. 2013, §2.3, eq. 3-5).

A *rig* is an RGB camera and a thermal camera in one housing (or on one bar) that expose together. Its
relative orientation is constant: with our ``cam_from_world`` poses,

    R_IR = R_rel R_RGB,    t_IR = R_rel t_RGB + t_rel,          (``cam_thermal_from_cam_rgb`` = (R_rel, t_rel))

which is seed 002's eq. 4 ``R* = R_RGB^T R_IR`` with world_from_camera rotations (``R* = R_rel^T``) and eq. 5
``X0_IR = R_RGB t + X0_RGB`` with the base vector ``b = -R_rel^T t_rel`` (the thermal projection centre in the
RGB camera frame, metres). See :mod:`thermogrammetry.adjustment.problem` for the derivation.

In a survey the RGB images are oriented from their tie points (features work well on RGB); each thermal
image paired with an oriented RGB image becomes a *rig view* of it (``BundleProblem.add_rig_view``): its
pose is not a parameter of its own, yet its tie observations (thermal-thermal and thermal-RGB) and manual
measurements enter the final adjustment through the rig. ``R_rel, t_rel`` is either given and held fixed,
or estimated in the block (started from the given value or from thermal images oriented together with
their partners) with its a-posteriori σ.

Evidence (what counts as oriented). A rig view whose image contributes fewer than
``RIG_MIN_OWN_OBSERVATIONS`` observations of its own (tie points kept by the final adjustment plus manual
measurements) is *rig-only*: its pose is nothing but its partner's pose moved by R*, t. It counts as
oriented when R*, t is calibrated -- given in the rig file, or estimated in this block from enough
evidence -- and is listed apart (``survey.json`` ``images_rig_only``, ``rig.rig_only``, a status reason).
R*, t is estimated in a block only with :func:`rig_estimation_evidence`: at least ``RIG_EST_MIN_FRAMES``
thermal frames with ``RIG_EST_MIN_OBSERVATIONS`` observations each whose partners span at least
``RIG_EST_MIN_SPREAD`` of the block, and after the adjustment a converged solve with finite σ of all six
rig parameters; otherwise the estimate is refused with the reason and the thermal frames without an
orientation of their own stay unoriented (a guessed R*, t is not an orientation). Where fewer than
``RIG_EST_MIN_FRAMES`` thermal frames tie to their partners at all (low-texture thermal frames), the survey first
tries :mod:`thermogrammetry.sfm.rigreg`: R*, t from registering the edges both bands see over all pairs, accepted
with its own evidence (>= 3 agreeing pairs, per-pair rotations within 0.5°) and then held fixed
(``RigFile.registered``).

The rig file (one schema, shared with the ``texture`` verb)::

    {"format": "thermogrammetry/rig",
     "cam_thermal_from_cam_rgb": {"R": [[3x3]], "t": [tx, ty, tz]},   # metres; optional when estimate is true
     "estimate": false,                 # true: R, t estimated in the block (the values above are the start)
     "thermal_camera": {camera JSON},   # optional in survey (held fixed like --camera); required by texture
     "rgb_camera": {camera JSON},       # optional: the RGB camera of the rig calibration, held fixed
     "frames": {"<RGB image>": "<thermal file>", ...},   # explicit pairs (names with or without extension)
     "pairing": {"rgb_suffix": "-visible", "thermal_suffix": "-radiometric"},   # pairs by common stem
     "notes": "free text"}

Without ``frames`` and ``pairing``, an RGB and a thermal image pair when their file stems are identical.

References
----------
Barazzetti, L., Brumana, R., Oreni, D., Previtali, M., Roncoroni, F. (2013). Mosaicking thermal images of
buildings. Proc. SPIE 8783 (seed 002, §2.3 eq. 3-5).
Markley, F. L. et al. (2007). Averaging quaternions. J. Guidance, Control, and Dynamics 30(4) (chordal mean).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataFileError, UnsupportedFormatError
from ..geometry.rotations import axis_angle_from_matrix, matrix_from_axis_angle, mean_rotation

__all__ = ["RigFile", "RigViews", "read_rig", "parse_rig", "pair_rig_images", "relative_from_poses",
           "attach_rig_images", "rig_report", "RIG_KEYS", "own_observations", "rig_estimation_evidence",
           "rig_estimate_accepted", "RIG_MIN_OWN_OBSERVATIONS", "RIG_EST_MIN_FRAMES", "RIG_EST_MIN_OBSERVATIONS",
           "RIG_EST_MIN_SPREAD"]

RIG_FORMAT = "thermogrammetry/rig"
#: below this many own observations a rig view is "rig-only" (3 points: the minimum of a resection)
RIG_MIN_OWN_OBSERVATIONS = 6
#: estimating R*, t needs this many thermal frames ...
RIG_EST_MIN_FRAMES = 3
#: ... each with this many own observations (tie + manual) ...
RIG_EST_MIN_OBSERVATIONS = 20
#: ... whose RGB partners span this fraction of the block's largest camera-centre distance
RIG_EST_MIN_SPREAD = 1.0 / 3.0
RIG_KEYS = ("format", "cam_thermal_from_cam_rgb", "estimate", "thermal_camera", "rgb_camera", "frames", "pairing", "notes")


@dataclass
class RigFile:
    """A validated rig file.

    Attributes
    ----------
    R, t : (3, 3), (3,) or None
        ``cam_thermal_from_cam_rgb`` (t in metres); None when only ``estimate`` is asked.
    estimate : bool
        True: estimated in the block (R, t are the start when given); False: held fixed.
    thermal_camera, rgb_camera : Camera or None
        Held fixed in the survey when given (from the rig's calibration).
    frames : dict RGB name -> thermal file (as written)
    rgb_suffix, thermal_suffix : str
        Stem suffixes removed before pairing by name.
    source : str
        File name for messages.
    """

    R: np.ndarray | None
    t: np.ndarray | None
    estimate: bool = False
    thermal_camera: object = None
    frames: dict = field(default_factory=dict)
    rgb_suffix: str = ""
    thermal_suffix: str = ""
    notes: str = ""
    source: str = "rig.json"
    rgb_camera: object = None
    #: set when R, t come from :func:`thermogrammetry.sfm.rigreg.register_rig` (its summary): t is then in the
    #: model units of the orientation (scaled to the CRS with the block's similarity) and R, t are held fixed
    registered: dict | None = None

    @property
    def relative(self):
        """``cam_thermal_from_cam_rgb`` as a :class:`~thermogrammetry.geometry.Pose` (None when not given)."""
        from ..geometry import Pose

        return None if self.R is None else Pose(self.R, self.t)


def read_rig(path) -> RigFile:
    """Read and validate a rig file (see the module docstring); errors name the file and the key."""
    p = Path(path)
    if not p.is_file():
        raise DataFileError(f"{p}: rig file not found")
    try:
        d = json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UnsupportedFormatError(f"{p}: not a JSON rig file ({exc})") from None
    return parse_rig(d, source=str(p))


def parse_rig(d, *, source: str = "rig.json", require_relative: bool = False, require_camera: bool = False,
              require_frames: bool = False) -> RigFile:
    """Validate a rig dict; ``require_*`` for the verbs that need those parts (texture needs all three)."""
    from ..camera import Camera

    if not isinstance(d, dict) or d.get("format") != RIG_FORMAT:
        raise UnsupportedFormatError(f"{source}: expected a JSON object with 'format': '{RIG_FORMAT}'")
    unknown = sorted(set(d) - set(RIG_KEYS))
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown}; expected some of {', '.join(RIG_KEYS)}")
    est = d.get("estimate", False)
    if not isinstance(est, bool):
        raise ConfigError(f"{source}: 'estimate' = {est!r}; expected true or false")
    R = t = None
    rel = d.get("cam_thermal_from_cam_rgb")
    if rel is not None:
        try:
            R = np.asarray(rel["R"], float)
            t = np.asarray(rel["t"], float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: 'cam_thermal_from_cam_rgb' must hold 'R' (3x3) and 't' (3, metres): {exc}") from None
        if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise ConfigError(f"{source}: 'cam_thermal_from_cam_rgb': R must be 3x3 and t 3 finite numbers; got shapes "
                              f"{R.shape} and {t.shape}")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ConfigError(f"{source}: 'cam_thermal_from_cam_rgb.R' is not a proper rotation (R R^T = I, det R = +1 expected)")
        if np.linalg.norm(t) > 100.0:
            raise ConfigError(f"{source}: 'cam_thermal_from_cam_rgb.t' = {t.tolist()}: a rig baseline of "
                              f"{np.linalg.norm(t):.1f} m; expected metres (< 100)")
    elif not est or require_relative:
        raise ConfigError(f"{source}: 'cam_thermal_from_cam_rgb' (R, t) is required"
                          + ("" if require_relative else " unless 'estimate' is true"))
    cam = None
    if d.get("thermal_camera") is not None:
        cam = Camera.from_dict(d["thermal_camera"], source=f"{source}: thermal_camera")
    elif require_camera:
        raise ConfigError(f"{source}: 'thermal_camera' (camera JSON) is required")
    rgb_cam = Camera.from_dict(d["rgb_camera"], source=f"{source}: rgb_camera") if d.get("rgb_camera") is not None else None
    frames = d.get("frames", {})
    if not isinstance(frames, dict) or not all(isinstance(k, str) and isinstance(v, str) and k and v for k, v in frames.items()):
        raise ConfigError(f"{source}: 'frames' must map RGB image names to thermal frame files (non-empty strings)")
    if require_frames and not frames:
        raise ConfigError(f"{source}: 'frames' must map RGB image names to thermal frame files")
    pairing = d.get("pairing", {})
    if not isinstance(pairing, dict) or set(pairing) - {"rgb_suffix", "thermal_suffix"} or \
            not all(isinstance(v, str) for v in pairing.values()):
        raise ConfigError(f"{source}: 'pairing' must be {{'rgb_suffix': str, 'thermal_suffix': str}}; got {pairing!r}")
    notes = d.get("notes", "")
    return RigFile(R, t, est, cam, dict(frames), pairing.get("rgb_suffix", ""), pairing.get("thermal_suffix", ""),
                   notes if isinstance(notes, str) else json.dumps(notes), source, rgb_cam)


def _strip(stem: str, suffix: str) -> str:
    return stem[: -len(suffix)] if suffix and stem.endswith(suffix) else stem


def pair_rig_images(rig: RigFile, images: list) -> tuple[dict, list, dict]:
    """Thermal image index -> RGB image index, from the rig file's ``frames`` or by name.

    Parameters
    ----------
    images : list of dict with ``name``, ``source`` (path) and ``sensor`` ("thermal" | "rgb")

    Returns
    -------
    master : dict int -> int
    notes : list of str
    unpaired : dict thermal index -> reason
    """
    keys_rgb: dict[str, int] = {}
    keys_th: dict[str, int] = {}
    for k, im in enumerate(images):
        names = {im["name"], Path(im.get("source", im["name"])).name, Path(im.get("source", im["name"])).stem}
        target = keys_rgb if im["sensor"] == "rgb" else keys_th
        for n in names:
            target.setdefault(n, k)
    master: dict[int, int] = {}
    notes: list[str] = []
    if rig.frames:
        missing = []
        for rgb_name, th_file in rig.frames.items():
            m = keys_rgb.get(rgb_name, keys_rgb.get(Path(rgb_name).stem))
            s = keys_th.get(Path(th_file).name, keys_th.get(Path(th_file).stem))
            if m is None or s is None:
                missing.append(rgb_name if m is None else th_file)
                continue
            if s in master and master[s] != m:
                raise ConfigError(f"{rig.source}: thermal image {images[s]['name']} is paired with two RGB images "
                                  f"({images[master[s]]['name']}, {images[m]['name']})")
            master[s] = m
        if missing:
            notes.append(f"{rig.source}: {len(missing)} pair(s) in 'frames' name images that are not inputs: "
                         f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
    else:
        by_key: dict[str, int] = {}
        for k, im in enumerate(images):
            if im["sensor"] == "rgb":
                by_key.setdefault(_strip(Path(im.get("source", im["name"])).stem, rig.rgb_suffix), k)
                by_key.setdefault(_strip(im["name"], rig.rgb_suffix), k)
        for k, im in enumerate(images):
            if im["sensor"] != "thermal":
                continue
            for key in (_strip(Path(im.get("source", im["name"])).stem, rig.thermal_suffix), _strip(im["name"], rig.thermal_suffix)):
                if key in by_key:
                    master[k] = by_key[key]
                    break
    used: dict[int, int] = {}
    for s, m in sorted(master.items()):
        if m in used:
            raise ConfigError(f"{rig.source}: RGB image {images[m]['name']} is paired with two thermal images "
                              f"({images[used[m]]['name']}, {images[s]['name']}); a rig exposes one pair at a time")
        used[m] = s
    unpaired = {k: "no RGB partner in the rig pairing" for k, im in enumerate(images)
                if im["sensor"] == "thermal" and k not in master}
    return master, notes, unpaired


def relative_from_poses(R_m, t_m, R_s, t_s):
    """Mean ``cam_s_from_cam_m`` of co-oriented pairs (chordal mean rotation, median translation).

    Parameters
    ----------
    R_m, t_m, R_s, t_s : (K, 3, 3), (K, 3) cam_from_world of the masters and the slaves

    Returns
    -------
    R (3, 3), t (3,), spread_deg (K,) angle of each pair's rotation from the mean
    """
    Rk = np.einsum("kij,klj->kil", R_s, R_m)  # R_s R_m^T
    R = mean_rotation(Rk)
    tk = t_s - np.einsum("ij,kj->ki", R, t_m)
    t = np.median(tk, axis=0)
    spread = np.degrees([np.linalg.norm(axis_angle_from_matrix(r @ R.T)) for r in Rk])
    return R, t, spread


@dataclass
class RigViews:
    """The rig of one block: slave (thermal) image -> master (RGB) image, and ``cam_thermal_from_cam_rgb``.

    ``R``, ``t`` hold the start and, after :func:`~thermogrammetry.sfm.georef.final_adjustment`, the estimate;
    ``std`` (6,) the a-posteriori σ of ``(wx, wy, wz)`` (rad, left increment ``R <- exp([w]x) R``, i.e. about
    the thermal camera's axes) and ``(tx, ty, tz)`` (m, model units in a local frame) when estimated.
    """

    master: dict
    R: np.ndarray
    t: np.ndarray
    fixed: bool
    std: np.ndarray | None = None
    covariance: np.ndarray | None = None
    start: str = ""
    #: σ (3,) rad of a fixed R_rel known from outside the adjustment (an image registration), same axes as ``std``;
    #: propagated into the rig views' rotation σ by :func:`slave_std`
    prior_rotation_std: np.ndarray | None = None
    #: σ (3,) of a fixed t_rel from the same registration (CRS units; 0 for a component it held), propagated into
    #: the rig views' centre σ by :func:`slave_std`
    prior_translation_std: np.ndarray | None = None


def _project_err(cam, R, t, X, xy):
    Xc = X @ R.T + t
    err = np.full(len(X), np.inf)
    ok = Xc[:, 2] > 0
    if ok.any():
        with np.errstate(all="ignore"):
            pr = cam.project(Xc[ok])
        e = np.linalg.norm(pr - xy[ok], axis=1)
        err[ok] = np.where(np.isfinite(e), e, np.inf)
    return err


def attach_rig_images(rec, images, views: RigViews, xy_by_image, *, max_error_px: float = 4.0,
                      min_tri_angle_deg: float = 1.5, gate_factor: float = 3.0) -> tuple[np.ndarray, list]:
    """Put the thermal images of ``views`` into the block of their masters (``images``), poses from the rig.

    Sets ``rec.R, rec.t`` of every slave whose master is in ``images`` (``R_rel R_m``, ``R_rel t_m + t_rel``),
    marks it registered in the master's component, drops its tie observations of existing points that
    reproject worse than ``gate_factor · max_error_px`` with that start, and triangulates the tracks that
    only the slaves made determinable (thermal-thermal tracks): linear n-view on the block's observations,
    kept when every observation reprojects within the gate and the intersection angle is at least
    ``min_tri_angle_deg``. Tracks with two or more valid observations in the block's other images keep
    their point.

    Returns
    -------
    images : (n,) int, the block with its slaves (sorted)
    notes : list of str
    """
    from .reconstruction import triangulate_tracks

    images = np.asarray(images, np.int64)
    in_img = np.zeros(len(rec.registered), bool)
    in_img[images] = True
    slaves = sorted(s for s, m in views.master.items() if in_img[m] and s != m)
    notes: list[str] = []
    if not slaves:
        return images, notes
    comp = int(rec.component[views.master[slaves[0]]])
    tr = rec.tracks
    slave_mask = np.zeros(len(rec.registered), bool)
    slave_mask[slaves] = True
    moved = [s for s in slaves if not (rec.registered[s] and rec.component[s] == comp)]
    for s in slaves:
        m = views.master[s]
        rec.R[s] = views.R @ rec.R[m]
        rec.t[s] = views.R @ rec.t[m] + views.t
        rec.registered[s] = True
        rec.component[s] = comp
        rec.status[s].registered, rec.status[s].component, rec.status[s].reason = True, comp, ""
    block = np.zeros(len(rec.registered), bool)
    block[images] = True
    block[slaves] = True
    base = rec.obs_valid & block[tr.image] & ~slave_mask[tr.image]
    cnt = np.bincount(tr.track[base], minlength=len(rec.points))
    owned = np.isfinite(rec.points).all(1) & (cnt >= 2)
    # slave observations of the block's points; the gate widens with the median misfit of the start (a rig or
    # intrinsics still far from their estimate), the final adjustment's robust round rejects what is left
    so = np.nonzero(slave_mask[tr.image] & owned[tr.track] & rec.obs_valid)[0]
    err_so = np.full(len(so), np.inf)
    for s in slaves:
        sel = tr.image[so] == s
        if sel.any():
            o = so[sel]
            err_so[sel] = _project_err(rec.cameras[rec.image_camera[s]], rec.R[s], rec.t[s], rec.points[tr.track[o]],
                                       xy_by_image[s][tr.feature[o]])
    fin = err_so[np.isfinite(err_so)]
    gate = max(gate_factor * max_error_px, 4.0 * float(np.median(fin)) if len(fin) else 0.0)
    bad = ~(err_so <= gate)
    rec.obs_valid[so[bad]] = False
    n_drop = int(bad.sum())
    # tracks the slaves make determinable
    cand = np.unique(tr.track[slave_mask[tr.image]])
    cand = cand[~owned[cand]]
    n_new = 0
    if len(cand):
        rec.points[cand] = np.nan
        is_c = np.zeros(len(rec.points), bool)
        is_c[cand] = True
        obs = np.nonzero(rec.obs_valid & block[tr.image] & is_c[tr.track])[0]
        c2 = np.bincount(tr.track[obs], minlength=len(rec.points))
        obs = obs[c2[tr.track[obs]] >= 2]
        if len(obs):
            im = tr.image[obs]
            rays = np.zeros((len(obs), 2))
            xy = np.zeros((len(obs), 2))
            for k in np.unique(im):
                sel = im == k
                xy[sel] = xy_by_image[k][tr.feature[obs[sel]]]
                rays[sel] = rec.cameras[rec.image_camera[k]].unproject(xy[sel])[:, :2]
            tid = tr.track[obs]
            ut = np.unique(tid)
            X, ang = triangulate_tracks(ut, tid, rec.R[im], rec.t[im], rays)
            pos = np.searchsorted(ut, tid)
            err = np.full(len(obs), np.inf)
            for k in np.unique(im):
                sel = im == k
                err[sel] = _project_err(rec.cameras[rec.image_camera[k]], rec.R[k], rec.t[k], X[pos[sel]], xy[sel])
            bad = np.zeros(len(ut), bool)
            np.logical_or.at(bad, pos, ~(err <= max_error_px * gate_factor))
            ok = np.isfinite(X).all(1) & (ang >= min_tri_angle_deg) & ~bad
            rec.points[ut[ok]] = X[ok]
            n_new = int(ok.sum())
    notes.append(f"rig: {len(slaves)} thermal image(s) posed from their RGB partners"
                 + (f" ({len(moved)} not oriented on their own)" if moved else "")
                 + f"; {n_new} thermal tie point(s) triangulated through the rig, {n_drop} observation(s) beyond "
                 f"{gate:.1f} px dropped")
    return np.unique(np.concatenate([images, np.asarray(slaves, np.int64)])), notes


def slave_std(views: RigViews, rec, fa, s: int) -> tuple[np.ndarray, np.ndarray]:
    """σ of the centre (m) and rotation (deg) of rig view ``s``, propagated from the master pose and the rig.

    Uses the a-posteriori covariance of ``fa`` (names ``image<m>.wx..Z0`` and ``rig0.wx..tz``) and, for a fixed rig
    registered on image edges, its rotation and translation σ (``views.prior_rotation_std``,
    ``views.prior_translation_std``, independent of the adjustment); first-order propagation by central
    differences. NaN when the covariance is not available.
    """
    m = views.master[s]
    names = list(fa.param_names or [])
    if fa.covariance is None or f"image{m}.X0" not in names:
        return np.full(3, np.nan), np.full(3, np.nan)
    idx = {n: k for k, n in enumerate(names)}
    cols = [idx[f"image{m}.{a}"] for a in ("wx", "wy", "wz", "X0", "Y0", "Z0")]
    rig_cols = [idx.get(f"rig0.{a}") for a in ("wx", "wy", "wz", "tx", "ty", "tz")]
    use_rig = not views.fixed and all(c is not None for c in rig_cols)
    if use_rig:
        cols += rig_cols
    prior = None
    if not use_rig and (views.prior_rotation_std is not None or views.prior_translation_std is not None):
        pr = np.zeros(3) if views.prior_rotation_std is None else np.asarray(views.prior_rotation_std, float)
        pt = np.zeros(3) if views.prior_translation_std is None else np.asarray(views.prior_translation_std, float)
        prior = np.nan_to_num(np.concatenate([pr, pt]), nan=0.0)
    Rm = rec.R[m]
    R0, t0 = views.R, views.t

    def f(p):
        Rm_ = matrix_from_axis_angle(p[0:3]) @ Rm
        Rr, tr_ = R0, t0
        if use_rig:
            Rr = matrix_from_axis_angle(p[6:9]) @ R0
            tr_ = t0 + p[9:12]
        elif prior is not None:
            Rr = matrix_from_axis_angle(p[6:9]) @ R0
            tr_ = t0 + p[9:12]
        Rs = Rr @ Rm_
        # C_s = -R_sᵀ t_s with t_s = R_r (-R_m C_m) + t_r, i.e. C_m - R_sᵀ t_r: returned relative to C_m, since
        # differences of projected-CRS coordinates (~1e6 m) over h = 1e-6 lose four digits
        dCs = p[3:6] - Rs.T @ tr_
        w = axis_angle_from_matrix(Rs @ (R0 @ Rm).T)
        return np.concatenate([dCs, w])

    n = len(cols) + (6 if prior is not None else 0)
    J = np.zeros((6, n))
    for a in range(n):
        h = 1e-6
        d = np.zeros(n)
        d[a] = h
        J[:, a] = (f(d) - f(-d)) / (2 * h)
    S = np.zeros((n, n))
    S[: len(cols), : len(cols)] = fa.covariance[np.ix_(cols, cols)]
    if prior is not None:  # independent of the adjustment
        S[len(cols):, len(cols):] = np.diag(prior ** 2)
    C = J @ S @ J.T
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    return sd[:3], np.degrees(sd[3:])


def rig_report(views: RigViews, georeferenced: bool) -> dict:
    """The rig for survey.json: our convention and seed 002's (R* = R_rel^T, base b = -R_rel^T t_rel)."""
    R, t = views.R, views.t
    b = -R.T @ t
    d = {"estimated": not views.fixed, "start": views.start, "pairs": len(views.master),
         "cam_thermal_from_cam_rgb": {"R": R.tolist(), "t": t.tolist()},
         "rotation_vector_deg": np.degrees(axis_angle_from_matrix(R)).tolist(),
         "seed002": {"R_star": R.T.tolist(), "t_base_rgb_frame": b.tolist()},
         "baseline": float(np.linalg.norm(t)), "unit": "m" if georeferenced else "model units (local frame)"}
    if views.std is not None:
        d["std"] = {"rotation_deg": np.degrees(views.std[:3]).tolist(), "t": views.std[3:].tolist()}
        if views.covariance is not None:
            # σ of the base vector b = -R^T t (seed 002's t) by first-order propagation
            J = np.zeros((3, 6))
            for a in range(6):
                h = 1e-7
                dd = np.zeros(6)
                dd[a] = h
                bp = -(matrix_from_axis_angle(dd[:3]) @ R).T @ (t + dd[3:])
                bm = -(matrix_from_axis_angle(-dd[:3]) @ R).T @ (t - dd[3:])
                J[:, a] = (bp - bm) / (2 * h)
            d["std"]["t_base_rgb_frame"] = np.sqrt(np.maximum(np.diag(J @ views.covariance @ J.T), 0)).tolist()
    return d


def _co_pairs(rec, master, images) -> list:
    """(slave, master) pairs oriented together (same component) with the master among ``images``."""
    inb = set(np.asarray(images).tolist())
    return [(s, m) for s, m in sorted(master.items())
            if m in inb and rec.registered[s] and rec.registered[m] and rec.component[s] == rec.component[m]]


def plan_rig_blocks(rec, rig: RigFile, master: dict, comps: list) -> tuple[list, dict, list]:
    """Which blocks carry the rig, and the blocks without the thermal images that join them.

    A block carries the rig when some of its RGB images have thermal partners and a start for
    ``R_rel, t_rel`` exists: given in the rig file, or (``estimate`` only) at least one thermal image
    oriented in that block together with its partner. The thermal partners of its RGB images are taken out of
    every block (they re-enter as rig views in :func:`attach_rig_images`).

    Returns
    -------
    comps : list of (n_k,) int arrays (same order; a block emptied this way is an empty array)
    enabled : dict block index -> number of co-oriented pairs
    notes : list of str
    """
    notes = []
    enabled = {}
    take = set()
    for ci, images in enumerate(comps):
        inb = set(np.asarray(images).tolist())
        ms = [(s, m) for s, m in master.items() if m in inb]
        if not ms:
            continue
        co = _co_pairs(rec, master, images)
        if rig.R is None and not co:
            notes.append(f"block {ci + 1}: rig.json gives no R, t and no thermal image was oriented together with its RGB "
                         "partner: the rig cannot start, the thermal images keep their own orientation")
            continue
        enabled[ci] = len(co)
        take |= {s for s, _ in ms}
    out = [np.asarray([i for i in np.asarray(c).tolist() if i not in take], np.int64) for c in comps]
    return out, enabled, notes


def t_with_sigma_text(t, sd) -> str:
    """``"x, y, z (σ a, b, held)"``: a rig translation with its σ per component ("held" where σ is None or NaN)."""
    sd = [np.nan if v is None else float(v) for v in sd]
    return (f"{', '.join(f'{x:.3f}' for x in t)} (σ "
            f"{', '.join('held' if not np.isfinite(x) else f'{x:.3f}' for x in sd)})")


def start_rig(rec, rig: RigFile, master: dict, images, scale: float = 1.0) -> tuple[RigViews, list]:
    """The starting ``R_rel, t_rel`` of a block: the rig file's, or the mean of its co-oriented pairs.

    ``images`` are the block's images before the similarity to the datum, ``scale`` that similarity's scale
    (model -> CRS), applied to a ``t`` estimated from the model.
    """
    notes = []
    co = _co_pairs(rec, master, images)
    if rig.registered is not None:
        r = rig.registered
        R0, t0 = rig.R.copy(), rig.t.copy() * scale
        how = (f"image registration of {r['pairs_used']} of {r['pairs']} RGB/thermal pairs (rotation σ "
               f"{', '.join(f'{x:.3f}' for x in r['rotation_std_deg'])} deg, spread {r['spread_deg']:.2f} deg; "
               + (f"t from the parallax between pairs: "
                  f"{t_with_sigma_text(t0, [None if v is None else v * scale for v in r.get('translation_std') or [None] * 3])})"
                  if r["t_determined"] else
                  f"t not determined (pairs at one depth), held at its start {np.round(t0, 3).tolist()})"))
    elif rig.R is not None:
        R0, t0, how = rig.R.copy(), rig.t.copy(), f"{rig.source}"
        if co:
            R1, t1, spread = relative_from_poses(rec.R[[m for _, m in co]], rec.t[[m for _, m in co]], rec.R[[s for s, _ in co]],
                                                 rec.t[[s for s, _ in co]])
            d = np.degrees(np.linalg.norm(axis_angle_from_matrix(R1 @ R0.T)))
            notes.append(f"rig: {len(co)} thermal image(s) oriented on their own with their partners agree with "
                         f"{rig.source}'s R* within {d:.2f} deg (spread {float(np.median(spread)):.2f} deg)")
    else:
        R0, t0, spread = relative_from_poses(rec.R[[m for _, m in co]], rec.t[[m for _, m in co]], rec.R[[s for s, _ in co]],
                                             rec.t[[s for s, _ in co]])
        t0 = t0 * scale
        how = f"mean of {len(co)} thermal image(s) oriented with their RGB partners (rotation spread median {float(np.median(spread)):.2f} deg)"
    prior = prior_t = None
    if rig.registered is not None:
        prior = np.deg2rad(np.asarray(rig.registered["rotation_std_deg"], float))
        if rig.registered.get("t_determined"):  # held components: 0 (the registration does not know them either)
            prior_t = np.array([np.nan if v is None else float(v) * scale
                                for v in rig.registered.get("translation_std") or [None] * 3])
    return RigViews(dict(master), R0, t0, fixed=not rig.estimate, start=how, prior_rotation_std=prior,
                    prior_translation_std=prior_t), notes


def own_observations(views: RigViews, images, obs_image, manual_obs=()) -> dict:
    """Observations of its own per rig view of a block: slave image -> count.

    Parameters
    ----------
    views : RigViews
    images : (n,) int, the block's images (masters and slaves)
    obs_image : (K,) int, image index of every tie observation that counts (e.g. ``FinalAdjustment.tie_obs_image``
        after the adjustment, or the valid observations of triangulated points before it)
    manual_obs : iterable of (image index, ...) manual measurements (tie points, GCPs) in the block
    """
    inb = set(np.asarray(images).tolist())
    slaves = [s for s, m in views.master.items() if s in inb and m in inb]
    cnt = np.bincount(np.asarray(obs_image, np.int64), minlength=max(slaves, default=-1) + 1) if len(obs_image) else None
    out = {s: int(cnt[s]) if cnt is not None and s < len(cnt) else 0 for s in slaves}
    for o in manual_obs:
        if int(o[0]) in out:
            out[int(o[0])] += 1
    return out


def rig_estimation_evidence(rec, views: RigViews, images, counts: dict, *, min_frames: int = RIG_EST_MIN_FRAMES,
                            min_obs: int = RIG_EST_MIN_OBSERVATIONS, min_spread: float = RIG_EST_MIN_SPREAD) -> tuple[bool, str]:
    """Is there enough evidence in a block to estimate R*, t? Returns ``(ok, reason)``.

    ``counts`` (slave -> own observations, :func:`own_observations`) before the adjustment. Enough: at least
    ``min_frames`` thermal frames with ``min_obs`` observations each, and the camera centres of their RGB
    partners spanning at least ``min_spread`` of the largest distance between the block's camera centres (a
    rig seen from a few neighbouring stations is a rig seen once: its rotation about the baseline and the
    baseline length trade against the block's own errors).
    """
    good = sorted(s for s, n in counts.items() if n >= min_obs)
    need = f"(>= {min_frames} thermal frames with >= {min_obs} own observations each, spread over the block, are needed)"
    if len(good) < min_frames:
        return False, (f"only {len(good)} thermal frame(s) with >= {min_obs} own observations {need}")
    C = rec.centers()
    Cb = C[np.asarray(images, np.int64)]
    Cg = C[[views.master[s] for s in good]]

    def span(P):
        return float(np.max(np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2))) if len(P) > 1 else 0.0

    full = span(Cb)
    frac = span(Cg) / full if full > 0 else 0.0
    if not frac >= min_spread:
        return False, (f"the {len(good)} thermal frames with own observations are bunched: their partners span "
                       f"{frac:.0%} of the block (< {min_spread:.0%}) {need}")
    return True, f"{len(good)} thermal frames with >= {min_obs} own observations, spanning {frac:.0%} of the block"


def rig_estimate_accepted(views: RigViews, fa) -> tuple[bool, str]:
    """After the final adjustment: a converged solve and finite σ of all six rig parameters."""
    res = fa.result
    term = getattr(getattr(res, "termination", None), "value", str(getattr(res, "termination", "")))
    if not getattr(res, "success", False) or term != "converged":
        return False, f"the adjustment did not converge ({term}: {getattr(res, 'reason', '')})"
    if views.std is None or not np.all(np.isfinite(views.std)) or not np.all(views.std > 0):
        return False, "no finite σ of R*, t (covariance not available or singular)"
    return True, ""
