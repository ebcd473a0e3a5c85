"""Image files: 8/16-bit greyscale PNG and TIFF, read and written deterministically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import ImageSetError

__all__ = ["write_png", "read_image", "read_frame"]


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


def read_frame(path: Path, page: int | None, *, writable: bool = True) -> np.ndarray:
    """Read one greyscale frame: (H, W) uint8, uint16 or float32/float64.

    ``writable`` False: the array may be a read-only view of Pillow's pixel bytes (one copy
    fewer, for a caller that copies it into its own array: :func:`pmdsim.io.imageset.load_camera_stacks`).

    PNG and single-page TIFF are read whole; a multi-page TIFF needs ``page`` (0-based) and a
    page index beyond the file's pages is an error. Float TIFF (mode ``F``) is returned as
    float32.

    Raises
    ------
    ImageSetError
        Missing or unreadable file, colour/palette image, a multi-page file without ``page``
        or a page out of range.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageSetError(f"image file {str(p)!r} does not exist")
    try:
        with Image.open(p) as im:
            n = int(getattr(im, "n_frames", 1))
            if page is None and n > 1:
                raise ImageSetError(
                    f"image {str(p)!r} is a multi-page file with {n} pages; give the entry a 'page' "
                    f"(0 … {n - 1}) — pmdsim does not read page 0 of a stack silently")
            k = 0 if page is None else page
            if k >= n:
                raise ImageSetError(f"image {str(p)!r}: 'page' = {k} is out of range (the file has {n} page(s))")
            im.seek(k)
            mode = im.mode
            arr = np.array(im) if writable else np.asarray(im)
    except ImageSetError:
        raise
    except Exception as e:  # PIL raises several types for broken files
        raise ImageSetError(f"cannot read image {str(p)!r}: {e}") from None
    if arr.ndim != 2 or mode not in ("L", "I;16", "I;16B", "I;16L", "I", "F"):
        raise ImageSetError(
            f"image {str(p)!r} is not greyscale (mode {mode}, shape {arr.shape}); 8/16-bit or float greyscale "
            "expected — palette, colour and 1-bit images are not fringe images")
    if mode == "F":
        return arr.astype(np.float32, copy=False)
    if mode in ("I;16", "I;16B", "I;16L", "I") and arr.dtype != np.uint16:
        if arr.min() < 0 or arr.max() > 65535:
            raise ImageSetError(f"image {str(p)!r}: values outside the 16-bit range")
        arr = arr.astype(np.uint16)
    if arr.dtype not in (np.uint8, np.uint16):
        raise ImageSetError(f"image {str(p)!r} has pixel type {arr.dtype}; 8/16-bit or float greyscale expected")
    return arr
