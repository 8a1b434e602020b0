"""The texture atlas: charts and packing with xatlas [3]_, and the texel centres inside its triangles.

References
----------
.. [3] Young J. et al., xatlas: mesh parameterisation and chart packing (github.com/jpcy/xatlas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .texture_mesh import check_mesh, local_origin

__all__ = ["Atlas", "Texels", "build_atlas", "rasterize_atlas"]


@dataclass
class Atlas:
    """An xatlas parameterisation: ``vmapping`` (N,) original vertex of each atlas vertex, ``faces`` (F, 3)
    atlas-vertex indices (same face order as the input), ``uv`` (N, 2) in [0, 1] with v measured from
    the TOP row of the texture (row = v · height), ``size`` (width, height) in texels."""

    vmapping: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    size: tuple[int, int]
    texel_size_m: float



def smallest_texel_m(vertices, faces, max_texture_px: int) -> float:
    """The smallest texel size (m) at which the mesh's area fits one ``max_texture_px`` square atlas (a lower bound:
    charts and padding need more)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    return float(np.sqrt(area) / int(max_texture_px))


def check_texel_size(vertices, faces, texel_size_m: float, max_texture_px: int, source: str) -> None:
    """Refuse a texel size at which the mesh's area alone needs more texels than one ``max_texture_px`` square atlas.

    Raises
    ------
    InvalidInputError
        naming ``source`` (the mesh file), the texel size, the texels it needs and the smallest size that fits.
    """
    lo = smallest_texel_m(vertices, faces, max_texture_px)
    if float(texel_size_m) < lo:
        need = (lo * int(max_texture_px) / float(texel_size_m)) ** 2
        raise InvalidInputError(f"--texel-size {texel_size_m:g} m: the {lo ** 2 * int(max_texture_px) ** 2:.4g} m^2 of "
                                f"{source} would need {need:.3g} texels, above one {max_texture_px} x {max_texture_px} "
                                f"atlas; expected a texel size of at least {lo:.3g} m")


def build_atlas(vertices, faces, texel_size_m: float, *, max_texture_px: int = 4096, padding: int = 2) -> Atlas:
    """Charts and packing with xatlas at ``texel_size_m``; coarsened until the atlas fits ``max_texture_px`` (from at
    least :func:`smallest_texel_m`: xatlas is never asked for an atlas that the mesh's area alone makes too large --
    it crashes the process on a texel size far below that)."""
    import xatlas

    V, F = check_mesh(vertices, faces)
    V32 = (V - local_origin(V)).astype(np.float32)  # xatlas works in float32: charts from local coordinates
    ts = max(float(texel_size_m), smallest_texel_m(V, F, max_texture_px))
    for _ in range(12):
        atlas = xatlas.Atlas()
        atlas.add_mesh(V32, F.astype(np.uint32))
        po = xatlas.PackOptions()
        po.texels_per_unit = 1.0 / ts
        po.padding = int(padding)
        po.bilinear = True
        po.blockAlign = False
        atlas.generate(xatlas.ChartOptions(), po)
        w, h = int(atlas.width), int(atlas.height)
        if max(w, h) <= max_texture_px and atlas.atlas_count == 1:
            vmap, idx, uv = atlas[0]
            idx = np.asarray(idx, np.int64)
            if len(idx) != len(F) or not np.array_equal(np.asarray(vmap, np.int64)[idx], F):
                raise InvalidInputError("xatlas changed the face order or topology; expected one atlas face per mesh face")
            return Atlas(np.asarray(vmap, np.int64), idx, np.asarray(uv, np.float64), (w, h), ts)
        ts *= max(1.25, max(w, h) / max_texture_px * 1.05)
    raise InvalidInputError(f"mesh too large for a {max_texture_px}-texel atlas even at {ts:.3g} m per texel")



@dataclass
class Texels:
    """Texel centres inside atlas triangles: ``rc`` (T, 2) row/col, ``face`` (T,), ``bary`` (T, 3), ``points`` (T, 3)."""

    rc: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    points: np.ndarray



def rasterize_atlas(atlas: Atlas, vertices, faces, *, chunk: int = 2_000_000) -> Texels:
    """Texel centres ``((col + 0.5)/W, (row + 0.5)/H)`` that fall inside each atlas triangle (vectorised).

    A texel on an edge shared by two triangles goes to the first; texels in the gutter belong to no face.
    """
    V, F = check_mesh(vertices, faces)
    W, H = atlas.size
    P = atlas.uv[atlas.faces] * np.array([W, H])  # (F, 3, 2) in texel units
    lo = np.floor(P.min(axis=1) - 0.5).astype(np.int64)
    hi = np.ceil(P.max(axis=1) - 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [W - 1, H - 1])
    nx = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    n = nx * ny
    out_f, out_rc, out_b = [], [], []
    starts = np.concatenate([[0], np.cumsum(n)])
    fi_all = np.arange(len(F))
    pos = 0
    while pos < len(F):
        end = int(np.searchsorted(starts, starts[pos] + chunk, side="right")) - 1
        end = max(end, pos + 1)
        fs = fi_all[pos:end]
        cnt = n[fs]
        f_rep = np.repeat(fs, cnt)
        local = np.arange(cnt.sum()) - np.repeat(starts[fs] - starts[pos], cnt)
        col = lo[f_rep, 0] + local % np.maximum(nx[f_rep], 1)
        row = lo[f_rep, 1] + local // np.maximum(nx[f_rep], 1)
        p = np.stack([col + 0.5, row + 0.5], axis=1)
        a, b, c = P[f_rep, 0], P[f_rep, 1], P[f_rep, 2]
        v0, v1, v2 = b - a, c - a, p - a
        den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
            l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
        l0 = 1 - l1 - l2
        eps = -1e-9
        inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps) & np.isfinite(l1)
        out_f.append(f_rep[inside])
        out_rc.append(np.stack([row[inside], col[inside]], axis=1))
        out_b.append(np.stack([l0[inside], l1[inside], l2[inside]], axis=1))
        pos = end
    face = np.concatenate(out_f) if out_f else np.zeros(0, np.int64)
    rc = np.concatenate(out_rc) if out_rc else np.zeros((0, 2), np.int64)
    bary = np.concatenate(out_b) if out_b else np.zeros((0, 3))
    key = rc[:, 0] * W + rc[:, 1]
    _, first = np.unique(key, return_index=True)
    first.sort()
    face, rc, bary = face[first], rc[first], np.clip(bary[first], 0, 1)
    bary /= bary.sum(axis=1, keepdims=True)
    pts = np.einsum("tj,tjk->tk", bary, V[F[face]])
    return Texels(rc, face, bary, pts)
