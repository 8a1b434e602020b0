"""Ring-coded marks on a mask circle grid: reading, and fixing the grid's numbering with them (seed 003).

The mark design is :mod:`thermogrammetry.targets.coded_marks`: a grid circle with a concentric ring of
``code_bits`` sectors, each cut out (1) or mask (0), with a mask bridge on every sector boundary.

Reading a mark (:func:`read_ring_marks`)
----------------------------------------
1. Disc candidates are the ellipses of :func:`~thermogrammetry.calibration.detect_circles.ellipse_candidates`
   (adaptive thresholds over several scales) of the wanted polarity.
2. Each candidate's fitted ellipse ``c + A u`` (``A = R(θ) diag(a, b)``, ``|u| = 1`` the disc's rim)
   defines the **disc-normalised frame** ``u``: an affine map of the target plane around the disc
   (perspective and lens distortion are smooth over the mark: their second-order part across a ring
   of 30 px is ~0.6 px at 35 px of corner distortion) takes the target's concentric circles of
   radius ``ρ · r`` to ``|u| = ρ`` and the target's polar angle ψ to ``φ = ψ + q`` (one unknown
   rotation ``q``; ``det A > 0`` keeps the sense of rotation of a front view).
3. The image (lightly smoothed) is sampled in that frame on the disc (ρ ≤ 0.5: the hot level of a
   bright mark), in the gap between disc and ring (cold level), on three circles across the ring
   (720 angles) and just outside the ring (cold again; at least half of that circle inside the frame).
   Values are normalised to 0 (cold) .. 1 (hot); the gap and the outside must read cold (a grid circle of another mark, a random blob or a mark
   whose ring leaves the frame fails here).
4. The ring's angular profile is cut at 0.5 into arcs; an arc of ``n`` sectors (bridges blurred away
   or not) is centred on the middle of its ``n`` sectors, so every arc gives the sector phase modulo
   one sector; their circular mean is the phase. Each sector's mean over its central half must be
   decisive (< 0.3 or > 0.7), else the reading is refused.
5. The bits are matched exactly against every rotation of every code
   (:func:`~thermogrammetry.targets.match_ring_code`; codes ≥ 3 bits apart under rotation: one or two
   wrong bits give no match rather than another code). The match gives the code id and the angle of
   the code's sector 0, i.e. the image direction of the target's +x axis at the mark.

Using the marks (:func:`detect_coded_circle_grid`)
--------------------------------------------------
The rings of every disc that carries one (decoded or not) are painted over with a plane through the
mask around them, then the plain grid detector runs on that image (so circles next to rings are
found and measured as on a plain grid). Each decoded mark is matched to a found circle; a lattice
rotation (multiple of 90°) and translation of the found circles' numbering that puts every circle on
the target, every decoded mark on its own circle and agrees with each mark's decoded orientation
(within 45°) is looked for; the one that most marks agree with is applied when no other does as well.
A whole grid's 180° ambiguity and a partial grid's placement are so resolved. No decoded mark, or
marks that disagree: the plain detector's numbering is kept (``extra["coded_marks"]["ordering"]``
says which).

References
----------
Khodaei, B. et al. (2015). 3D surface generation from aerial thermal imagery (seed 003, section 3.2:
28 circles with 4 coded targets cut out of a mask, 20 mm at 50 mm, in front of a monitor).
Schneider, C.-T. (1991). Objektgestützte Mehrbildzuordnung. PhD thesis, TU Dresden (ring codes).
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10).
"""

from __future__ import annotations

import dataclasses
import warnings

import cv2
import numpy as np

from ..errors import ConfigError
from ..targets import CodedCircleGridTarget, match_ring_code
from .detect_common import Detection, to_gray_float

__all__ = ["read_ring_marks", "paint_over_rings", "number_by_marks", "detect_coded_circle_grid"]

_N_ANGLES = 720


def _frame(c):
    """(centre (2,), A (2, 2)) of an ellipse-candidate row: image = centre + A u, |u| = 1 on the rim."""
    ca, sa = np.cos(c[6]), np.sin(c[6])
    A = np.array([[ca, -sa], [sa, ca]]) @ np.diag([0.5 * c[2], 0.5 * c[3]])
    return np.array(c[:2], float), A


