"""Size cap on decoded images, checked from the file's header *before* pixel memory is allocated.

A damaged or hostile file can declare any size (a 498-byte TIFF may claim 80 x 4,000,000 pixels); decoding
it would allocate gigabytes or raise ``MemoryError``.  Every reader and image loader calls
:func:`check_image_size` with the declared size first.

The cap is a number of pixels per image (all bands of one pixel count once).  Default
:data:`DEFAULT_MAX_PIXELS` = 2**28 (268 Mpixel, 16384 x 16384), far above any thermal frame (<= 1.3 Mpixel)
or survey RGB frame (<= 150 Mpixel).  Change it with the environment variable ``THERMOGRAMMETRY_MAX_PIXELS``
(read at each check) or :func:`set_max_pixels`.
"""

from __future__ import annotations

import os

from ..errors import ConfigError, ImageTooLargeError

__all__ = ["DEFAULT_MAX_PIXELS", "MAX_PIXELS_ENV", "max_pixels", "set_max_pixels", "check_image_size",
           "MAX_CELLS_ENV", "default_max_cells", "max_cells", "check_cells"]

DEFAULT_MAX_PIXELS = 1 << 28
MAX_PIXELS_ENV = "THERMOGRAMMETRY_MAX_PIXELS"
_override: int | None = None


def set_max_pixels(n: int | None) -> None:
    """Set the cap for this process (``None``: back to the environment variable or the default)."""
    global _override
    if n is not None and (int(n) != n or int(n) < 1):
        raise ConfigError(f"max_pixels={n!r}: expected a positive integer")
    _override = None if n is None else int(n)


def max_pixels() -> int:
    """The current cap in pixels (see module docstring)."""
    if _override is not None:
        return _override
    env = os.environ.get(MAX_PIXELS_ENV)
    if env:
        try:
            v = int(float(env))
        except ValueError:
            raise ConfigError(f"${MAX_PIXELS_ENV}={env!r}: expected a positive integer number of pixels") from None
        if v < 1:
            raise ConfigError(f"${MAX_PIXELS_ENV}={env!r}: expected a positive integer number of pixels")
        return v
    return DEFAULT_MAX_PIXELS


def check_image_size(width: int, height: int, where: str, *, frames: int = 1) -> None:
    """Refuse an image whose declared ``width x height`` (x ``frames``) exceeds :func:`max_pixels`.

    Raises
    ------
    ImageTooLargeError
        Naming ``where`` (the file), the declared size and the cap.
    """
    w, h, f = int(width), int(height), max(int(frames), 1)
    n = w * h * f
    cap = max_pixels()
    if w < 0 or h < 0 or n > cap:
        raise ImageTooLargeError(
            f"{where}: declares a {w}x{h}{f' x {f} frames' if f > 1 else ''} image ({n / 1e6:.1f} Mpixel), above the "
            f"size cap of {cap / 1e6:.1f} Mpixel; a damaged header or not a real frame (raise the cap with "
            f"{MAX_PIXELS_ENV}=N if the image is genuine)"
        )


# ----------------------------------------------------------------------------------------------- raster cells
MAX_CELLS_ENV = "THERMOGRAMMETRY_MAX_CELLS"
#: bytes of memory per raster cell the default cap allows for (a DSM read whole as float64 with its mask and one
#: copy, or the ortho's seven rasters' temporaries on disk)
BYTES_PER_CELL = 64


def default_max_cells() -> int:
    """The default cap on the cells of one raster: this machine's memory / :data:`BYTES_PER_CELL`, at least 2**24
    (16.8 M cells); 360 M cells on a 23 GB machine."""
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        mem = 8 << 30
    return max(1 << 24, int(mem) // BYTES_PER_CELL)


def max_cells(option: int | None = None) -> int:
    """The cap in cells: ``option`` (a verb's ``--max-cells``) if given, else ``$THERMOGRAMMETRY_MAX_CELLS``, else
    :func:`default_max_cells`."""
    if option is not None:
        if isinstance(option, bool) or int(option) != option or int(option) < 1:
            raise ConfigError(f"--max-cells {option!r}: expected a positive integer number of raster cells")
        return int(option)
    env = os.environ.get(MAX_CELLS_ENV)
    if env:
        try:
            v = int(float(env))
        except ValueError:
            v = 0
        if v < 1:
            raise ConfigError(f"${MAX_CELLS_ENV}={env!r}: expected a positive integer number of raster cells")
        return v
    return default_max_cells()


def check_cells(width: int, height: int, where: str, *, cap: int | None = None, what: str = "raster") -> None:
    """Refuse a raster of ``width x height`` cells above :func:`max_cells` (``cap`` = the verb's ``--max-cells``).

    Raises
    ------
    ImageTooLargeError
        Naming ``where``, the size, the cap and how to raise it.
    """
    limit = max_cells(cap)
    w, h = int(width), int(height)
    if w * h > limit:
        raise ImageTooLargeError(
            f"{where}: a {what} of {w} x {h} = {w * h:,} cells, above the cap of {limit:,} cells (sized for this "
            f"machine's memory); raise it with --max-cells N (or {MAX_CELLS_ENV}=N) if that is intended")
