"""Target detection on thermal images: the public entry points.

Targets (described once, in millimetres, by :mod:`thermogrammetry.targets`; ``ChessboardSpec`` is
:class:`~thermogrammetry.targets.ChessboardTarget` and so on) and their detectors:

========================  ===================================  =========================================
spec                      detector                             module
========================  ===================================  =========================================
:class:`ChessboardSpec`   :func:`detect_chessboard`            :mod:`.detect_chessboard`
:class:`CircleGridSpec`   :func:`detect_circle_grid`           :mod:`.detect_circles`
:class:`CodedCheckerboardSpec`  :func:`detect_coded_checkerboard`  :mod:`.detect_coded`
========================  ===================================  =========================================

All take an image array (uint8, uint16 or float; contrast normalisation is done inside) and return
a :class:`Detection`: ``found``, ``points_px`` (N, 2) in OpenCV pixel convention ((0, 0) = centre of
the top-left pixel), ``object_ids`` (N,) indexing ``spec.object_points()`` (millimetres, z = 0),
and a ``reason``. A target that is not found is a value, never an exception; bad input (wrong dtype
or shape, empty or constant image, wrong spec type) raises
:class:`~thermogrammetry.errors.InvalidInputError`.

No function here reads files: :mod:`.detect_io` has a thin reader for the command line.

Example
-------
>>> spec = ChessboardSpec(inner_columns=6, inner_rows=5, square_mm=100.0)     # doctest: +SKIP
>>> dets = detect_many(images, spec, image_ids=names)                          # doctest: +SKIP
>>> [(d.image_id, d.found, d.reason) for d in dets]                            # doctest: +SKIP
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

from ..errors import ConfigError, InvalidInputError
from .detect_chessboard import canonical_grid_order, detect_chessboard, refine_corners
from .detect_circles import (
    detect_circle_grid,
    ellipse_centre_bias,
    refine_circle_centres,
)
from .detect_coded import detect_coded_checkerboard, detect_marker
from .detect_common import (
    ChessboardSpec,
    CircleGridSpec,
    CodedCheckerboardSpec,
    Detection,
    clahe_u8,
    normalize_to_u8,
    to_gray_float,
)

__all__ = [
    "Detection",
    "ChessboardSpec",
    "CircleGridSpec",
    "CodedCheckerboardSpec",
    "detect",
    "detect_many",
    "detect_chessboard",
    "detect_circle_grid",
    "detect_coded_checkerboard",
    "detect_marker",
    "canonical_grid_order",
    "refine_corners",
    "refine_circle_centres",
    "ellipse_centre_bias",
    "to_gray_float",
    "normalize_to_u8",
    "clahe_u8",
]


def detect(image, spec, image_id: str = "", **options) -> Detection:
    """Detect the target described by ``spec`` in one image (dispatch on the spec's type).

    ``options`` are passed to the detector (see :func:`detect_chessboard`,
    :func:`detect_circle_grid`, :func:`detect_coded_checkerboard`).
    """
    inner = getattr(spec, "target", None)  # metre-unit views of thermogrammetry.synthetic.targets
    if not isinstance(spec, (ChessboardSpec, CircleGridSpec, CodedCheckerboardSpec)) and inner is not None:
        spec = inner
    if isinstance(spec, ChessboardSpec):
        return detect_chessboard(image, spec, image_id, **options)
    if isinstance(spec, CircleGridSpec):
        return detect_circle_grid(image, spec, image_id, **options)
    if isinstance(spec, CodedCheckerboardSpec):
        return detect_coded_checkerboard(image, spec, image_id, **options)
    raise ConfigError(
        f"spec: expected ChessboardSpec, CircleGridSpec or CodedCheckerboardSpec (the millimetre descriptions of "
        f"thermogrammetry.targets), got {type(spec).__name__}"
    )


def detect_many(images, spec, image_ids: Iterable[str] | None = None, *, on_bad_image: str = "raise",
                progress: Callable[[int, Detection], None] | None = None, **options) -> list[Detection]:
    """Detect the target in a batch of images; one :class:`Detection` per image, in input order.

    Parameters
    ----------
    images : sequence of arrays, or mapping image_id -> array
        The images (uint8 / uint16 / float, (H, W) or (H, W, C)). Arrays only -- no paths.
    spec : ChessboardSpec | CircleGridSpec | CodedCheckerboardSpec
    image_ids : iterable of str, optional
        Names carried into the results (default: the mapping's keys, or "0", "1", ...).
    on_bad_image : {"raise", "record"}
        An image that is not a valid image (wrong dtype/shape, empty, constant) raises
        (``"raise"``), or becomes a not-found Detection whose reason carries the error (``"record"``)
        -- a blank frame in a calibration sequence need not stop the run.
    progress : callable(index, detection), optional
        Called after each image (for progress bars).
    **options
        Passed to the detector.

    Returns
    -------
    list of Detection, same length and order as ``images``.
    """
    if on_bad_image not in ("raise", "record"):
        raise ConfigError(f"on_bad_image: expected 'raise' or 'record', got {on_bad_image!r}")
    if isinstance(images, Mapping):
        ids = list(images.keys()) if image_ids is None else [str(i) for i in image_ids]
        arrays = list(images.values())
    else:
        arrays = list(images)
        ids = [str(i) for i in range(len(arrays))] if image_ids is None else [str(i) for i in image_ids]
    if len(ids) != len(arrays):
        raise InvalidInputError(f"image_ids: got {len(ids)} ids for {len(arrays)} images; expected one id per image")
    out: list[Detection] = []
    for k, (iid, img) in enumerate(zip(ids, arrays)):
        try:
            d = detect(img, spec, iid, **options)
        except ConfigError:
            raise
        except InvalidInputError as exc:
            if on_bad_image == "raise":
                raise
            d = Detection.failure(iid, f"bad image: {exc}")
        out.append(d)
        if progress is not None:
            progress(k, d)
    return out
