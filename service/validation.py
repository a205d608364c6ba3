"""Checks on what clients send, done in the API before anything is stored or queued.

Image checks use Pillow only (the library's ``read_image`` would pull torch into the API): the
header gives the size, which is checked against the pixel limit BEFORE any decoding, so a
decompression bomb costs nothing; then the whole file is decoded once, which catches truncated
and corrupt files. Option values are checked by ``geomatch.options`` (torch-free), which holds
every option, its choices and its range once.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image

from core.errors import BadFile, DecompressionBomb, InvalidRequest, TooLarge, UnsupportedFormat
from geomatch import options

# what the pipeline reads (geomatch.options.IMAGE_SUFFIXES); MPO is how Pillow names many camera JPEGs
FORMATS = {"JPEG": "jpeg", "MPO": "jpeg", "PNG": "png", "TIFF": "tiff", "BMP": "bmp", "WEBP": "webp"}
MIN_SIDE = 16  # the matcher's minimum (geomatch.imageio)
MAX_NAME = 200


@dataclass(frozen=True)
class ImageInfo:
    width: int
    height: int
    format: str


def check_name(name: str | None) -> str:
    """A plain file name: it becomes a path component under the project and COLMAP's image name."""
    if name is None or not name.strip():
        raise BadFile("a file has no name")
    if "/" in name or "\\" in name:
        raise BadFile(f"file name {name!r} contains a path separator; send plain file names")
    if ".." in name:
        raise BadFile(f"file name {name!r} contains '..'")
    if name.startswith("."):
        raise BadFile(f"file name {name!r} starts with a dot")
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise BadFile(f"file name {name!r} contains control characters")
    if len(name) > MAX_NAME:
        raise BadFile(f"file name is {len(name)} characters long; at most {MAX_NAME}")
    if name != name.strip():
        raise BadFile(f"file name {name!r} starts or ends with white space")
    return name


def check_image(path: Path, name: str, max_pixels: int) -> ImageInfo:
    """Raise BadFile / UnsupportedFormat / TooLarge with a message naming ``name``, else describe it."""
    if path.stat().st_size == 0:
        raise BadFile(f"{name}: empty file (0 bytes)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                width, height, fmt = im.width, im.height, im.format or "?"
                if fmt not in FORMATS:
                    accepted = ", ".join(sorted(set(FORMATS.values())))
                    raise UnsupportedFormat(f"{name}: {fmt} images are not accepted; send {accepted}")
                if width * height > max_pixels:
                    raise DecompressionBomb(
                        f"{name}: {width}x{height} = {width * height} pixels exceeds the limit of "
                        f"{max_pixels} (decompression bomb guard)"
                    )
                im.load()  # decodes everything: truncated or corrupt data fails here
    except (BadFile, UnsupportedFormat, TooLarge):
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise DecompressionBomb(
            f"{name}: exceeds the limit of {max_pixels} pixels (decompression bomb guard; {e})"
        ) from None
    except Exception as e:  # Pillow raises OSError, SyntaxError, ValueError, struct.error ...
        reason = "truncated or corrupt image data" if "truncat" in str(e).lower() else "not a readable image"
        detail = str(e).replace(str(path), name)  # the staging path is the server's business
        raise BadFile(f"{name}: {reason} ({detail})") from None
    if width < MIN_SIDE or height < MIN_SIDE:
        raise BadFile(f"{name}: {width}x{height} is too small to match (at least {MIN_SIDE}x{MIN_SIDE})")
    return ImageInfo(width, height, FORMATS[fmt])


def check_option(name: str, value: Any) -> Any:
    """``value`` as option ``name`` accepts it (``geomatch.options``), else InvalidRequest."""
    try:
        return options.check(name, value)
    except options.OptionError as e:
        raise InvalidRequest(str(e)) from None


def check_pair_spec(spec: str) -> str:
    return str(check_option("pairs", spec))


def check_pair_list(pairs: list[list[str]], names: set[str]) -> list[list[str]]:
    if not pairs:
        raise InvalidRequest("the pair list is empty")
    out = []
    for p in pairs:
        if len(p) != 2:
            raise InvalidRequest(f"a pair has two image names, got {p!r}")
        a, b = p
        for n in (a, b):
            if n not in names:
                raise InvalidRequest(
                    f"pair [{a!r}, {b!r}] names {n!r}, which is not an image of this project"
                )
        if a == b:
            raise InvalidRequest(f"pair [{a!r}, {b!r}] matches an image with itself")
        out.append([a, b])
    return out
