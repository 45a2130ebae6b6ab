"""Image reading and writing with errors that name the file (OpenCV underneath).

Mask PNGs
---------
A mask is a PNG file (checked by its signature bytes: JPEG or anything else under a ``.png`` name
is refused). Its size is read from the PNG header and refused before any pixel is decoded when it
differs from the frame's (or exceeds :data:`benchmark.core.annotation.MAX_MASK_PIXELS`). A pixel is
foreground when:

* **single channel** (grey, 1/8/16-bit): its value is non-zero;
* **colour** (RGB, or a palette image, which reads as its palette's colours): **any** channel is
  non-zero, so a red, green or blue mask on black reads the same;
* **with alpha** (grey + alpha, RGBA, palette with transparency): a fully transparent pixel
  (alpha 0) is background; otherwise the colour rule applies. An image whose colour channels are
  zero everywhere and whose alpha varies is an **alpha-only mask**: foreground where alpha is
  non-zero. (A fully opaque all-black image is an empty mask.)
"""

from __future__ import annotations

import atexit
import contextlib
import os
import struct
import sys
import tempfile
import threading
import zlib
from pathlib import Path
from typing import Iterator, Optional

import cv2
import numpy as np

from .atomic import atomic_path
from .errors import InputError


NATIVE_STDERR_LOCK = threading.RLock()
"""Held while native decoders write to file descriptor 2 into a capture (:func:`native_decoder_messages`);
a thread writing its own lines to the terminal takes it too, so no line of its lands in a capture."""
_MAX_MESSAGE_BYTES = 4096
_capture_file = None
"""The file fd 2 is pointed at during a capture: one per process, emptied for each (a decode is on the path of
every frame a scene loads)."""


@contextlib.contextmanager
def native_decoder_messages() -> Iterator[list[str]]:
    """Capture what native code (libpng, libjpeg inside OpenCV) writes to file descriptor 2 during the block;
    the list yielded holds it, one line a message, once the block ends. Those libraries print their errors
    and warnings there, past Python, before they fail or pad an image: caught, they become one error naming
    the file instead of raw lines on the terminal."""
    global _capture_file
    said: list[str] = []
    with NATIVE_STDERR_LOCK:
        if _capture_file is None or _capture_file.closed:
            _capture_file = tempfile.TemporaryFile()
            atexit.register(_capture_file.close)  # closed with the process, not left to the collector
        capture = _capture_file
        capture.seek(0)
        capture.truncate()
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        saved = os.dup(2)
        try:
            os.dup2(capture.fileno(), 2)
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            capture.seek(0)
            text = capture.read(_MAX_MESSAGE_BYTES).decode("utf-8", "replace")
            said.extend(line.strip() for line in text.splitlines() if line.strip())


def refuse_if_said(path: Path, said: list[str], what: str, field: Optional[str] = None) -> None:
    """An :class:`InputError` naming the file (and ``field``) where a native decoder said anything while it
    read it (:func:`native_decoder_messages`): it printed because the file is damaged. ``what``: the refusal
    ("cannot decode image"), followed by the decoder's first message."""
    if said:
        from .strict import terminal_text

        raise InputError(path, field, f"{what}: the decoder reports {terminal_text(said[0])[:200]}")


def decode_checked(path: Path, data: bytes, *, kind: str = "image") -> np.ndarray:
    """``cv2.imdecode`` (``IMREAD_UNCHANGED``) of ``data``, the file ``path``'s checked bytes: an image the
    decoder says anything about (libpng's or libjpeg's errors and warnings: a corrupt stream, a JPEG scan cut
    short and padded) or cannot decode is an :class:`InputError` naming the file and ``kind``, with the
    decoder's first message."""
    with native_decoder_messages() as said:
        try:
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        except cv2.error:
            img = None
    refuse_if_said(path, said, f"cannot decode {kind}")
    if img is None:
        raise InputError(path, None, f"cannot decode {kind} (truncated or corrupt)")
    return img


