"""Ring-coded marks on a mask circle grid (seed 003: 28 circles with 4 coded targets).

Seed 003 calibrates its UAV thermal camera on "a grid of 28 regularly sized circles with 4 coded
targets cut out of a thin non-conductor material", 44 x 24 cm, circles 20 mm in diameter at 50 mm
spacing, held in front of a powered-on monitor (the cut-outs are hot, the mask is cold). The paper
does not draw its codes; this module is the project's design of such a mark, one that can be cut out
of a mask.

Design of a mark (binding for renderer and detector)
----------------------------------------------------
* A mark sits **on a grid circle**: its central disc *is* that circle (so the grid keeps its
  ``columns x rows`` points and the disc is measured like every other circle).
* Around the disc, a concentric **ring of** ``code_bits`` **equal sectors** (default 12, 30° each)
  between the radii ``ring_inner_mm`` and ``ring_outer_mm`` (default 1.5 and 2.5 disc radii: 15 and
  25 mm for seed 003). Sector ``k`` is centred on the target-frame direction at angle ``k · 360° /
  code_bits`` from +x towards +y (the frame of :class:`~thermogrammetry.targets.CircleGridTarget`:
  x right along a row, y down; clockwise on the artwork seen from the front). Bit ``k`` of the code
  = 1: sector ``k`` is cut out (it shows the emitter like the disc), 0: it stays mask.
* Every sector boundary carries a **bridge** of mask of width ``bridge_mm`` (parallel-sided, default
  a quarter of the disc radius): the mask annulus between disc and ring stays attached to the rest of
  the mask whatever the code, so each 1-bit is a separate arc cut-out.
* The annulus between the disc and the ring (gap, width ≥ 0.2 disc radius) and the annulus outside
  the ring (at least one disc radius up to the nearest neighbouring disc) are plain mask: a
  detector reads the cold level there and refuses a reading that does not show it.

Code set
--------
:func:`ring_codes` lists the valid codes for ``code_bits`` bits: binary necklaces that are

* **aperiodic** (the 12 rotations are distinct: the reading fixes the mark's in-plane rotation, which
  tells the target's x axis in the image), with at least 2 bits of difference between a code and any
  of its own non-trivial rotations;
* of **weight 3 .. code_bits - 3** (at least 3 bits from an uncoded disc, all zeros, and from a full
  ring);
* at a cyclic Hamming distance of at least 3 from every other code under every rotation (a reading
  with one or two wrong bits matches no code, or its own, never another one: the detector decodes
  exact matches only).

The set is built greedily in increasing order of each necklace's smallest rotation (read as a
binary number, bit 0 most significant), so it is deterministic; for 12 bits it holds
``len(ring_codes(12))`` = 16 codes (code id = index; 4 marks per target need 4). Rotation invariance: the detector reads the
ring from an arbitrary start and finds the code and its rotation among the rotations of the set.

References
----------
.. [1] Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from
   aerial thermal imagery. ISPRS Arch. XL-1/W5, 401-405 (seed 003, section 3.2: mask of 28 circles
   and 4 coded targets, 20 mm circles at 50 mm).
.. [2] Schneider, C.-T. (1991). Objektgestützte Mehrbildzuordnung. PhD thesis, TU Dresden (ring
   codes around a central disc, the family used by AICON/GOM-style coded targets).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import ConfigError
from . import BOARD, FEATURE, CircleGridTarget, _in_box, _int, _length

__all__ = ["ring_codes", "code_bits_of", "match_ring_code", "CodedCircleGridTarget", "SEED003_MARKS",
           "seed003_coded_grid"]

#: seed-003-like layout on a 7 x 4 grid: (column, row, code id); one mark in each 3 x 2 corner block
#: of the grid, no two marks neighbours
SEED003_MARKS = ((1, 1, 0), (5, 1, 1), (2, 2, 2), (4, 2, 3))


def _rotations(v: int, n: int) -> list[int]:
    mask = (1 << n) - 1
    return [((v << k) | (v >> (n - k))) & mask for k in range(n)]


@lru_cache(maxsize=8)
def _codes(n_bits: int, min_distance: int) -> tuple[int, ...]:
    n = n_bits
    pop = np.array([bin(i).count("1") for i in range(1 << n)], dtype=np.int64)
    accepted: list[int] = []
    acc_rot = np.zeros(0, dtype=np.int64)  # every rotation of every accepted code
    seen = set()
    for v in range(1 << n):
        rots = _rotations(v, n)
        canon = min(rots)
        if canon in seen:
            continue
        seen.add(canon)
        if canon != v:
            continue
        w = pop[v]
        if w < 3 or w > n - 3 or len(set(rots)) != n:
            continue
        if min(pop[v ^ r] for r in rots[1:]) < 2:
            continue
        if acc_rot.size and pop[np.bitwise_xor(acc_rot, v)].min() < min_distance:
            continue
        accepted.append(v)
        acc_rot = np.concatenate([acc_rot, np.array(rots, dtype=np.int64)])
    return tuple(accepted)


def ring_codes(code_bits: int = 12, min_distance: int = 3) -> np.ndarray:
    """The valid ring codes, (K, code_bits) uint8, row = code id, column k = sector k (see the module
    docstring for the rules: aperiodic, weight 3 .. code_bits - 3, cyclic distance >= ``min_distance``).

    Parameters
    ----------
    code_bits : int
        Sectors of the ring (8 .. 16).
    min_distance : int
        Smallest Hamming distance between two codes under any rotation.
    """
    n = _int("ring_codes", "code_bits", code_bits, 8)
    if n > 16:
        raise ConfigError(f"ring_codes.code_bits={code_bits!r}: expected 8 .. 16 sectors")
    d = _int("ring_codes", "min_distance", min_distance, 1)
    vals = _codes(n, d)
    return np.array([[(v >> (n - 1 - k)) & 1 for k in range(n)] for v in vals], dtype=np.uint8).reshape(-1, n)


def code_bits_of(code_id: int, code_bits: int = 12) -> np.ndarray:
    """(code_bits,) uint8 bits of code ``code_id`` (sector k = element k)."""
    codes = ring_codes(code_bits)
    i = _int("code_bits_of", "code_id", code_id, 0)
    if i >= len(codes):
        raise ConfigError(f"code id {code_id!r}: expected 0 <= id < {len(codes)} (the {code_bits}-bit ring codes)")
    return codes[i]


@lru_cache(maxsize=8)
def _lookup(code_bits: int) -> dict:
    codes = ring_codes(code_bits)
    out = {}
    for cid, c in enumerate(codes):
        for s in range(code_bits):
            # a reading that starts s sectors after the code's sector 0: reading[k] = code[(k + s) % n]
            out[tuple(np.roll(c, -s).tolist())] = (cid, s)
    return out


def match_ring_code(bits, code_bits: int = 12):
    """Code id and rotation of a reading, or None.

    Parameters
    ----------
    bits : sequence of 0/1, length ``code_bits``
        Sector values read from an arbitrary start sector.

    Returns
    -------
    (code_id, shift) or None
        ``bits[k] == code[(k + shift) % code_bits]``: the reading's sector 0 is the code's sector
        ``shift``. None when the reading equals no rotation of any code (exact matches only).
    """
    key = tuple(int(b) for b in np.asarray(bits).ravel())
    if len(key) != code_bits:
        raise ConfigError(f"match_ring_code: expected {code_bits} bits, got {len(key)}")
    return _lookup(int(code_bits)).get(key)


@dataclass(frozen=True)
class CodedCircleGridTarget(CircleGridTarget):
    """A mask circle grid some of whose circles carry a ring code (module docstring: the design).

    Parameters
    ----------
    columns, rows, spacing_mm, asymmetric, diameter_mm, margin_mm
        As :class:`~thermogrammetry.targets.CircleGridTarget`; ``diameter_mm`` is required when there
        are marks (the ring is sized from it).
    marks : tuple of (column, row, code_id)
        Grid position of each coded circle (column 0 .. columns-1 along a row, row 0 .. rows-1; the
        circle's object point is ``row · columns + column``) and its code id in
        :func:`ring_codes`. Positions and ids are unique; two marks' rings may not touch (centres at
        least ``2 · ring_outer_mm + d/2`` apart: no two marks on neighbouring circles of a grid with
        the default ring).
    code_bits : int
        Sectors of every ring (default 12).
    ring_inner_mm, ring_outer_mm : float or None
        Ring radii (default 1.5 and 2.5 disc radii); ``ring_inner_mm >= 1.2 · d/2`` (a mask gap a
        detector can read), ``ring_outer_mm <= nearest-neighbour distance - d`` (one disc radius of
        mask between the ring and the neighbouring discs).
    bridge_mm : float or None
        Width of the mask bridge on every sector boundary (default d/8, a quarter of the radius);
        at most half a sector's arc at the inner radius.

    Notes
    -----
    The grid's object points, their order and the frame are those of
    :class:`~thermogrammetry.targets.CircleGridTarget`. ``classify`` adds the cut-out sectors as
    FEATURE.

    References
    ----------
    Khodaei et al. (2015), seed 003, section 3.2 (28 circles, 4 coded targets, 20 mm at 50 mm).
    """

    marks: tuple = ()
    code_bits: int = 12
    ring_inner_mm: float | None = None
    ring_outer_mm: float | None = None
    bridge_mm: float | None = None

    def __post_init__(self):
        super().__post_init__()
        n = type(self).__name__
        nb = _int(n, "code_bits", self.code_bits, 8)
        if nb > 16:
            raise ConfigError(f"{n}.code_bits={nb}: expected 8 .. 16 sectors")
        object.__setattr__(self, "code_bits", nb)
        n_codes = len(ring_codes(nb))
        try:
            raw = [tuple(m) for m in (self.marks or ())]
        except TypeError:
            raise ConfigError(f"{n}.marks={self.marks!r}: expected a sequence of (column, row, code_id)") from None
        marks = []
        for m in raw:
            if len(m) != 3:
                raise ConfigError(f"{n}.marks: entry {m!r}: expected (column, row, code_id)")
            c = _int(n, "marks column", m[0], 0)
            r = _int(n, "marks row", m[1], 0)
            i = _int(n, "marks code_id", m[2], 0)
            if c >= self.columns or r >= self.rows:
                raise ConfigError(f"{n}.marks: position (column {c}, row {r}) outside the {self.columns}x{self.rows} "
                                  f"grid; expected column 0..{self.columns - 1}, row 0..{self.rows - 1}")
            if i >= n_codes:
                raise ConfigError(f"{n}.marks: code id {i} at (column {c}, row {r}); expected 0 <= id < {n_codes} "
                                  f"(the {nb}-bit ring codes)")
            marks.append((c, r, i))
        pos = [(c, r) for c, r, _ in marks]
        if len(set(pos)) != len(pos):
            raise ConfigError(f"{n}.marks={tuple(marks)}: two marks on one circle; expected distinct positions")
        ids = [i for *_, i in marks]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"{n}.marks={tuple(marks)}: a code id used twice; expected distinct ids")
        object.__setattr__(self, "marks", tuple(marks))
        if not marks:
            for f in ("ring_inner_mm", "ring_outer_mm", "bridge_mm"):
                v = getattr(self, f)
                if v is not None:
                    object.__setattr__(self, f, _length(n, f, v))
            return
        d = self._need_diameter()
        r0 = 0.5 * d
        ri = 1.5 * r0 if self.ring_inner_mm is None else _length(n, "ring_inner_mm", self.ring_inner_mm)
        ro = 2.5 * r0 if self.ring_outer_mm is None else _length(n, "ring_outer_mm", self.ring_outer_mm)
        br = 0.25 * r0 if self.bridge_mm is None else _length(n, "bridge_mm", self.bridge_mm)
        if ri < 1.2 * r0:
            raise ConfigError(f"{n}.ring_inner_mm={ri:.6g}: expected >= 1.2 disc radii ({1.2 * r0:.6g} mm; the mask "
                              "gap between disc and ring must be readable)")
        if ro <= ri + 0.2 * r0:
            raise ConfigError(f"{n}.ring_outer_mm={ro:.6g}: expected > ring_inner_mm + 0.2 disc radii "
                              f"({ri + 0.2 * r0:.6g} mm)")
        nn = self.nearest_neighbour_mm
        if ro > nn - d + 1e-9:
            raise ConfigError(f"{n}.ring_outer_mm={ro:.6g}: expected <= nearest-neighbour distance - diameter "
                              f"({nn - d:.6g} mm: one disc radius of mask between a ring and the next disc)")
        if br >= np.pi * ri / nb:
            raise ConfigError(f"{n}.bridge_mm={br:.6g}: expected < half a sector's arc at the inner radius "
                              f"({np.pi * ri / nb:.6g} mm)")
        object.__setattr__(self, "ring_inner_mm", ri)
        object.__setattr__(self, "ring_outer_mm", ro)
        object.__setattr__(self, "bridge_mm", br)
        c = self.mark_centres_mm()
        need = 2 * ro + r0
        for a in range(len(c)):
            for b in range(a + 1, len(c)):
                if np.hypot(*(c[a] - c[b])) < need - 1e-9:
                    raise ConfigError(f"{n}.marks: marks at (column {marks[a][0]}, row {marks[a][1]}) and (column "
                                      f"{marks[b][0]}, row {marks[b][1]}) are {np.hypot(*(c[a] - c[b])):.6g} mm apart; "
                                      f"expected >= {need:.6g} mm (2 x ring_outer_mm + a disc radius)")

    # ------------------------------------------------------------------------------------------
    @classmethod
    def seed003(cls, **overrides) -> "CodedCircleGridTarget":
        """The seed-003-like mask: 7 x 4 circles of 20 mm at 50 mm, 45 mm border, marks
        :data:`SEED003_MARKS` (seed 003's 44 x 24 cm mask has 70 mm side borders and 45 mm top and
        bottom; one ``margin_mm`` describes the border here). ``overrides`` replace any field."""
        kw = dict(columns=7, rows=4, spacing_mm=50.0, diameter_mm=20.0, margin_mm=45.0, marks=SEED003_MARKS)
        kw.update(overrides)
        return cls(**kw)

    def plain(self) -> CircleGridTarget:
        """The same grid without marks (a :class:`CircleGridTarget`)."""
        return CircleGridTarget(self.columns, self.rows, self.spacing_mm, asymmetric=self.asymmetric,
                                diameter_mm=self.diameter_mm, margin_mm=self.margin_mm)

    @property
    def mark_point_ids(self) -> np.ndarray:
        """(M,) int64 object-point index (``row · columns + column``) of each mark, in ``marks`` order."""
        return np.array([r * self.columns + c for c, r, _ in self.marks], dtype=np.int64)

    @property
    def mark_code_ids(self) -> np.ndarray:
        """(M,) int64 code id of each mark, in ``marks`` order."""
        return np.array([i for *_, i in self.marks], dtype=np.int64)

    def mark_centres_mm(self) -> np.ndarray:
        """(M, 2) float64 mark (= disc) centres in the target plane, mm."""
        if not self.marks:
            return np.zeros((0, 2))
        return self.object_points()[self.mark_point_ids, :2]

    def point_of_code(self, code_id: int) -> int | None:
        """Object-point index of the mark with ``code_id``, None when no mark carries it."""
        for (c, r, i) in self.marks:
            if i == int(code_id):
                return r * self.columns + c
        return None

    def ring_mask(self, x_mm: np.ndarray, y_mm: np.ndarray, centres_mm: np.ndarray | None = None) -> np.ndarray:
        """True where target-plane points (mm) fall in a cut-out ring sector (bridges excluded).

        Parameters
        ----------
        x_mm, y_mm : ndarray, any shape
        centres_mm : (M, 2) ring centres, mm (default :meth:`mark_centres_mm`; a renderer moves them
            with displaced discs).
        """
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        out = np.zeros(x.shape, dtype=bool)
        if not self.marks:
            return out
        cen = self.mark_centres_mm() if centres_mm is None else np.asarray(centres_mm, np.float64)
        n = self.code_bits
        w = 2 * np.pi / n
        ri, ro, hb = self.ring_inner_mm, self.ring_outer_mm, 0.5 * self.bridge_mm
        xb, yb = np.broadcast_arrays(x, y)
        xf, yf = xb.ravel(), yb.ravel()
        flat = out.reshape(-1)
        # each ring is evaluated on the points whose x lies within its outer radius (points sorted by x once);
        # every other point is outside its band
        order = np.argsort(xf, kind="stable")
        xs = xf[order]
        with np.errstate(invalid="ignore"):
            for (cx, cy), cid in zip(cen, self.mark_code_ids):
                bits = code_bits_of(int(cid), n)
                near = order[np.searchsorted(xs, cx - ro, side="left"):np.searchsorted(xs, cx + ro, side="right")]
                dx, dy = xf[near] - cx, yf[near] - cy
                rho = np.hypot(dx, dy)
                band = (rho >= ri) & (rho <= ro)
                if not np.any(band):
                    continue
                near, dx, dy, rho = near[band], dx[band], dy[band], rho[band]
                phi = np.mod(np.arctan2(dy, dx), 2 * np.pi)
                k = np.mod(np.rint(phi / w), n).astype(np.intp)  # sector centred on k·w
                # distance to the nearer sector boundary ray (at (k ± 1/2)·w): bridge where < bridge/2
                off = np.abs(phi - k * w)
                off = np.minimum(off, 2 * np.pi - off)  # angle from the sector centre, 0 .. w/2
                dist = rho * np.sin(np.clip(0.5 * w - off, 0.0, None))
                flat[near] |= (bits[k] == 1) & (dist >= hb)
        return out

    def classify(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Part label (SURROUND=0, BOARD=1 mask, FEATURE=2 circle or cut-out ring sector), int8."""
        lab = super().classify(x_mm, y_mm)
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        ring = self.ring_mask(x, y) & _in_box(x, y, self.extent_mm()) & (lab == BOARD)
        lab[ring & np.isfinite(x) & np.isfinite(y)] = FEATURE
        return lab

    def mark_outline_points(self, n: int = 32) -> np.ndarray:
        """(M·n, 3) mm: points on every mark's outer ring radius (visibility checks of whole marks)."""
        c = self.mark_centres_mm()
        a = 2 * np.pi * np.arange(n) / n
        rim = np.stack([self.ring_outer_mm * np.cos(a), self.ring_outer_mm * np.sin(a)], axis=1)
        p = (c[:, None, :] + rim[None]).reshape(-1, 2)
        return np.column_stack([p, np.zeros(len(p))])


def seed003_coded_grid(**overrides) -> CodedCircleGridTarget:
    """:meth:`CodedCircleGridTarget.seed003` (7 x 4, 20 mm circles at 50 mm, 4 ring-coded marks)."""
    return CodedCircleGridTarget.seed003(**overrides)
