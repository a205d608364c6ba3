"""Checks on what clients send, done in the API before anything is stored or queued.

Image checks use Pillow only (the library's ``read_image`` would pull torch into the API): the
header gives the size, which is checked against the pixel limit BEFORE any decoding, so a
decompression bomb costs nothing. The data is then checked for truncation and corruption without
ever holding the whole bitmap (a full decode of a 9400 x 9400 PNG holds hundreds of MiB):
a PNG is inflated in a stream and counted, a JPEG is decoded at a reduced scale, and another format
is decoded only while its bitmap fits ``DECODE_BUDGET``; past that its header is all the API reads,
and a worker that cannot decode it fails the job with the reason. Option values are checked by
``geomatch.options`` (torch-free), which holds every option, its choices and its range once.
"""

from __future__ import annotations

import struct
import unicodedata
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from PIL import Image, ImageFile

from geomatch import options
from geomatch_core.errors import BadFile, DecompressionBomb, InvalidRequest, TooLarge, UnsupportedFormat

# what the pipeline reads (geomatch.options.IMAGE_SUFFIXES); MPO is how Pillow names many camera JPEGs
FORMATS = {"JPEG": "jpeg", "MPO": "jpeg", "PNG": "png", "TIFF": "tiff", "BMP": "bmp", "WEBP": "webp"}
MIN_SIDE = 16  # the matcher's minimum (geomatch.imageio)
MAX_NAME = 200
# A file name is a file's name under the project's folder: Linux file systems take 255 bytes.
MAX_NAME_BYTES = 255
# Bitmap bytes the API may hold to check one upload (Pillow keeps 4 bytes a pixel for RGB).
DECODE_BUDGET = 32 * 1024 * 1024
_STEP = 1 << 16  # bytes read / inflated at a time by the PNG check
# the seven passes of an interlaced PNG: first column and row, column and row steps
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


@dataclass(frozen=True)
class ImageInfo:
    width: int
    height: int
    format: str


# A project name as the use case takes it: stripped of white space (``str.isspace``) at both ends,
# then 1 to 200 characters, none of them a control character (Unicode Cc); at most 200 as sent.
# The same rule as a JSON Schema pattern, for OpenAPI (tests/service/test_units.py proves the two
# agree): WHITE is str.isspace's set, VISIBLE neither a control character nor white space.
_WHITE = r"[\t-\r\x1c-\x20\x85\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000]"
_VISIBLE = r"[^\x00-\x20\x7f-\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000]"
PROJECT_NAME_PATTERN = rf"^{_WHITE}*{_VISIBLE}(?:[^\x00-\x1f\x7f-\x9f]*{_VISIBLE})?{_WHITE}*$"
MAX_PROJECT_NAME = 200


def text_problem(value: str) -> str | None:
    """What makes ``value`` unfit to be stored as text, or None. JSON may carry a lone surrogate
    (``"\\ud800"``), which no store can encode as UTF-8; control characters (NUL among them, which
    PostgreSQL refuses) have no place in a name either."""
    for c in value:
        kind = unicodedata.category(c)
        if kind == "Cs":
            return f"contains U+{ord(c):04X}, a lone UTF-16 surrogate (not a character)"
        if kind == "Cc":
            return f"contains the control character U+{ord(c):04X}"
    return None


def check_text(field: str, value: str) -> str:
    problem = text_problem(value)
    if problem is not None:
        raise InvalidRequest(f"{field} {problem}")
    return value


def check_project_name(name: str | None) -> str:
    """The name to store (``PROJECT_NAME_PATTERN`` says the same for OpenAPI)."""
    raw = name or ""
    stripped = check_text("project name", raw.strip())
    if not stripped or len(raw) > MAX_PROJECT_NAME:
        raise InvalidRequest(f"project name must be 1 to {MAX_PROJECT_NAME} characters")
    return stripped