def read_image_pixels(path: str | Path) -> np.ndarray:
    """The decoded pixels of a PNG or JPEG as OpenCV gives them (``IMREAD_UNCHANGED``: uint8 or uint16, BGR(A)
    or grey), after every check that needs no decoding: a regular file, a header within the pixels any frame
    may have, a PNG stream complete and consistent with its header and handed to the decoder with its
    critical chunks only (:func:`_png_checked`), a JPEG with its end marker; then decoded with the decoder's
    messages caught (:func:`decode_checked`). An :class:`InputError` names the file otherwise."""
    from .strict import file_problem, open_regular

    path = Path(path)
    problem = file_problem(path)
    if problem == "missing":
        raise InputError(path, None, "image file not found")
    if problem is not None:
        raise InputError(path, None, f"is {problem}, expected an image file")
    try:
        with open_regular(path) as fh:
            head = fh.read(64 * 1024)
            limit = _image_file_limit(path, head)  # a PNG too large for a frame is refused here, unread
            rest = fh.read(limit - len(head) + 1) if len(head) == 64 * 1024 else b""
    except OSError as err:
        raise InputError(path, None, f"cannot read: {err.strerror or err}") from None
    if len(head) + len(rest) > limit:
        raise InputError(path, None, f"file of more than {limit} bytes: more than its pixels can need")
    data = head + rest
    if data[:8] == PNG_SIGNATURE:
        return decode_checked(path, _png_checked(path, data))
    if data[:3] == b"\xff\xd8\xff":
        _check_frame_pixels(path, *jpeg_layout(path, data)[:2])  # a JPEG's size comes only with the whole file
        return decode_checked(path, data)
    # OpenCV would decode BMP, TIFF, WebP... of any declared size: frames and masks are PNG or JPEG
    raise InputError(path, None, "not a PNG or JPEG file (no PNG or JPEG signature)")


def _check_frame_pixels(path: Path, width: int, height: int) -> None:
    """An :class:`InputError` for an image of more pixels than any frame may have, before it is decoded."""
    from .annotation import MAX_MASK_PIXELS

    if width * height > MAX_MASK_PIXELS:
        raise InputError(path, None, f"image of {width}x{height} pixels is larger than the {MAX_MASK_PIXELS} pixels "
                                     "any frame may have")


def _image_file_limit(path: Path, head: bytes) -> int:
    """The most bytes an image file may have, plus a MiB for metadata: a PNG (its header checked against the
    pixels a frame may have) twice what its rows can need (8 bytes a pixel at most: 16-bit RGBA), a JPEG (8-bit,
    its size read only after the whole file) 4 bytes a pixel of the largest frame."""
    from .annotation import MAX_MASK_PIXELS

    if head[:8] == PNG_SIGNATURE:
        width, height, _, _ = png_header(path, head[:33])
        _check_frame_pixels(path, width, height)
        return 2 * (8 * width * height + height) + (1 << 20)
    return 4 * MAX_MASK_PIXELS + (1 << 20)


def read_image(path: str | Path, *, keep_alpha: bool = False) -> np.ndarray:
    """Read an 8- or 16-bit PNG/JPEG as float32 RGB(A) in [0, 1], shape (H, W, 3) or (H, W, 4).

    Truncated, corrupt or unreadable files raise :class:`InputError` naming the file (:func:`read_image_pixels`).
    """
    img = read_image_pixels(path)
    if img.dtype == np.uint16:
        scale = 65535.0
    elif img.dtype == np.uint8:
        scale = 255.0
    else:
        raise InputError(path, "dtype", f"unsupported image dtype {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        if not keep_alpha:
            img = img[:, :, :3]
    else:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)
        if keep_alpha:
            full = np.full(img.shape[:2] + (1,), scale, dtype=img.dtype)
            img = np.concatenate([img, full], axis=2)
    return img.astype(np.float32) / scale


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
"""Samples per pixel of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA)."""
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
"""The seven passes of an interlaced PNG: (first column, first row, column step, row step)."""
_INFLATE_STEP = 1 << 20
"""Bytes of rows inflated at a time while a PNG stream is checked (the rows are counted, never kept)."""


