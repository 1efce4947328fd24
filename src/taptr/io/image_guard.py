"""The one way taptr opens still images: header first, then decoded by the same library.

A few kilobytes of PNG can declare a 100,000 × 100,000 image, and a file named ``.png`` can
hold any format a decoder recognises by its content. Every image taptr reads (frames of
image folders, Kubric frames, TAP-Vid's encoded frames, masks, overlays, photographs) goes
through `open_image` and `read_image`, which:

- refuse paths that are not regular files before opening them (`taptr.io.file_kind`);
- read the header only, with Pillow restricted to the formats the caller accepts (`FRAME_FORMATS`
  for video frames, `STILL_FORMATS` for masks, overlays and photographs): a file whose
  header Pillow cannot read as one of them is refused, never decoded by content;
- refuse images above the ``image_pixels`` limit of `taptr.io.limits` before decoding;
- decode with Pillow, the library that read the header, so the checked size is the
  decoded size (OpenCV, which sniffs formats by content and has its own limits, decodes no
  input image).

Pillow's own decompression-bomb guard is turned into the same one-line error.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from collections.abc import Iterator, Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

from taptr.io import limits
from taptr.io.file_kind import require_file

FRAME_FORMATS = ("PNG", "JPEG")
"""Formats of video frames (image folders, Kubric, TAP-Vid): what their suffixes name."""

STILL_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "WEBP", "PPM")
"""Formats of masks, overlays and photographs: the common lossless and photo formats."""


class NotAnImageError(ValueError):
    """A file whose header is not that of an accepted image format; it was not decoded."""


_PIL_ERRORS = (UnidentifiedImageError, OSError, ValueError, SyntaxError, TypeError, EOFError)

_GREY_MODES = ("1", "L", "I", "F", "I;16", "I;16L", "I;16B", "I;16N")
"""Single-band modes: decoded as they are (2-D arrays)."""


@contextlib.contextmanager
def open_image(
    source: str | os.PathLike[str] | bytes,
    label: str,
    formats: Sequence[str] = FRAME_FORMATS,
) -> Iterator[Image.Image]:
    """Opens an image lazily (header only), refusing it above the ``image_pixels`` limit.

    Args:
        source: an image file or its encoded bytes.
        label: names the image in messages (a path, or a file and frame).
        formats: Pillow format names accepted; anything else is refused unread.

    Raises:
        FileNotFoundError: no file at ``source``.
        ValueError: a path that is not a regular file, a header Pillow cannot read as one of
            ``formats`` (the message says "not a readable ... image"), or an image
            declaring more pixels than the limit allows (`taptr.io.limits.LimitError`).
    """
    if not isinstance(source, bytes):
        source = require_file(source, "image")
    allowed = limits.limit("image_pixels")
    if Image.MAX_IMAGE_PIXELS is not None and allowed > Image.MAX_IMAGE_PIXELS:
        # the user raised the limit: PIL's own guard (errors above twice it) must follow
        Image.MAX_IMAGE_PIXELS = allowed
    try:
        with warnings.catch_warnings():
            # the pixel limit below decides; PIL's warning would only repeat it
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(
                io.BytesIO(source) if isinstance(source, bytes) else source, formats=list(formats)
            )
    except Image.DecompressionBombError as error:
        raise _bomb(label, error) from None
    except _PIL_ERRORS as error:
        raise NotAnImageError(
            f"{label}: not a readable image ({', '.join(formats)} expected; {_reason(error)})"
        ) from None
    with image:
        width, height = image.size
        limits.check("image_pixels", width * height, f"{label}: a {width}x{height} image")
        yield image


def read_image(
    source: str | os.PathLike[str] | bytes,
    label: str,
    *,
    formats: Sequence[str] = FRAME_FORMATS,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """An image file (or its bytes) as (H, W, 3) uint8 RGB, through `open_image`.

    Args:
        source: an image file or its encoded bytes.
        label: names the image in messages.
        formats: Pillow format names accepted.
        size: (height, width) the header must declare (frames of one video), or None.

    Raises:
        ValueError: as `open_image`; another size than ``size``; corrupt data.
    """
    with open_image(source, label, formats) as image:
        _check_size(image, label, size)
        return to_rgb(image, label)


def read_image_channels(
    source: str | os.PathLike[str], label: str, *, formats: Sequence[str] = STILL_FORMATS
) -> np.ndarray:
    """An image with its alpha: (H, W) grey, or (H, W, 3) RGB, or (H, W, 4) RGBA, or (H, W, 2).

    Grey stays one band (16-bit and float grey keep their values); palette images become
    RGBA when they have a transparent colour, else RGB; colour with alpha becomes RGBA (or
    grey + alpha, 2 bands); other colour modes become RGB. 16-bit colour is read at 8 bits.

    Raises:
        ValueError: as `open_image`, and for corrupt data.
    """
    with open_image(source, label, formats) as image:
        try:
            return np.asarray(_channel_image(image))
        except Image.DecompressionBombError as error:
            raise _bomb(label, error) from None
        except _PIL_ERRORS as error:
            raise ValueError(f"{label}: cannot decode the image ({_reason(error)})") from None


def _channel_image(image: Image.Image) -> Image.Image:
    """``image`` decoded in the mode `read_image_channels` returns."""
    if image.mode in _GREY_MODES:
        image.load()
        return image
    if image.mode in ("LA", "La", "PA"):
        return image.convert("LA")
    if image.mode == "P":
        return image.convert("RGBA" if "transparency" in image.info else "RGB")
    if image.mode in ("RGBA", "RGBa"):
        return image.convert("RGBA")
    return image.convert("RGB")


def image_size(path: str | os.PathLike[str], label: str) -> tuple[int, int]:
    """(height, width) declared by an image file's header, checked against the limit.

    Raises:
        ValueError: as `open_image`.
    """
    with open_image(path, label) as image:
        return image.size[1], image.size[0]


def to_rgb(image: Image.Image, label: str) -> np.ndarray:
    """Decodes an image opened by `open_image` to (H, W, 3) uint8 RGB.

    Raises:
        ValueError: the data is truncated, corrupt or in an unsupported codec.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            if image.mode in ("I", "F") or image.mode.startswith("I;16"):
                # Pillow's conversion to 8 bits clips 16-bit grey: keep its high byte instead,
                # as every other reader of 16-bit frames does
                grey = np.asarray(image).astype(np.float64)
                if image.mode.startswith("I;16"):
                    grey = np.floor(grey / 256)
                eight = np.clip(grey, 0, 255).astype(np.uint8)
                return np.repeat(eight[..., None], 3, axis=2)
            return np.asarray(image.convert("RGB"))
    except Image.DecompressionBombError as error:
        raise _bomb(label, error) from None
    except _PIL_ERRORS as error:
        raise ValueError(f"{label}: cannot decode the image ({_reason(error)})") from None


def _check_size(image: Image.Image, label: str, size: tuple[int, int] | None) -> None:
    if size is not None and (image.size[1], image.size[0]) != tuple(size):
        raise ValueError(
            f"{label}: its size {image.size[0]}x{image.size[1]} differs; the first frame is "
            f"{size[1]}x{size[0]}"
        )


def _reason(error: BaseException) -> str:
    """The first line of a decoder's message, without the file name Pillow puts in it."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    return re.sub(r" '[^']*'$", "", text)[:200]


def _bomb(label: str, error: Exception) -> limits.LimitError:
    """Our one-line message for PIL's decompression-bomb error."""
    declared = re.search(r"\((\d+) pixels\)", str(error))
    pixels = f"{int(declared.group(1)):,} pixels" if declared else "too many pixels"
    return limits.LimitError(
        f"{label}: refusing a likely decompression bomb: the image declares {pixels}, more "
        f"than the limit of {limits.limit('image_pixels'):,} (set "
        f"{limits.LIMITS['image_pixels'].variable} higher to read it)"
    )