def _sample(img, centre, A, rho, phi):
    """Bilinear samples of ``img`` at ``centre + A (ρ cos φ, ρ sin φ)``; NaN outside the frame.
    ``rho`` and ``phi`` broadcast."""
    rho, phi = np.broadcast_arrays(np.asarray(rho, float), np.asarray(phi, float))
    u = np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=-1)
    p = centre + u @ A.T
    mx = p[..., 0].astype(np.float32).reshape(1, -1)
    my = p[..., 1].astype(np.float32).reshape(1, -1)
    v = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    v = v.reshape(rho.shape).astype(np.float64)
    h, w = img.shape
    out = (p[..., 0] < 0) | (p[..., 0] > w - 1) | (p[..., 1] < 0) | (p[..., 1] > h - 1)
    v[out] = np.nan
    return v


def _geometry(target: CodedCircleGridTarget):
    r = 0.5 * target.diameter_mm
    ri, ro = target.ring_inner_mm / r, target.ring_outer_mm / r
    nn = target.nearest_neighbour_mm / r
    return dict(
        disc=np.array([0.0, 0.25, 0.5]),
        gap=0.5 * (1.0 + ri),
        ring=ri + (ro - ri) * np.array([0.3, 0.5, 0.7]),
        outside=min(ro + 0.4, 0.5 * (ro + nn - 1.0)),
        inner=ri,
        outer=ro,
        half_bridge=0.5 * target.bridge_mm / (0.5 * (target.ring_inner_mm + target.ring_outer_mm)),
    )


def _frac_hot(v):
    """Fraction of the finite values above 0.5 (1.0 when none is finite: nothing to vouch for)."""
    v = np.asarray(v)
    f = np.isfinite(v)
    return float(np.mean(v[f] > 0.5)) if f.any() else 1.0


def _read_one(img, cand_row, target, bright, geo):
    """Read one candidate. Returns a dict (see :func:`read_ring_marks`)."""
    n = target.code_bits
    w = 2 * np.pi / n
    centre, A = _frame(cand_row)
    phi = np.linspace(0.0, 2 * np.pi, _N_ANGLES, endpoint=False)
    out = dict(centre_px=centre, frame=A, code_id=-1, shift=-1, x_axis_px=None, ring=False, reason="")
    disc = _sample(img, centre, A, geo["disc"][:, None], phi[None, ::15])
    gap = _sample(img, centre, A, geo["gap"], phi)
    ring = _sample(img, centre, A, geo["ring"][:, None], phi[None, :])
    outside = _sample(img, centre, A, geo["outside"], phi)
    if np.isnan(disc).any() or np.isnan(gap).mean() > 0.5:
        out["reason"] = "disc or gap outside the frame"
        return out
    hot = float(np.nanmedian(disc))
    cold = float(np.nanmedian(np.concatenate([gap, outside])))
    sign = 1.0 if bright else -1.0
    if not sign * (hot - cold) > 0:
        out["reason"] = "disc not of the expected polarity against the mask around it"
        return out
    s_gap = (gap - cold) / (hot - cold)
    s_out = (outside - cold) / (hot - cold)
    s_ring = (ring - cold) / (hot - cold)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: ring angles outside the frame
        prof = np.nanmean(s_ring, axis=0)
        gap_hot = _frac_hot(s_gap)
        out_hot = _frac_hot(s_out)
        ring_hot = _frac_hot(prof)
    # a ring is there (decoded or not): a clean gap and outside, and at least half a sector's worth of
    # hot ring; a mark cut by the frame border counts as well, so that its arcs are painted over
    out["ring"] = bool(gap_hot < 0.05 and out_hot < 0.1 and 0.5 / n < ring_hot < 1.0 - 0.5 / n)
    if np.isnan(ring).any():
        out["reason"] = "ring leaves the frame"
        return out
    if np.isnan(outside).mean() > 0.5:
        out["reason"] = "the mask outside the ring leaves the frame"
        return out
    noise = 1.4826 * np.median(np.abs(np.diff(s_gap))) / np.sqrt(2.0)
    if gap_hot > 0.02 or out_hot > 0.1 or noise > 0.12:
        out["reason"] = (f"mask around the disc not clean (gap {100 * gap_hot:.0f} % hot, outside "
                         f"{100 * out_hot:.0f} % hot, noise {noise:.2f} of the contrast)")
        return out
    hi = prof > 0.5
    if hi.all() or not hi.any():
        out["reason"] = "ring uniform (no code)"
        return out
    # arcs: cyclic runs of hi; the profile rolled so that it starts on a low sample
    s0 = int(np.argmin(hi))
    hr = np.roll(hi, -s0)
    pr = np.roll(prof, -s0)
    d = np.diff(hr.astype(int))
    starts, ends = np.flatnonzero(d == 1) + 1, np.flatnonzero(d == -1) + 1
    if hr[-1]:
        ends = np.r_[ends, len(hr)]
    step = 2 * np.pi / _N_ANGLES

    def cross(i):  # sub-sample position of the 0.5 crossing between samples i-1 and i (rolled index)
        a, b = pr[(i - 1) % len(pr)], pr[i % len(pr)]
        return (i - 1 + (0.5 - a) / (b - a)) if b != a else float(i)

    est = []
    for a, b in zip(starts, ends):
        t0, t1 = cross(a) * step, cross(b) * step
        length = t1 - t0
        k = max(1, int(round((length + 2 * geo["half_bridge"]) / w)))
        mid = 0.5 * (t0 + t1) + s0 * step
        est.append(mid - 0.5 * (k - 1) * w)
    z = np.exp(1j * np.asarray(est) * (2 * np.pi / w))
    if np.abs(z.mean()) < 0.8:
        out["reason"] = "arcs do not sit on one sector grid"
        return out
    phase = float(np.angle(z.mean())) * w / (2 * np.pi)
    bits = np.zeros(n, int)
    for k in range(n):
        c = phase + k * w
        sel = np.abs(np.angle(np.exp(1j * (phi - c)))) <= 0.25 * w
        m = float(np.mean(prof[sel]))
        if 0.3 <= m <= 0.7:
            out["reason"] = f"sector {k} undecided ({m:.2f} of the contrast)"
            return out
        bits[k] = m > 0.5
    hit = match_ring_code(bits, n)
    if hit is None:
        out["reason"] = f"bits {''.join(map(str, bits))} match no code"
        return out
    cid, shift = hit
    phi0 = phase + ((-shift) % n) * w  # normalised angle of the code's sector 0 = target +x
    v = A @ np.array([np.cos(phi0), np.sin(phi0)])
    out.update(code_id=int(cid), shift=int(shift), x_axis_px=v / np.linalg.norm(v), bits=bits,
               contrast=float(hot - cold), reason="decoded")
    return out