def png_row_bytes(width: int, height: int, depth: int, colour: int, interlaced: bool) -> list[int]:
    """Length in bytes of every filtered row of a PNG's image data (its filter byte included), in stream order."""
    bits = _PNG_CHANNELS[colour] * depth
    passes = _ADAM7 if interlaced else ((0, 0, 1, 1),)
    rows: list[int] = []
    for x0, y0, dx, dy in passes:
        w = (width - x0 + dx - 1) // dx if width > x0 else 0
        h = (height - y0 + dy - 1) // dy if height > y0 else 0
        if w and h:
            rows.extend([1 + (w * bits + 7) // 8] * h)
    return rows


def _png_checked(path: Path, data: bytes) -> bytes:
    """The PNG ``data`` as the decoder is given it: its critical chunks only (IHDR, PLTE, tRNS, the image data
    as one IDAT, IEND), once checked that a decoder reads them without a fault: every chunk present up to
    its IEND with its CRC right, IHDR once and first, a known colour type and bit depth, a palette where and
    as long as the colour type allows, a tRNS of the length its colour type takes, the IDAT chunks together,
    and image data that inflate to exactly the rows the header declares, each starting with a valid filter
    type. Anything else is refused naming the file: a decoder would pad missing rows, or print its own
    error or warning to the terminal. Ancillary chunks (gamma, colour profiles, text) are left out: OpenCV
    applies none of them, and a damaged one only makes the decoder print."""
    width, height, depth, colour = png_header(path, data[:33])
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16) or (colour in (2, 4, 6) and depth < 8) \
            or (colour == 3 and depth > 8):
        raise InputError(path, "IHDR", f"PNG of colour type {colour} and bit depth {depth}: not a valid pair")
    if data[28] not in (0, 1):
        raise InputError(path, "IHDR", f"unknown PNG interlace method {data[28]}")
    rows = png_row_bytes(width, height, depth, colour, bool(data[28]))
    expected = sum(rows)
    kept: dict[bytes, bytes] = {}
    idat: list[bytes] = []
    idat_done = False
    inflate = zlib.decompressobj()
    produced, row, next_start = 0, 0, 0  # bytes of rows so far; the row whose filter byte comes at next_start

    def take(block: bytes) -> None:
        nonlocal produced, row, next_start
        end = produced + len(block)
        while row < len(rows) and next_start < end:
            if block[next_start - produced] > 4:
                raise InputError(path, "IDAT", f"corrupt PNG: row {row} has filter type {block[next_start - produced]}")
            next_start += rows[row]
            row += 1
        produced = end
        if produced > expected:
            raise InputError(path, "IDAT", f"PNG image data longer than the {expected} bytes of rows its "
                                           f"{width}x{height} header declares")

    offset = 8
    while True:
        if offset + 12 > len(data):
            raise InputError(path, None, f"truncated PNG: it ends at byte {len(data)} before its IEND chunk")
        length, = struct.unpack(">I", data[offset:offset + 4])
        kind = data[offset + 4:offset + 8]
        if offset + 12 + length > len(data):
            raise InputError(path, None, f"truncated PNG: chunk {kind!r} at byte {offset} declares {length} bytes, "
                                         f"the file has {len(data) - offset - 12} left")
        body = data[offset + 8:offset + 8 + length]
        if zlib.crc32(kind + body) != struct.unpack(">I", data[offset + 8 + length:offset + 12 + length])[0]:
            raise InputError(path, None, f"corrupt PNG: chunk {kind!r} at byte {offset} fails its CRC")
        if not kind[0] & 0x20 and kind not in (b"IHDR", b"PLTE", b"IDAT", b"IEND"):  # critical: its reader must know it
            raise InputError(path, None, f"PNG with the unknown critical chunk {kind!r} at byte {offset}")
        if kind == b"IHDR" and offset != 8:
            raise InputError(path, None, f"corrupt PNG: a second IHDR chunk at byte {offset}")
        if kind in (b"PLTE", b"tRNS") and (idat or kind in kept):
            raise InputError(path, None, f"corrupt PNG: chunk {kind!r} at byte {offset} out of place")
        if kind in (b"PLTE", b"tRNS"):
            kept[kind] = body
        if kind == b"IDAT" and idat_done:
            raise InputError(path, None, f"corrupt PNG: image data chunks apart (another IDAT at byte {offset})")
        if idat and kind != b"IDAT":
            idat_done = True
        if kind == b"IDAT":
            idat.append(body)
            try:
                block = inflate.decompress(body, _INFLATE_STEP)
                take(block)
                while inflate.unconsumed_tail:
                    take(inflate.decompress(inflate.unconsumed_tail, _INFLATE_STEP))
            except zlib.error as err:
                raise InputError(path, "IDAT", f"corrupt PNG image data ({err})") from None
        offset += 12 + length
        if kind == b"IEND":
            break
    if inflate.unused_data:  # a second stream or garbage after the first: not one zlib stream of rows
        raise InputError(path, "IDAT", f"{len(inflate.unused_data)} bytes after the end of the PNG image data stream")
    if not inflate.eof or produced != expected:
        raise InputError(path, "IDAT", f"PNG image data holds {produced} of the {expected} bytes of rows its "
                                       f"{width}x{height} header declares" + ("" if inflate.eof else
                                                                             " (the stream is cut short)"))
    palette, alpha = kept.get(b"PLTE"), kept.get(b"tRNS")
    if colour == 3 and palette is None:
        raise InputError(path, "PLTE", "palette PNG without a palette")
    if palette is not None:
        entries = len(palette) // 3
        # a palette longer than the bit depth can index is out of the PNG rules but read by libpng (truncated
        # in silence): kept, as readers keep it
        if colour in (0, 4) or len(palette) % 3 or not 1 <= entries <= 256:
            raise InputError(path, "PLTE", f"a palette of {len(palette)} bytes for colour type {colour}")
        if colour != 3:
            palette = None  # a suggested palette of a colour image: nothing OpenCV reads
    if alpha is not None:
        entries = len(kept[b"PLTE"]) // 3 if colour == 3 else 0
        allowed = {0: (2,), 2: (6,), 3: tuple(range(1, entries + 1))}.get(colour, ())  # none with an alpha channel
        if len(alpha) not in allowed:
            raise InputError(path, "tRNS", f"a transparency chunk of {len(alpha)} bytes for colour type {colour}")

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return b"".join([data[:33], chunk(b"PLTE", palette) if palette is not None else b"",
                     chunk(b"tRNS", alpha) if alpha is not None else b"", chunk(b"IDAT", b"".join(idat)),
                     chunk(b"IEND", b"")])


_JPEG_FRAME_MARKERS = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
"""Start-of-frame markers (baseline, extended, progressive, lossless; Huffman or arithmetic)."""
MAX_JPEG_SCANS = 64
"""Scans a JPEG may hold (a progressive one has about ten): each costs a pass over every coefficient, so a
small file of thousands of scans would keep the decoder busy for minutes."""


def jpeg_layout(path: str | Path, data: bytes) -> tuple[int, int, int]:
    """``(width, height, scans)`` of a JPEG, walking its markers and its scans' entropy-coded data without
    decoding, up to its end-of-image marker (bytes after it, such as a trailer, are not the image's). Refused
    naming the file: no frame header before the first scan, frame headers of different sizes, a segment
    running past the end, more than :data:`MAX_JPEG_SCANS` scans, and no end-of-image marker (a file cut
    short: the decoder would pad the missing rows with grey)."""
    offset, size, scans = 2, None, 0
    n = len(data)
    while True:
        if offset + 2 > n:
            raise InputError(path, None, "truncated JPEG: no end-of-image marker after its last scan")
        if data[offset] != 0xFF:
            raise InputError(path, None, f"corrupt JPEG: no marker at byte {offset}")
        marker = data[offset + 1]
        if marker == 0xFF:  # fill byte
            offset += 1
            continue
        if marker == 0xD9:
            break
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            offset += 2
            continue
        if offset + 4 > n:
            raise InputError(path, None, "truncated JPEG: no end-of-image marker after its last scan")
        length, = struct.unpack(">H", data[offset + 2:offset + 4])
        if length < 2 or offset + 2 + length > n:
            raise InputError(path, None, f"truncated JPEG: segment 0x{marker:02X} at byte {offset} runs past the end")
        if marker in _JPEG_FRAME_MARKERS:
            if length < 8:
                raise InputError(path, None, "corrupt JPEG: a frame header too short")
            height, width = struct.unpack(">HH", data[offset + 5:offset + 9])
            if width == 0 or height == 0:
                raise InputError(path, None, f"JPEG of {width}x{height} pixels")
            if size is not None and size != (width, height):
                raise InputError(path, None, "corrupt JPEG: frame headers of different sizes")
            size = (width, height)
        offset += 2 + length
        if marker == 0xDA:  # a scan: its entropy-coded data runs to the next marker other than a stuffed byte or RSTn
            if size is None:
                raise InputError(path, None, "corrupt JPEG: a scan before any frame header")
            scans += 1
            if scans > MAX_JPEG_SCANS:
                raise InputError(path, None, f"JPEG of more than {MAX_JPEG_SCANS} scans")
            while True:
                offset = data.find(b"\xff", offset)
                if offset < 0 or offset + 1 >= n:
                    raise InputError(path, None, "truncated JPEG: no end-of-image marker after its last scan")
                follower = data[offset + 1]
                if follower == 0x00 or 0xD0 <= follower <= 0xD7 or follower == 0xFF:
                    offset += 1 if follower == 0xFF else 2
                    continue
                break
    if size is None or scans == 0:
        raise InputError(path, None, "corrupt JPEG: no frame header or no scan before its end")
    return size[0], size[1], scans


def png_header(path: str | Path, data: Optional[bytes] = None) -> tuple[int, int, int, int]:
    """``(width, height, bit depth, colour type)`` from a PNG's signature and IHDR chunk, without
    decoding pixels. Anything that is not a PNG raises :class:`InputError` naming the file."""
    path = Path(path)
    if data is None:
        data = _read_bytes(path, 33)
    if data[:8] != PNG_SIGNATURE:
        what = "a JPEG" if data[:3] == b"\xff\xd8\xff" else "empty" if not data else "not a PNG"
        raise InputError(path, None, f"expected a PNG file, but the file is {what} (no PNG signature)")
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InputError(path, "IHDR", "truncated PNG: no header chunk")
    length, = struct.unpack(">I", data[8:12])
    width, height, depth, colour = struct.unpack(">IIBB", data[16:26])
    if length != 13 or zlib.crc32(data[12:29]) != struct.unpack(">I", data[29:33])[0]:
        raise InputError(path, "IHDR", "corrupt PNG header chunk")
    if width == 0 or height == 0:
        raise InputError(path, "IHDR", f"PNG of {width}x{height} pixels")
    return width, height, depth, colour


def _read_bytes(path: Path, limit: int = -1) -> bytes:
    if path.is_dir():
        raise InputError(path, None, "is a folder, expected a PNG file")
    if not path.is_file():
        raise InputError(path, None, "mask file not found")
    try:
        with open(path, "rb") as fh:
            return fh.read(limit)
    except OSError as err:
        raise InputError(path, None, f"cannot read: {err.strerror or err}") from None


def read_png_bytes(path: str | Path, size: Optional[tuple[int, int]] = None) -> tuple[bytes, int, int, int, int]:
    """The bytes of a mask PNG, checked as far as possible without decoding pixels:
    ``(data, width, height, bit depth, colour type)``.

    Refused with an :class:`InputError` naming the file: not a PNG (signature), a header of another
    size than ``size`` = ``(height, width)`` or beyond :data:`benchmark.core.annotation.MAX_MASK_PIXELS`, a
    file far larger than its pixels can need, and a chunk that runs past the end of the file (a
    decoder would allocate the length it declares before finding the data missing).
    """
    from .annotation import MAX_MASK_PIXELS

    path = Path(path)
    width, height, depth, colour = png_header(path, _read_bytes(path, 33))
    if size is not None and (height, width) != (int(size[0]), int(size[1])):
        raise InputError(path, None, f"mask is {width}x{height} (WxH), the frame is {int(size[1])}x{int(size[0])}")
    if width * height > MAX_MASK_PIXELS:
        raise InputError(path, None, f"mask of {width}x{height} pixels is larger than the {MAX_MASK_PIXELS} "
                                     "pixels any frame may have")
    # deflate never needs much more than the raw rows (8 bytes a pixel at most: 16-bit RGBA)
    limit = 2 * height * (1 + 8 * width) + (1 << 20)
    data = _read_bytes(path, limit + 1)
    if len(data) > limit:
        raise InputError(path, None, f"file of more than {limit} bytes for a {width}x{height} mask")
    offset = 8
    while True:
        if offset + 12 > len(data):
            raise InputError(path, None, f"truncated PNG: it ends at byte {len(data)} before its IEND chunk")
        length, = struct.unpack(">I", data[offset:offset + 4])
        kind = data[offset + 4:offset + 8]
        if offset + 12 + length > len(data):
            raise InputError(path, None, f"truncated PNG: chunk {kind!r} at byte {offset} declares {length} bytes, "
                                         f"the file has {len(data) - offset - 12} left")
        offset += 12 + length
        if kind == b"IEND":
            return data, width, height, depth, colour


def read_mask(path: str | Path, size: Optional[tuple[int, int]] = None) -> np.ndarray:
    """Read a mask PNG (module docstring) as (H, W) uint8/uint16 values, non-zero = foreground.

    ``size`` = the frame's ``(height, width)``: a PNG of another size is refused from its header,
    before decoding. Without it the header must stay within
    :data:`benchmark.core.annotation.MAX_MASK_PIXELS`. A single-channel mask keeps its values; a colour
    mask gives the largest channel (zeroed where alpha is 0), or the alpha of an alpha-only mask.
    Every malformed file raises :class:`InputError` naming it (:func:`read_png_bytes`).
    """
    path = Path(path)
    data, width, height, _, _ = read_png_bytes(path, size)
    img = decode_checked(path, _png_checked(path, data), kind="mask PNG")
    if img.shape[:2] != (height, width) or img.dtype not in (np.uint8, np.uint16):
        raise InputError(path, None, "cannot decode mask PNG (truncated or corrupt)")
    if img.ndim == 2:
        return img
    if img.shape[2] in (2, 4):
        colour, alpha = img[:, :, :-1], img[:, :, -1]
        if not colour.any() and alpha.min() != alpha.max():
            return alpha  # alpha-only mask
        value = colour.max(axis=2)
        value[alpha == 0] = 0
        return value
    return img.max(axis=2)  # any channel non-zero: the order of colour channels does not matter


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write float [0, 1] or uint8 RGB(A) / gray to PNG or JPEG, atomically."""
    path = Path(path)
    img = np.asarray(image)
    if img.dtype != np.uint8 and img.dtype != np.uint16:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise InputError(path, None, "cannot encode image")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