def check_name(name: str | None) -> str:
    """A plain file name: it becomes a path component under the project and COLMAP's image name.
    Messages show the name through repr, so that whatever it holds reaches the client escaped."""
    if name is None or not name.strip():
        raise BadFile("a file has no name")
    problem = text_problem(name)
    if problem is not None and "surrogate" in problem:
        raise BadFile(f"file name {name!r} {problem}")
    if "/" in name or "\\" in name:
        raise BadFile(f"file name {name!r} contains a path separator; send plain file names")
    if ".." in name:
        raise BadFile(f"file name {name!r} contains '..'")
    if name.startswith("."):
        raise BadFile(f"file name {name!r} starts with a dot")
    if problem is not None:
        raise BadFile(f"file name {name!r} contains control characters")
    if len(name) > MAX_NAME:
        raise BadFile(f"file name is {len(name)} characters long; at most {MAX_NAME}")
    size = len(name.encode())
    if size > MAX_NAME_BYTES:
        raise BadFile(
            f"file name is {size} bytes long in UTF-8; at most {MAX_NAME_BYTES} bytes "
            "(the file system's limit on a name)"
        )
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
                _check_data(im, path, fmt)
    except (BadFile, UnsupportedFormat, TooLarge):
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise DecompressionBomb(
            f"{name}: exceeds the limit of {max_pixels} pixels (decompression bomb guard; {e})"
        ) from None
    except Exception as e:  # Pillow raises OSError, SyntaxError, ValueError, struct.error ...
        corrupt = isinstance(e, _Corrupt) or "truncat" in str(e).lower()
        reason = "truncated or corrupt image data" if corrupt else "not a readable image"
        detail = str(e).replace(str(path), name)  # the staging path is the server's business
        raise BadFile(f"{name}: {reason} ({detail})") from None
    if width < MIN_SIDE or height < MIN_SIDE:
        raise BadFile(f"{name}: {width}x{height} is too small to match (at least {MIN_SIDE}x{MIN_SIDE})")
    return ImageInfo(width, height, FORMATS[fmt])


class _Corrupt(ValueError):
    pass