def read_ring_marks(gray: np.ndarray, target: CodedCircleGridTarget, bright: bool, cand: np.ndarray | None = None) -> list:
    """Read every ring-coded mark of one polarity in an image.

    Parameters
    ----------
    gray : ndarray (H, W) float
        The image (any scale).
    target : CodedCircleGridTarget (mm)
    bright : bool
        Cut-outs brighter than the mask (hot emitter behind a cold mask, seed 003).
    cand : ndarray (K, 8), optional
        :func:`~thermogrammetry.calibration.detect_circles.ellipse_candidates` of ``gray`` for this
        polarity, when already computed.

    Returns
    -------
    list of dict, one per disc that carries a ring (decoded or not), keys: ``centre_px`` (2,) the
    disc's ellipse centre (px), ``frame`` (2, 2) the disc-normalised frame ``A``, ``code_id`` (-1 when
    not decoded), ``shift``, ``x_axis_px`` (2,) unit image direction of the target's +x axis at the
    mark (None when not decoded), ``ring`` (True), ``reason`` ("decoded" or why not).
    """
    from .detect_circles import _one_per_disc, ellipse_candidates

    if not target.marks:
        return []
    if cand is None:
        cand = ellipse_candidates(gray, bright)
    if len(cand) == 0:
        return []
    cand = _one_per_disc(cand[cand[:, 7] <= 0.15])
    geo = _geometry(target)
    img = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), 0.7)
    found = []
    for row in cand:
        if row[3] < 3.0:
            continue
        r = _read_one(img, row, target, bright, geo)
        if r["ring"] or r["code_id"] >= 0:
            found.append(r)
    # one reading per disc (nested candidates of one disc): keep decoded ones first
    found.sort(key=lambda r: r["code_id"] < 0)
    keep = []
    for r in found:
        rad = np.sqrt(abs(np.linalg.det(r["frame"])))
        if all(np.hypot(*(r["centre_px"] - k["centre_px"])) > 0.5 * rad for k in keep):
            keep.append(r)
    # a ring that is not read is painted over only when it surely belongs to a grid disc: not inside a
    # decoded mark's ring zone (an arc of that ring taken for a disc), at least half the disc area
    # of the decoded marks, and no disc candidate as large as itself within its ring zone
    dec = [r for r in keep if r["code_id"] >= 0]
    dec_area = np.median([abs(np.linalg.det(r["frame"])) for r in dec]) if dec else 0.0
    areas = np.pi * 0.25 * cand[:, 2] * cand[:, 3]
    zone = geo["outer"] + 0.3
    out = list(dec)
    for r in keep:
        if r["code_id"] >= 0:
            continue
        a_r = abs(np.linalg.det(r["frame"]))
        if any(np.linalg.norm(np.linalg.solve(k["frame"], r["centre_px"] - k["centre_px"])) < zone + 1.0 for k in dec):
            continue
        if a_r < 0.5 * dec_area:
            continue
        u = np.linalg.solve(r["frame"], (cand[:, :2] - r["centre_px"]).T).T
        near = (np.hypot(u[:, 0], u[:, 1]) > 0.5) & (np.hypot(u[:, 0], u[:, 1]) < zone + 1.0) & (areas >= 0.8 * np.pi * a_r)
        if np.any(near):
            continue
        out.append(r)
    keep = out
    # a code read on two discs: neither can be trusted
    ids = [r["code_id"] for r in keep if r["code_id"] >= 0]
    for r in keep:
        if r["code_id"] >= 0 and ids.count(r["code_id"]) > 1:
            r.update(code_id=-1, x_axis_px=None, reason=f"code {r['code_id']} read on two discs")
    return keep


