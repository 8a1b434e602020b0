"""Thin image reader for target detection (the command line's edge; algorithms take arrays).

Reads 8-bit JPEG/PNG, 16-bit PNG/TIFF and float TIFF as they are (no scaling): the detectors
normalise contrast themselves. Radiometric formats (R-JPEG, FFF, SEQ) belong to
:mod:`thermogrammetry.io` readers, not here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import CorruptFileError, DataFileError, UnsupportedFormatError

__all__ = ["read_image", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm")


def read_image(path) -> np.ndarray:
    """Read one image file into an array, keeping its bit depth.

    Returns
    -------
    ndarray (H, W) or (H, W, C): uint8, uint16 or float32 (TIFF with float samples).

    Raises
    ------
    DataFileError
        The file does not exist.
    UnsupportedFormatError
        The suffix is not one of :data:`IMAGE_SUFFIXES`.
    CorruptFileError
        The file cannot be decoded.
    """
    p = Path(path)
    if not p.is_file():
        raise DataFileError(f"{p}: no such image file")
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise UnsupportedFormatError(f"{p}: unsupported image type {suffix!r}; expected one of {', '.join(IMAGE_SUFFIXES)}")
    from ..errors import ImageTooLargeError
    from ..io.limits import check_image_size

    _check_declared_size(p, check_image_size)
    if suffix in (".tif", ".tiff"):
        try:
            import tifffile

            arr = tifffile.imread(str(p))
        except Exception as exc:
            raise CorruptFileError(f"{p}: cannot read TIFF: {exc}") from None
        arr = np.asarray(arr)
        if arr.size == 0 or arr.ndim < 2:
            raise CorruptFileError(f"{p}: the TIFF holds no image data (got an array of shape {arr.shape})")
        if arr.ndim == 3 and arr.shape[0] in (1, 3, 4) and arr.shape[2] not in (1, 3, 4):
            arr = np.moveaxis(arr, 0, -1)  # planar (C, H, W) → (H, W, C)
        return arr
    data = np.fromfile(str(p), dtype=np.uint8)
    try:
        arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except (cv2.error, MemoryError) as exc:
        raise ImageTooLargeError(f"{p}: the image cannot be decoded ({type(exc).__name__}: "
                                 f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else 'out of memory'})") from None
    if arr is None:
        raise CorruptFileError(f"{p}: cannot decode the image (empty or damaged {suffix} file)")
    return arr


def _check_declared_size(p, check) -> None:
    """Refuse an image whose header declares more pixels than the size cap, before decoding it
    (:mod:`thermogrammetry.io.limits`).  Headers Pillow cannot read are left to the decoder."""
    import warnings

    from PIL import Image

    from ..errors import ImageTooLargeError

    from ..io.limits import MAX_PIXELS_ENV, max_pixels

    cap = max_pixels()
    old = Image.MAX_IMAGE_PIXELS
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Image.MAX_IMAGE_PIXELS = max(cap // 2, 1)  # Pillow refuses beyond twice this, from the header alone
            with Image.open(p) as im:  # reads the header only
                w, h = im.size
    except Image.DecompressionBombError as exc:
        raise ImageTooLargeError(f"{p}: declares an image above the size cap of {cap / 1e6:.1f} Mpixel ({exc}); "
                                 f"raise the cap with {MAX_PIXELS_ENV}=N if the image is genuine") from None
    except Exception:
        return
    finally:
        Image.MAX_IMAGE_PIXELS = old
    check(w, h, str(p))