def _check_data(im: ImageFile.ImageFile, path: Path, fmt: str) -> None:
    """Truncated or corrupt data fails here (an exception naming why), in bounded memory."""
    w, h = im.size
    if fmt == "PNG":
        with path.open("rb") as f:
            _check_png(f, w, h)
        return
    if fmt in ("JPEG", "MPO"):
        # libjpeg scales while it decodes (1/2 ... 1/8): every byte is still read and checked. A
        # progressive file keeps its coefficients whole (2 bytes a sample) whatever the scale.
        if im.info.get("progressive") and w * h * 2 * len(im.getbands()) > DECODE_BUDGET:
            return
        scale = next((s for s in (1, 2, 4, 8) if (w // s) * (h // s) * 4 <= DECODE_BUDGET), 8)
        if scale > 1:
            im.draft(im.mode, (w // scale, h // scale))
        im.load()
        return
    if fmt == "BMP":
        _check_bmp(im, path)
    elif fmt == "TIFF":
        _check_tiff(im, path)
    if w * h * 4 <= DECODE_BUDGET:
        im.load()


def _check_bmp(im: ImageFile.ImageFile, path: Path) -> None:
    """The data a BMP's header promises is in the file. An uncompressed BMP's rows are fixed
    in size (Pillow's tile has the offset and the row stride), so a cut file shows without
    decoding; without this check one over DECODE_BUDGET would pass on its header alone and fail
    its match job. An RLE BMP states the size of its encoded data in the header (biSizeImage, which
    the format requires for compressed data)."""
    size = path.stat().st_size
    h = im.size[1]
    for tile in im.tile:
        if tile.codec_name == "raw" and isinstance(tile.args, tuple):  # (rawmode, stride, direction)
            need = tile.offset + int(tile.args[1]) * h
        else:  # bmp_rle: the encoded data's size, from the BITMAPINFOHEADER
            with path.open("rb") as f:
                head = f.read(38)
            if len(head) < 38:
                raise _Corrupt("truncated file")
            data_size = struct.unpack_from("<I", head, 34)[0]
            if data_size == 0 and im.size[0] * h * 4 > DECODE_BUDGET:
                raise _Corrupt("a compressed BMP too large to decode here, without its data size")
            need = tile.offset + data_size
        if need > size:
            raise _Corrupt(f"truncated file: {size} bytes, the header promises {need}")


# TIFF tags: where each strip (or tile) of the first image starts and how many bytes it has
_STRIP_OFFSETS, _STRIP_BYTES, _TILE_OFFSETS, _TILE_BYTES = 273, 279, 324, 325


def _check_tiff(im: Image.Image, path: Path) -> None:
    """Every strip or tile of the image the pipeline reads (the first) lies within the file: an
    uncompressed TIFF over DECODE_BUDGET would otherwise pass on its header alone, however
    little of its data it carried."""
    size = path.stat().st_size
    tags = getattr(im, "tag_v2", {})
    tiled = _TILE_OFFSETS in tags
    offsets = tags.get(_TILE_OFFSETS if tiled else _STRIP_OFFSETS)
    counts = tags.get(_TILE_BYTES if tiled else _STRIP_BYTES)
    if offsets is None or counts is None:
        return  # Pillow computes what is missing; the decode within the budget is the check
    offsets = offsets if isinstance(offsets, tuple) else (offsets,)
    counts = counts if isinstance(counts, tuple) else (counts,)
    if len(offsets) != len(counts):
        raise _Corrupt(f"{len(offsets)} strip offsets but {len(counts)} strip sizes")
    need = max((int(o) + int(c) for o, c in zip(offsets, counts, strict=True)), default=0)
    if need > size:
        raise _Corrupt(f"truncated file: {size} bytes, the strips reach byte {need}")


def _check_png(f: IO[bytes], width: int, height: int) -> None:
    """Every chunk's CRC, and the image data inflated as a stream and counted against what the
    header promises, a piece at a time: the bitmap is never held."""
    f.seek(8)
    length, kind = struct.unpack(">I4s", _read(f, 8))
    ihdr = _read(f, length)
    if kind != b"IHDR" or length != 13:
        raise _Corrupt("no IHDR chunk first")
    if zlib.crc32(kind + ihdr) != struct.unpack(">I", _read(f, 4))[0]:
        raise _Corrupt("bad CRC in IHDR")
    depth, colour, interlace = ihdr[8], ihdr[9], ihdr[12]
    expected = _png_data_size(width, height, depth, colour, interlace)
    inflater = zlib.decompressobj()
    produced = 0
    while True:
        length, kind = struct.unpack(">I4s", _read(f, 8))
        crc = zlib.crc32(kind)
        left = length
        while left:
            piece = _read(f, min(left, _STEP))
            left -= len(piece)
            crc = zlib.crc32(piece, crc)
            if kind != b"IDAT":
                continue
            if inflater.eof:
                raise _Corrupt("image data after the end of its stream")
            while piece:
                try:
                    produced += len(inflater.decompress(piece, _STEP))
                except zlib.error as e:
                    raise _Corrupt(f"zlib: {e}") from None
                if produced > expected:
                    raise _Corrupt("more image data than the header's size")
                piece = inflater.unconsumed_tail
        if crc != struct.unpack(">I", _read(f, 4))[0]:
            raise _Corrupt(f"{kind.decode('latin-1')} chunk: bad CRC")
        if kind == b"IEND":
            break
    produced += len(inflater.flush())
    if not inflater.eof or produced != expected:
        raise _Corrupt(f"truncated image data ({produced} of {expected} bytes)")


def _read(f: IO[bytes], n: int) -> bytes:
    data = f.read(n)
    if len(data) != n:
        raise _Corrupt("truncated file")
    return data


def _png_data_size(width: int, height: int, depth: int, colour: int, interlace: int) -> int:
    """Bytes of the filtered scanlines (a filter byte, then the row) that IDAT inflates to."""
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour)
    if channels is None or depth not in (1, 2, 4, 8, 16) or interlace not in (0, 1):
        raise _Corrupt("bad IHDR")
    bits = channels * depth

    def size(w: int, h: int) -> int:
        return h * (1 + (w * bits + 7) // 8) if w and h else 0

    if not interlace:
        return size(width, height)
    return sum(size((width - x + dx - 1) // dx, (height - y + dy - 1) // dy) for x, y, dx, dy in _ADAM7)


def check_option(name: str, value: Any) -> Any:
    """``value`` as option ``name`` accepts it (``geomatch.options``), else InvalidRequest."""
    try:
        return options.check(name, value)
    except options.OptionError as e:
        raise InvalidRequest(str(e)) from None


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