def paint_over_rings(gray: np.ndarray, marks: list, target: CodedCircleGridTarget) -> np.ndarray:
    """A copy of ``gray`` with every mark's ring (normalised radius ``ring_inner - 0.3`` ..
    ``ring_outer + 0.3`` disc radii, never nearer than 1.15 to the disc) replaced by a least-squares
    plane through the mask samples of the gap and outside the ring: the plain grid detector then sees
    discs on a plain mask. (H, W) float32."""
    out = np.array(gray, np.float32, copy=True)
    if not marks:
        return out
    geo = _geometry(target)
    lo, hi = max(1.15, geo["inner"] - 0.3), geo["outer"] + 0.3
    h, w = out.shape
    phi = np.linspace(0.0, 2 * np.pi, 180, endpoint=False)
    for m in marks:
        c, A = m["centre_px"], m["frame"]
        # mask samples for the plane (raw image, before painting)
        pts = []
        for rho in (geo["gap"], geo["outside"]):
            u = np.column_stack([rho * np.cos(phi), rho * np.sin(phi)])
            pts.append(c + u @ A.T)
        pts = np.concatenate(pts)
        vals = _sample(np.asarray(gray, np.float32), c, A, np.r_[np.full(180, geo["gap"]), np.full(180, geo["outside"])],
                       np.r_[phi, phi])
        ok = np.isfinite(vals)
        if ok.sum() < 20:
            continue
        G = np.column_stack([np.ones(ok.sum()), pts[ok, 0] - c[0], pts[ok, 1] - c[1]])
        coef, *_ = np.linalg.lstsq(G, vals[ok], rcond=None)
        res = vals[ok] - G @ coef
        keep = np.abs(res) <= 3.0 * 1.4826 * np.median(np.abs(res)) + 1e-12  # robust: one refit
        if keep.sum() >= 10:
            coef, *_ = np.linalg.lstsq(G[keep], vals[ok][keep], rcond=None)
        ext = hi * np.sqrt((A ** 2).sum(axis=1))
        x0, x1 = int(max(0, np.floor(c[0] - ext[0]))), int(min(w - 1, np.ceil(c[0] + ext[0])))
        y0, y1 = int(max(0, np.floor(c[1] - ext[1]))), int(min(h - 1, np.ceil(c[1] + ext[1])))
        if x1 < x0 or y1 < y0:
            continue
        yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        d = np.stack([xx - c[0], yy - c[1]], axis=-1)
        u = d @ np.linalg.inv(A).T
        rho = np.hypot(u[..., 0], u[..., 1])
        sel = (rho >= lo) & (rho <= hi)
        plane = coef[0] + coef[1] * (xx - c[0]) + coef[2] * (yy - c[1])
        sub = out[y0:y1 + 1, x0:x1 + 1]
        sub[sel] = plane[sel]
    return out


def _lattice(target) -> tuple[np.ndarray, dict]:
    """Integer lattice coordinates (units of the spacing) of every object point, and the inverse map."""
    q = np.rint(target.object_points()[:, :2] / target.spacing_mm).astype(int)
    return q, {(int(a), int(b)): i for i, (a, b) in enumerate(q)}


