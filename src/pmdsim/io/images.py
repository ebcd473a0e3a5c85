"""Image files: 8/16-bit greyscale PNG and TIFF, read and written deterministically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import ImageSetError

__all__ = ["write_png", "read_image"]


def write_png(path: str | Path, image: np.ndarray, *, compress_level: int = 1) -> None:
    """Write an 8- or 16-bit greyscale PNG (H, W). Deterministic: no timestamps are embedded."""
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"write_png needs a (H, W) uint8 or uint16 image, got {img.shape} {img.dtype}")
    if img.dtype == np.uint8:
        pil = Image.fromarray(img, mode="L")
    else:
        pil = Image.fromarray(img.astype("<u2"))  # mode I;16 (the mode argument fails on Pillow ≥ 13)
    pil.save(path, format="PNG", compress_level=compress_level)


def read_image(path: str | Path) -> np.ndarray:
    """Read a greyscale 8- or 16-bit PNG or TIFF as (H, W) uint8/uint16.

    Raises
    ------
    ImageSetError
        If the file is missing, unreadable, not greyscale or of another bit depth.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageSetError(f"image file {str(p)!r} does not exist")
    try:
        with Image.open(p) as im:
            mode = im.mode
            arr = np.array(im)
    except Exception as e:  # PIL raises several types for broken files
        raise ImageSetError(f"cannot read image {str(p)!r}: {e}") from None
    if arr.ndim != 2 or mode not in ("L", "I;16", "I;16B", "I;16L", "I"):
        raise ImageSetError(
            f"image {str(p)!r} is not greyscale: not an 8- or 16-bit grey image (mode {mode}, shape {arr.shape}); "
            "palette, colour and 1-bit images are not fringe images"
        )
    if mode in ("I;16", "I;16B", "I;16L", "I") and arr.dtype != np.uint16:
        if arr.min() < 0 or arr.max() > 65535:
            raise ImageSetError(f"image {str(p)!r}: values outside the 16-bit range")
        arr = arr.astype(np.uint16)
    if arr.dtype == np.bool_:
        raise ImageSetError(f"image {str(p)!r} is a 1-bit image; 8- or 16-bit greyscale expected")
    if arr.dtype not in (np.uint8, np.uint16):
        raise ImageSetError(f"image {str(p)!r} has pixel type {arr.dtype}; 8- or 16-bit greyscale expected")
    return arr
