"""Circle-grid detection for mask-based thermal calibration targets (Khodaei et al. 2015; Vidas et al. 2012).

A mask with circular holes in front of a warm (or cold) background appears as bright (or dark)
discs. The steps:

1. contrast normalisation (percentile stretch of 8/16-bit or float images; CLAHE as a fallback);
2. ``cv2.findCirclesGrid`` with a ``SimpleBlobDetector`` tuned for small, blurred discs, for bright
   and dark discs (``polarity="auto"``), symmetric or asymmetric, with and without clustering;
3. grid ordering: the candidate orders that keep the pattern are checked against a homography fit
   of the object points; among the valid ones the right-handed one (board frame z away from the
   camera) with corner 0 nearest the image's top-left is kept;
4. sub-pixel centres by background-subtracted, intensity-weighted moments in a circular window,
   re-centred until it converges (blur is a symmetric convolution: it leaves the centroid of a disc
   in place as long as the window holds the blurred disc);
5. perspective-bias correction: the centroid of an imaged circle is the centre of the image ellipse,
   which is not the image of the circle's centre. With a homography ``H`` (plane mm → image px)
   fitted to the centres, each circle ``(x - x0)² + (y - y0)² = R²`` is mapped to its image conic
   ``C' = H^-T C H^-1``; the ellipse centre minus ``H (x0, y0)`` is the bias, subtracted from the
   measurement (two passes).

This module keeps the entry point (:func:`detect_circle_grid`: the cascade of passes, then the
sub-pixel centres, bias correction and completion of a found grid); the steps are in
:mod:`.circle_candidates` (blob and ellipse candidates), :mod:`.circle_order` (grid ordering, whole
grids from ellipses), :mod:`.circle_lattice` (partial grids) and :mod:`.circle_refine` (sub-pixel
centres, perspective bias), whose public names are importable from here as before.

References
----------
Vidas, S., Lakemond, R., Denman, S., Fookes, C., Sridharan, S., Wark, T. (2012). A mask-based
approach for the geometric calibration of thermal-infrared cameras. IEEE TIM 61(6), 1625-1635.
Heikkilä, J. (2000). Geometric camera calibration using circular control points. IEEE TPAMI 22(10),
1066-1077 (perspective bias of circle centres; conic projection).
Khodaei, B. et al. (2015). 3D surface generation from aerial thermal imagery (mask grid of
20 mm holes at 50 mm spacing, contrast enhancement, sub-pixel centres).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import ConfigError
from .circle_candidates import REDRAWN_DETECTOR, blob_detector, ellipse_candidates, one_per_disc, redraw_blobs
from .circle_lattice import partial_grid
from .circle_order import apply_h, fit_h, grid_from_ellipses, order_grid_by_homography
from .circle_refine import circle_shape_matrices, ellipse_centre_bias, refine_circle_centres, refine_circle_edges
from .detect_common import (
    CircleGridSpec,
    Detection,
    clahe_u8,
    flatten_background,
    image_size_of,
    normalize_to_u8,
    spec_of,
    to_gray_float,
)

__all__ = ["detect_circle_grid", "refine_circle_centres", "refine_circle_edges", "circle_shape_matrices", "ellipse_centre_bias", "order_grid_by_homography",
           "ellipse_candidates"]

#: old private names, still imported from here (circle_bias, detect_circle_marks, tests)
_fit_h = fit_h
_one_per_disc = one_per_disc


def detect_circle_grid(image, spec: CircleGridSpec, image_id: str = "", *, polarity: str = "auto",
                       refine: str = "edges", perspective_correction: bool = True, partial: bool = True,
                       min_partial_points: int = 6, flatfield: bool = True) -> Detection:
    """Find a symmetric or asymmetric circle grid and measure sub-pixel centres.

    Parameters
    ----------
    image : array_like (H, W) or (H, W, 1|3|4), uint8 / uint16 / float
    spec : CircleGridSpec
    image_id : str
    polarity : {"auto", "bright", "dark"}
        Discs brighter (holes over a warm background) or darker than their surround; "auto" tries
        bright first, then dark.
    refine : {"edges", "moments", "none"}
        "moments": :func:`refine_circle_centres` on the float image; "edges" (default): those, then the
        area centroid of each disc's sub-pixel outline (:func:`refine_circle_edges`; needs
        ``spec.diameter_mm``, otherwise the moment centres are kept): 0.008 px RMS against the exact
        centroid on sharp 640 x 512 views of 60 mm circles under ~80 px barrel distortion and 55° tilt,
        where the moment window gave 0.09 px (a temperature gradient across the discs, windows too
        small for strongly foreshortened discs); "none": blob-detector centres.
    perspective_correction : bool
        Remove the perspective bias (:func:`ellipse_centre_bias`); needs ``spec.diameter_mm``.
    partial : bool
        When no pass finds the whole grid, accept part of it (circles outside the frame, cut by its
        border or hidden): the ellipse candidates of a consistent size are put on a lattice by
        growing it from neighbour to neighbour (:func:`~.circle_lattice._grow_lattice`), the patch is placed on the
        target (:func:`~.circle_lattice._place_on_target`) and checked with a second-order map and the polarity
        test; circles whose measuring window leaves the frame are dropped. A symmetric patch may fit
        the target at several places (a 3x3 patch of a 4x3 grid at two); they differ by a rigid
        motion of the target plane, which the view's own pose absorbs, so the calibration is the
        same whichever is taken (not so for a rig with a shared target pose: keep the views whole
        there). ``extra["partial"]`` says so and ``extra["placements"]`` counts the valid ones.
    min_partial_points : int
        Fewest circles of a partial grid (default 6, the calibration's minimum per image).
    flatfield : bool
        When the passes on the stretched image fail, run them again on the image flattened by
        :func:`~thermogrammetry.calibration.detect_common.flatten_background` (σ = 1/16 of the larger
        side): low-contrast masks under a heater's hot spot or vignetting ("bright-flatfield",
        "bright-flatfield-ellipses", "...-flatfield-partial"). Centres are measured on the raw image.

    Returns
    -------
    Detection
        ``points_px`` (K, 2) in canonical order (:func:`order_grid_by_homography`), ``object_ids``
        (K,): ``arange(N)`` for a whole grid, the found circles' ids for a partial one.

    Notes
    -----
    A :class:`~thermogrammetry.targets.CodedCircleGridTarget` with marks goes through
    :func:`~thermogrammetry.calibration.detect_circle_marks.detect_coded_circle_grid`: the ring-coded
    marks are read, their rings painted over, this detector runs on the plain grid, and the decoded
    marks fix the numbering (the 180° ambiguity of a whole symmetric grid, the placement of a partial
    one); ``extra["coded_marks"]`` records which marks were decoded.
    """
    spec = spec_of(spec, CircleGridSpec, "CircleGridSpec")
    if getattr(spec, "marks", ()):
        # ring-coded marks (Khodaei et al. 2015): read them, paint their rings over, number the grid by them
        from .detect_circle_marks import detect_coded_circle_grid

        return detect_coded_circle_grid(image, spec, image_id, polarity=polarity, refine=refine,
                                        perspective_correction=perspective_correction, partial=partial,
                                        min_partial_points=min_partial_points, flatfield=flatfield)
    if polarity not in ("auto", "bright", "dark"):
        raise ConfigError(f"polarity: expected 'auto', 'bright' or 'dark', got {polarity!r}")
    if refine not in ("edges", "moments", "none"):
        raise ConfigError(f"refine: expected 'edges', 'moments' or 'none', got {refine!r}")
    if int(min_partial_points) < 4:
        raise ConfigError(f"min_partial_points: expected >= 4 circles, got {min_partial_points!r}")
    gray = to_gray_float(image, f"image {image_id!r}" if image_id else "image")
    size = image_size_of(gray)
    u8 = normalize_to_u8(gray)
    area = float(gray.size)
    blob = blob_detector(area)
    kind = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    pattern = spec.pattern_size
    pols = ["bright", "dark"] if polarity == "auto" else [polarity]
    small = min(gray.shape) < 300

    tried = []

    def blob_pass(pol, vname, img, scale):
        """The blob detector + cv2.findCirclesGrid on one 8-bit variant; the ordered grid or None."""
        det = blob if scale == 1 else blob_detector(area * scale * scale)
        # findCirclesGrid's grid search grows steeply with the number of blobs (18 s for 800 noise
        # blobs in a 160x120 frame): detect the blobs here, keep the largest few times N (grid
        # discs are larger than noise specks) and hand findCirclesGrid a clean redrawn image
        # a light blur first: noise specks otherwise make thousands of contours (2.5 s per call
        # on a 640x480 noise frame, 0.2 s after the blur); the centres are refined on the raw image
        keypoints = det.detect(cv2.GaussianBlur(img, (0, 0), 1.0 * scale))
        if len(keypoints) < spec.n_points:
            tried.append(f"{pol}-{vname} ({len(keypoints)} blobs < {spec.n_points})")
            return None, ""
        cap = max(3 * spec.n_points, spec.n_points + 30)
        keypoints = sorted(keypoints, key=lambda k: -k.size)[:cap]
        clean = redraw_blobs(img.shape, keypoints)
        for flags, fname in ((kind, ""), (kind | cv2.CALIB_CB_CLUSTERING, "+clustering")):
            ok, centres = cv2.findCirclesGrid(clean, pattern, flags=flags, blobDetector=REDRAWN_DETECTOR)
            name = f"{pol}-{vname}{fname}"
            if not ok or centres is None:
                tried.append(name)
                continue
            pts = centres.reshape(-1, 2).astype(np.float64)
            if scale != 1:
                pts = (pts + 0.5) / scale - 0.5
            ordered, rms = order_grid_by_homography(pts, spec)
            if ordered is None:
                tried.append(f"{name} (rejected: grid fits neither a homography nor a second-order map)")
                continue
            return ordered, name
        return None, ""

    for pol in pols:
        base = 255 - u8 if pol == "bright" else u8  # the blob detector looks for dark blobs
        variants = [("stretch", base, 1), ("clahe", clahe_u8(base), 1)]
        if small:
            variants.append(("upsampled", cv2.resize(base, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC), 3))
        for vname, img, scale in variants:
            ordered, name = blob_pass(pol, vname, img, scale)
            if ordered is not None:
                return _finish(gray, ordered, spec, image_id, size, name, tried, pol == "bright", refine,
                               perspective_correction)
    # large discs under strong distortion / perspective: ellipse candidates over several scales of
    # adaptive threshold, grid topology from the candidates' neighbour structure, distortion-aware check
    cands = {}
    for pol in pols:
        cands[pol] = ellipse_candidates(gray, pol == "bright")
        pts, why = grid_from_ellipses(gray, spec, pol == "bright", cands[pol])
        name = f"{pol}-ellipses"
        if pts is not None:
            return _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine, perspective_correction)
        tried.append(f"{name} ({why})")
    # low contrast under a hot spot / vignetting: the same passes on the image flattened by a wide
    # blur (flatten_background, σ = 1/16 of the larger side: it must span more than a circle and
    # its gap; a chessboard's 1/64-1/32 leaves the discs of a sparse grid half-flattened). Run only
    # when everything above failed, so a view found before keeps its centres; the centres are
    # measured on the raw image (its plane background takes the smooth remainder of the hot spot)
    ff_imgs = []
    if flatfield:
        for frac, tag in ((16.0, "flatfield"), (32.0, "flatfield-narrow")):
            ff_u8 = flatten_background(gray, max(gray.shape) / frac)
            ff_img = ff_u8.astype(np.float32)
            ff_imgs.append((tag, ff_img))
            for pol in pols:
                ordered, name = blob_pass(pol, tag, 255 - ff_u8 if pol == "bright" else ff_u8, 1)
                if ordered is not None:
                    return _finish(gray, ordered, spec, image_id, size, name, tried, pol == "bright", refine,
                                   perspective_correction)
            for pol in pols:
                # one row per disc: a flattened disc gives nested contours at many thresholds
                cands[f"{tag}-{pol}"] = one_per_disc(ellipse_candidates(ff_img, pol == "bright"))
                pts, why = grid_from_ellipses(ff_img, spec, pol == "bright", cands[f"{tag}-{pol}"])
                name = f"{pol}-{tag}-ellipses"
                if pts is not None:
                    return _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine,
                                   perspective_correction)
                tried.append(f"{name} ({why})")
    # part of the grid: outside the frame, cut by its border or hidden
    if partial:
        for tag, img in [("", gray)] + ff_imgs:
            for pol in pols:
                key = f"{tag}-{pol}" if tag else pol
                pts, ids, n_place, why = partial_grid(img, spec, pol == "bright", cands[key], int(min_partial_points))
                name = f"{pol}-{tag + '-' if tag else ''}partial"
                if pts is not None and len(ids) == spec.n_points:
                    # every circle: a whole grid after all, in the canonical order of the other passes
                    full = np.empty_like(pts)
                    full[ids] = pts
                    ordered, _ = order_grid_by_homography(full, spec, tol_frac=0.5)
                    return _finish(gray, full if ordered is None else ordered, spec, image_id, size,
                                   name.replace("partial", "lattice"), tried, pol == "bright", refine,
                                   perspective_correction)
                if pts is not None:
                    det = _finish(gray, pts, spec, image_id, size, name, tried, pol == "bright", refine,
                                  perspective_correction, ids=ids, min_points=int(min_partial_points),
                                  n_placements=n_place)
                    if det.found:
                        return det
                    why = det.reason
                tried.append(f"{name} ({why})")
    return Detection.failure(image_id, f"no {pattern[0]}x{pattern[1]} "
                             f"{'asymmetric ' if spec.asymmetric else ''}circle grid found (tried: {', '.join(tried)})", size)


def _finish(gray, pts, spec, image_id, size, name, tried, bright, refine, perspective_correction, *, ids=None,
            min_points=None, n_placements=1) -> Detection:
    """Sub-pixel centres, bias correction and the Detection of grid points ``pts`` (ids: ``arange(N)``
    for a whole grid; for a partial one (``ids`` given) circles whose window leaves the image or whose
    centre is unstable are dropped, and fewer than ``min_points`` left is a failure)."""
    partial = ids is not None
    ids = np.arange(spec.n_points, dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
    obj = spec.object_points()[ids, :2]
    H = fit_h(obj, pts)
    # nearest-neighbour distance in px at every circle, from the homography
    nn_mm = spec.spacing_mm * (np.sqrt(2.0) if spec.asymmetric else 1.0)
    steps = np.stack([np.linalg.norm(apply_h(H, obj + d) - apply_h(H, obj), axis=1)
                      for d in ([nn_mm, 0], [0, nn_mm], [-nn_mm, 0], [0, -nn_mm])])
    nn_px = np.min(steps, axis=0)
    # (for asymmetric grids the nearest neighbour is diagonal, s*sqrt(2) away; an axis step of that
    # length approximates its pixel distance)
    if spec.diameter_mm is not None:
        r_px = 0.5 * spec.diameter_mm / nn_mm * nn_px
    else:
        r_px = 0.2 * nn_px  # Khodaei et al. 2015 geometry (20 mm holes, 50 mm spacing) as a guess
    notes = []
    cut = np.zeros(len(pts), bool)
    if refine in ("moments", "edges"):
        # window: the disc plus ~3 sigma of a typical thermal blur, clear of the neighbouring disc
        # (which starts at nn_px - r_px) with a 2 px background annulus in between
        win = np.minimum(r_px * 1.25 + 3.0, nn_px - r_px - 3.0)
        if np.any(win < r_px + 1.0):
            notes.append("circles too close for moment windows; blob centres kept")
        else:
            # plane background where the annulus (win .. win + 2) stays >= 3 px clear of the
            # neighbouring disc (its blurred edge would read as a gradient); the median elsewhere
            # the annulus as wide as the room allows (2-6 px; a wider one gives a steadier plane)
            ring = np.clip((nn_px - r_px) - win - 3.0, 2.0, 6.0)
            plane = (nn_px - r_px) - (win + ring) >= 3.0
            new, ok = refine_circle_centres(gray, pts, r_px, win, bright, plane_background=plane, ring_px=ring)
            moved = np.linalg.norm(new - pts, axis=1) > 0.5 * r_px + 1.0
            keep = ok & ~moved
            # a circle cut by the frame border (its disc plus 2 px of blur reaching outside) would be
            # off by pixels (9 px measured on a 60 mm circle cut by the border): dropped; a whole disc
            # whose window or annulus leaves the frame, or whose centre does not settle, keeps its
            # blob position
            h_img, w_img = gray.shape
            r_mm = 0.5 * spec.diameter_mm if spec.diameter_mm is not None else 0.2 * nn_mm
            ang = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
            ring_mm = 1.05 * r_mm * np.column_stack([np.cos(ang), np.sin(ang)])
            cut = np.zeros(len(pts), bool)
            for k in range(len(pts)):  # the disc's outline by the homography, placed at its blob centre
                o = apply_h(H, obj[k] + ring_mm) - apply_h(H, obj[k:k + 1]) + pts[k]
                cut[k] = bool(np.any((o[:, 0] < 1.5) | (o[:, 0] > w_img - 2.5) | (o[:, 1] < 1.5) | (o[:, 1] > h_img - 2.5)))
            pts = np.where(keep[:, None], new, pts)
            if np.any(~keep & ~cut) and not (refine == "edges" and spec.diameter_mm is not None):
                notes.append(f"{int((~keep & ~cut).sum())} centre(s) kept at blob positions (window at the border "
                             "or unstable)")
            if np.any(cut) and not (refine == "edges" and spec.diameter_mm is not None):
                notes.append(f"{int(cut.sum())} circle(s) cut by the frame border dropped")
                pts, ids, obj = pts[~cut], ids[~cut], obj[~cut]
                partial = True
                if len(ids) < max(min_points or 6, 4):
                    return Detection.failure(image_id, f"{len(ids)} whole circles left (< {max(min_points or 6, 4)}; "
                                             "the others are cut by the frame border)", size)
    if refine == "edges" and spec.diameter_mm is not None and len(pts) >= 4:
        # outline-based centres (immune to a temperature gradient across the disc and to a moment
        # window that does not hold a strongly foreshortened disc), started from the moment centres
        Q = circle_shape_matrices(fit_h(obj, pts), obj, 0.5 * spec.diameter_mm)
        new, ok_e, outl, _ = refine_circle_edges(gray, pts, Q, bright)
        ok_e &= np.linalg.norm(new - pts, axis=1) < 0.25 * np.sqrt(1.0 / np.linalg.eigvalsh(Q)[:, 0]) + 1.0
        pts = np.where(ok_e[:, None], new, pts)
        if np.any(~ok_e) and ok_e.sum() >= 8:
            # a blob detector's centre can be pixels off (a disc merged with a contrast feature): start
            # again where a second-order map through the other circles puts it
            good_i = np.flatnonzero(ok_e)
            sc = max(float(np.abs(obj).max()), 1e-9)
            A = lambda o: np.column_stack([np.ones(len(o)), o[:, 0] / sc, o[:, 1] / sc, (o[:, 0] / sc) ** 2,
                                           o[:, 0] * o[:, 1] / sc**2, (o[:, 1] / sc) ** 2])
            coef, *_ = np.linalg.lstsq(A(obj[good_i]), pts[good_i], rcond=None)
            bad = np.flatnonzero(~ok_e)
            guess = A(obj[bad]) @ coef
            new_b, ok_b, outl_b, _ = refine_circle_edges(gray, guess, Q[bad], bright)
            ok_b &= np.linalg.norm(new_b - guess, axis=1) < 0.25 * np.sqrt(1.0 / np.linalg.eigvalsh(Q[bad])[:, 0]) + 1.0
            pts[bad[ok_b]] = new_b[ok_b]
            outl[bad[ok_b]] = outl_b[ok_b]
            ok_e[bad[ok_b]] = True
            if np.any(ok_b):
                notes.append(f"{int(ok_b.sum())} centre(s) measured again from the grid's prediction")
            if np.any(~ok_e):
                # neither the blob's nor the predicted start gives an outline: the circle is dropped
                # rather than kept at a blob position that may be pixels off
                keep_e = ok_e.copy()
                notes.append(f"{int((~keep_e).sum())} circle(s) without a measurable outline dropped")
                pts, ids, obj, ok_e, outl, cut = (pts[keep_e], ids[keep_e], obj[keep_e], ok_e[keep_e], outl[keep_e],
                                                  cut[keep_e])
                partial = True
        if len(ids) < spec.n_points and len(ids) >= 6:
            # complete a partial grid: circles the candidate passes missed (a size outside the group's
            # range under steep perspective, a merged blob) are measured where the found ones put them
            pts, ids, obj, ok_e, outl, cut, n_add = _complete_grid(gray, spec, pts, ids, ok_e, outl, cut, bright)
            if n_add:
                notes.append(f"{n_add} circle(s) added where the others predict them")
                partial = len(ids) < spec.n_points
                if not partial:
                    name = name.replace("partial", "lattice")  # a whole grid, as a lattice pass that finds all
        # cut by the frame border: the measured outline (rays that left the frame were filled in by the
        # outline's conic) within 1.5 px of the border; without an outline, the homography's estimate
        h_img, w_img = gray.shape
        with np.errstate(invalid="ignore"):
            out_e = np.any((outl[..., 0] < 1.5) | (outl[..., 0] > w_img - 2.5) | (outl[..., 1] < 1.5)
                           | (outl[..., 1] > h_img - 2.5), axis=1)
        cut = np.where(ok_e, out_e, cut)
        if np.any(cut):
            notes.append(f"{int(cut.sum())} circle(s) cut by the frame border dropped")
            pts, ids, obj, ok_e = pts[~cut], ids[~cut], obj[~cut], ok_e[~cut]
            partial = True
            if len(ids) < max(min_points or 6, 4):
                return Detection.failure(image_id, f"{len(ids)} whole circles left (< {max(min_points or 6, 4)}; "
                                         "the others are cut by the frame border)", size)
        if np.any(~ok_e):
            notes.append(f"{int((~ok_e).sum())} centre(s) by moments or blob positions (too few edge points)")
    if perspective_correction and spec.diameter_mm is not None:
        raw = pts.copy()
        for _ in range(2):
            H = fit_h(obj, pts)
            pts = raw - ellipse_centre_bias(H, obj, 0.5 * spec.diameter_mm)
        notes.append("perspective bias corrected")
    elif perspective_correction:
        notes.append("no perspective-bias correction (diameter_mm unknown)")
    H = fit_h(obj, pts)
    rms = float(np.sqrt(np.mean(np.sum((apply_h(H, obj) - pts) ** 2, axis=1))))
    reason = f"found by {name}" + (f" after {', '.join(tried)} failed" if tried else "")
    if partial:
        notes.insert(0, f"partial grid: {len(ids)} of {spec.n_points} circles"
                     + (f" (the patch fits the target at {n_placements} places, equivalent up to the view's pose)"
                        if n_placements > 1 else ""))
    if notes:
        reason += "; " + "; ".join(notes)
    extra = {"homography_rms_px": rms, "radius_px": float(np.median(r_px)), "polarity": "bright" if bright else "dark"}
    if partial:
        extra.update(partial=True, placements=int(n_placements))
    return Detection(image_id=str(image_id), found=True, points_px=np.ascontiguousarray(pts),
                     object_ids=np.ascontiguousarray(ids), reason=reason, image_size=size, method=name, extra=extra)


def _complete_grid(gray, spec, pts, ids, ok_e, outl, cut, bright):
    """Measure the circles of ``spec`` missing from ``ids`` where a map through the found ones puts
    them (second-order with >= 8 circles, else the homography); a circle is added when its outline is
    measured (:func:`refine_circle_edges`) within a third of its radius of the prediction, on >= 90 % of
    its rays and within max(0.25 px, 1 % of its radius) RMS of a conic (a whole disc: 0.10 px measured at 2 K
    contrast; 0.63 px for a disc of radius 12 px half under an occluding bar), and its area is
    within 0.6-1.6 of the homography's ellipse. Returns the arrays sorted by id, and the number added."""
    h, w = gray.shape
    all_obj = spec.object_points()[:, :2]
    obj = all_obj[ids]
    missing = np.setdiff1d(np.arange(spec.n_points), ids)
    good = np.flatnonzero(ok_e)
    if missing.size == 0 or good.size < 6:
        return pts, ids, obj, ok_e, outl, cut, 0
    H = fit_h(obj[good], pts[good])
    if H is None:
        return pts, ids, obj, ok_e, outl, cut, 0
    guess = apply_h(H, all_obj[missing])
    if good.size >= 8:
        sc = max(float(np.abs(all_obj).max()), 1e-9)

        def A(o):
            x, y = o[:, 0] / sc, o[:, 1] / sc
            return np.column_stack([np.ones(len(o)), x, y, x * x, x * y, y * y])

        coef, *_ = np.linalg.lstsq(A(obj[good]), pts[good], rcond=None)
        guess = A(all_obj[missing]) @ coef
    Q = circle_shape_matrices(H, all_obj[missing], 0.5 * spec.diameter_mm)
    semi = np.sqrt(1.0 / np.linalg.eigvalsh(Q))  # (K, 2): minor, major semi-axes
    inside = (guess[:, 0] > semi[:, 0]) & (guess[:, 0] < w - 1 - semi[:, 0]) & (guess[:, 1] > semi[:, 0]) & \
        (guess[:, 1] < h - 1 - semi[:, 0])
    if not np.any(inside):
        return pts, ids, obj, ok_e, outl, cut, 0
    missing, guess, Q, semi = missing[inside], guess[inside], Q[inside], semi[inside]
    new, ok_n, outl_n, qual = refine_circle_edges(gray, guess, Q, bright)
    x, y = outl_n[..., 0], outl_n[..., 1]
    with np.errstate(invalid="ignore"):
        area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    expect = np.pi * semi[:, 0] * semi[:, 1]
    # a whole disc: nearly every ray measured (a disc cut by an occluder or the frame border leaves
    # rays without an edge, filled in by the conic)
    with np.errstate(invalid="ignore"):
        ok_n &= (np.linalg.norm(new - guess, axis=1) < semi[:, 0] / 3.0 + 1.0) & (area > 0.6 * expect) & \
            (area < 1.6 * expect) & (qual[:, 0] >= 0.9) & (qual[:, 1] <= np.maximum(0.25, 0.01 * semi[:, 1]))
    if not np.any(ok_n):
        return pts, ids, obj, ok_e, outl, cut, 0
    ids2 = np.concatenate([ids, missing[ok_n]])
    order = np.argsort(ids2)
    cat = lambda a, b: np.concatenate([a, b])[order]
    pts2 = cat(pts, new[ok_n])
    return (pts2, ids2[order], all_obj[ids2[order]], cat(ok_e, np.ones(int(ok_n.sum()), bool)),
            cat(outl, outl_n[ok_n]), cat(cut, np.zeros(int(ok_n.sum()), bool)), int(ok_n.sum()))