def number_by_marks(det: Detection, marks: list, target: CodedCircleGridTarget) -> tuple[Detection, dict]:
    """Renumber a grid detection so that the decoded marks sit on their own circles.

    Parameters
    ----------
    det : Detection (found) of the plain grid, any valid numbering (a whole grid's canonical order or a
        partial grid's first placement).
    marks : list of dict from :func:`read_ring_marks` (decoded ones are used).
    target : CodedCircleGridTarget

    Returns
    -------
    (Detection, info) -- the renumbered detection (points sorted by object id) or ``det`` itself when
    no numbering is fixed, and a dict: ``decoded`` {code id: object id} of the marks the numbering
    agrees with, ``rejected`` {code id: why}, ``undecoded`` (count of rings not read), ``ordering``
    ("coded marks" / "geometric: ..."), ``agreeing_numberings`` (1 when fixed),
    ``numberings_without_marks`` (lattice rotations + translations that keep every found circle on the
    target: > 1 where the circles alone are ambiguous), ``renumbered`` (the marks changed the numbering).
    """
    pts, ids = det.points_px, det.object_ids
    q, lut = _lattice(target)
    cur = q[ids]
    rots = [np.array([[1, 0], [0, 1]]), np.array([[0, -1], [1, 0]]), np.array([[-1, 0], [0, -1]]), np.array([[0, 1], [-1, 0]])]
    # numberings the circles alone allow: lattice rotations and translations that keep every circle
    # on the target (2 for a whole rectangular symmetric grid: its 180° turn)
    n_geo = 0
    for Rk in rots:
        new = cur @ Rk.T
        for j in range(len(q)):
            t = q[j] - new[0]
            n_geo += all((int(a), int(b)) in lut for a, b in new + t)
    info = {"decoded": {}, "rejected": {}, "undecoded": int(sum(m["code_id"] < 0 for m in marks)),
            "ordering": "", "agreeing_numberings": 0, "numberings_without_marks": int(n_geo), "renumbered": False}
    dec = [m for m in marks if m["code_id"] >= 0]
    if not dec:
        info["ordering"] = "geometric: no mark decoded"
        return det, info
    rad = float(det.extra.get("radius_px", 5.0))
    use = []
    for m in dec:
        pid = target.point_of_code(m["code_id"])
        if pid is None:
            info["rejected"][m["code_id"]] = "no mark of the target carries this code"
            continue
        dist = np.linalg.norm(pts - m["centre_px"], axis=1)
        k = int(np.argmin(dist))
        if dist[k] > 0.5 * rad + 1.0:
            info["rejected"][m["code_id"]] = "its disc is not among the grid's measured circles"
            continue
        use.append((m, k, pid))
    if not use:
        info["ordering"] = "geometric: no decoded mark on a measured circle"
        return det, info
    obj_all = target.object_points()[:, :2]
    cands = {}
    for Rk_i, Rk in enumerate(rots):
        for (_, k, pid) in use:
            t = q[pid] - Rk @ cur[k]
            key = (Rk_i, int(t[0]), int(t[1]))
            if key in cands:
                continue
            new = cur @ Rk.T + t
            new_ids = [lut.get((int(a), int(b))) for a, b in new]
            if any(i is None for i in new_ids):
                continue
            new_ids = np.array(new_ids, np.int64)
            H, _ = cv2.findHomography(obj_all[new_ids], pts, 0)
            if H is None:
                continue
            agree = []
            for (m, kk, pidm) in use:
                if new_ids[kk] != pidm:
                    continue
                o = obj_all[pidm]
                e = 0.5 * target.spacing_mm
                pp = np.array([[o[0], o[1], 1.0], [o[0] + e, o[1], 1.0]]) @ H.T
                pp = pp[:, :2] / pp[:, 2:3]
                v = pp[1] - pp[0]
                cosang = float(v @ m["x_axis_px"] / max(np.linalg.norm(v), 1e-12))
                if cosang > np.cos(np.deg2rad(45.0)):
                    agree.append(m["code_id"])
            cands[key] = (new_ids, agree)
    if not cands:
        info["ordering"] = "geometric: no renumbering puts the circles on the target"
        return det, info
    ranked = sorted(cands.values(), key=lambda c: -len(c[1]))
    best = len(ranked[0][1])
    tied = [c for c in ranked if len(c[1]) == best]
    if best == 0 or len(tied) > 1:
        for m, _, _ in use:
            info["rejected"][m["code_id"]] = "marks disagree with each other or with the grid"
        info["ordering"] = "geometric: the decoded marks fix no single numbering"
        info["agreeing_numberings"] = len(tied) if best else 0
        return det, info
    new_ids, agree = ranked[0]
    for m, k, pid in use:
        if m["code_id"] in agree:
            info["decoded"][int(m["code_id"])] = int(pid)
        else:
            info["rejected"][m["code_id"]] = "its position or orientation disagrees with the other marks"
    info["ordering"] = "coded marks"
    info["agreeing_numberings"] = 1
    info["renumbered"] = bool(np.any(new_ids != ids))
    order = np.argsort(new_ids)
    extra = dict(det.extra)
    extra["placements"] = 1
    reason = det.reason
    if "fits the target at" in reason:
        reason = reason.replace(", equivalent up to the view's pose)", "; numbered by the coded marks)")
    reason += f"; numbered by coded mark(s) {', '.join(str(c) for c in sorted(info['decoded']))}"
    out = dataclasses.replace(det, points_px=np.ascontiguousarray(pts[order]), object_ids=np.ascontiguousarray(new_ids[order]),
                              reason=reason, extra=extra)
    return out, info


