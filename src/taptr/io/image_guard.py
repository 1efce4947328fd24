"""Image headers checked before decoding: decompression bombs become one-line errors.

A few kilobytes of PNG can declare a 100,000 × 100,000 image. Every reader of png/jpg
frames (image folders, Kubric frames, TAP-Vid's encoded frames) opens images through
`open_image`, which reads the header only and refuses images above the ``image_pixels``
limit of `taptr.io.limits` before anything is decoded. PIL's own decompression-bomb guard is
turned into the same one-line error.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from collections.abc import Iterator

import numpy as np
from PIL import Image, UnidentifiedImageError

from taptr.io import limits

_PIL_ERRORS = (UnidentifiedImageError, OSError, ValueError, SyntaxError, TypeError, EOFError)


@contextlib.contextmanager
def open_image(source: str | os.PathLike[str] | bytes, label: str) -> Iterator[Image.Image]:
    """Opens an image lazily (header only), refusing it above the ``image_pixels`` limit.

    Args:
        source: an image file or its encoded bytes.
        label: names the image in messages (a path, or a file and frame).

    Raises:
        ValueError: PIL cannot read the header (the message says "not a readable image"),
            or the image declares more pixels than the limit allows (`taptr.io.limits.LimitError`).
    """
    allowed = limits.limit("image_pixels")
    if Image.MAX_IMAGE_PIXELS is not None and allowed > Image.MAX_IMAGE_PIXELS:
        # the user raised the limit: PIL's own guard (errors above twice it) must follow
        Image.MAX_IMAGE_PIXELS = allowed
    try:
        with warnings.catch_warnings():
            # the pixel limit below decides; PIL's warning would only repeat it
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(source) if isinstance(source, bytes) else source)
    except Image.DecompressionBombError as error:
        raise _bomb(label, error) from None
    except _PIL_ERRORS as error:
        raise ValueError(f"{label}: not a readable image ({error})") from None
    with image:
        width, height = image.size
        limits.check("image_pixels", width * height, f"{label}: a {width}x{height} image")
        yield image


def image_size(path: str | os.PathLike[str], label: str) -> tuple[int, int] | None:
    """(height, width) declared by an image file's header, checked against the limit.

    Returns:
        The size, or None when PIL cannot read the header (the caller's own decoder then
        reports the file).

    Raises:
        ValueError: the image declares more pixels than the ``image_pixels`` limit.
    """
    try:
        with open_image(path, label) as image:
            return image.size[1], image.size[0]
    except limits.LimitError:
        raise
    except ValueError:
        return None


def to_rgb(image: Image.Image, label: str) -> np.ndarray:
    """Decodes an image opened by `open_image` to (H, W, 3) uint8 RGB.

    Raises:
        ValueError: the data is truncated, corrupt or in an unsupported codec.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            return np.asarray(image.convert("RGB"))
    except Image.DecompressionBombError as error:
        raise _bomb(label, error) from None
    except _PIL_ERRORS as error:
        raise ValueError(f"{label}: cannot decode the image ({error})") from None


def _bomb(label: str, error: Exception) -> limits.LimitError:
    """Our one-line message for PIL's decompression-bomb error."""
    declared = re.search(r"\((\d+) pixels\)", str(error))
    pixels = f"{int(declared.group(1)):,} pixels" if declared else "too many pixels"
    return limits.LimitError(
        f"{label}: refusing a likely decompression bomb: the image declares {pixels}, more "
        f"than the limit of {limits.limit('image_pixels'):,} (set "
        f"{limits.LIMITS['image_pixels'].variable} higher to read it)"
    )