def detect_coded_circle_grid(image, spec: CodedCircleGridTarget, image_id: str = "", *, polarity: str = "auto",
                             **kw) -> Detection:
    """Find a circle grid with ring-coded marks: read the marks, paint their rings over, find the plain
    grid (:func:`~thermogrammetry.calibration.detect_circles.detect_circle_grid` with every option in
    ``kw``) and number it by the marks (:func:`number_by_marks`).

    Parameters
    ----------
    image : array_like (H, W) or (H, W, 1|3|4), uint8 / uint16 / float
    spec : CodedCircleGridTarget (mm), with ``diameter_mm`` and ``marks``
    image_id : str
    polarity : {"auto", "bright", "dark"}
        Cut-outs brighter or darker than the mask; "auto": the polarity with more decoded marks (ties:
        more rings, then bright), the grid detector then tries that polarity first.

    Returns
    -------
    Detection
        As the plain detector's, numbered by the marks where they fix it; ``extra["coded_marks"]``:
        ``decoded`` {code id: object id}, ``rejected`` {code id: why}, ``undecoded`` (rings not read),
        ``ordering``, ``polarity`` of the marks, and ``readings`` [code id or -1, x, y, reason] per ring.
    """
    from .detect_circles import detect_circle_grid, ellipse_candidates

    if not isinstance(spec, CodedCircleGridTarget):
        raise ConfigError(f"spec: expected a CodedCircleGridTarget (thermogrammetry.targets), got {type(spec).__name__}")
    if polarity not in ("auto", "bright", "dark"):
        raise ConfigError(f"polarity: expected 'auto', 'bright' or 'dark', got {polarity!r}")
    gray = to_gray_float(image, f"image {image_id!r}" if image_id else "image")
    pols = ["bright", "dark"] if polarity == "auto" else [polarity]
    best = None
    for pol in pols:
        m = read_ring_marks(gray, spec, pol == "bright", ellipse_candidates(gray, pol == "bright"))
        score = (sum(r["code_id"] >= 0 for r in m), len(m))
        if best is None or score > best[0]:
            best = (score, pol, m)
    _, mpol, marks = best
    clean = paint_over_rings(gray, marks, spec)
    det_pol = polarity if polarity != "auto" or not marks else mpol
    det = detect_circle_grid(clean, spec.plain(), image_id, polarity=det_pol, **kw)
    if not det.found and det_pol != polarity:
        det = detect_circle_grid(clean, spec.plain(), image_id, polarity=polarity, **kw)
    readings = [[int(r["code_id"]), float(r["centre_px"][0]), float(r["centre_px"][1]), r["reason"]] for r in marks]
    if not det.found:
        info = {"decoded": {}, "rejected": {}, "undecoded": int(sum(r["code_id"] < 0 for r in marks)),
                "ordering": "grid not found", "agreeing_numberings": 0}
    else:
        det, info = number_by_marks(det, marks, spec)
    info.update(polarity=mpol, readings=readings)
    extra = dict(det.extra)
    extra["coded_marks"] = info
    return dataclasses.replace(det, extra=extra)
