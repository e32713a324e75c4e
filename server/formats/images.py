"""Image bytes in and out: header sniffing (size limits before decoding) and encoding.

The width and height of a JPEG or PNG are read from its header so an oversize image
(a "decompression bomb") is refused before the decoder allocates anything.
"""

from __future__ import annotations

import struct

import numpy as np

from hippomap.errors import InputError

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_STANDALONE = {0x01, 0xD8} | set(range(0xD0, 0xD8))
JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def image_kind(data: bytes) -> str | None:
    """``"jpeg"``, ``"png"`` or None from the magic bytes."""
    if data[:3] == JPEG_MAGIC:
        return "jpeg"
    if data[:8] == PNG_MAGIC:
        return "png"
    return None


def image_dimensions(data: bytes) -> tuple[int, int]:
    """``(width, height)`` from a JPEG's SOF segment or a PNG's IHDR chunk."""
    kind = image_kind(data)
    if kind == "png":
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise InputError("corrupt PNG: no IHDR header")
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if kind != "jpeg":
        raise InputError("image payload is not a JPEG or PNG (bad magic bytes)")
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise InputError(f"corrupt JPEG: expected a marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _STANDALONE:
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if length < 2:
            raise InputError(f"corrupt JPEG: segment length {length} at byte {i}")
        if marker in _SOF:
            if i + 9 > n:
                break
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(w), int(h)
        if marker == 0xDA:  # start of scan before any frame header
            break
        i += 2 + length
    raise InputError("corrupt JPEG: no frame header (SOF) found")


def is_truncated(data: bytes) -> bool:
    """A JPEG without its end-of-image marker, or a PNG without IEND: the decoder would
    silently fill the missing part with gray, so such frames are refused."""
    tail = data[-32:].rstrip(b"\x00")
    if image_kind(data) == "jpeg":
        return not tail.endswith(b"\xff\xd9")
    if image_kind(data) == "png":
        return b"IEND" not in tail
    return False


def check_jpeg_strict(data: bytes) -> np.ndarray | None:
    """Decode a JPEG fully and strictly: InputError on any corruption the decoder notices; the
    gray image (H, W) uint8 it decoded, so that the frame is not decoded a second time (None for
    a non-JPEG, or from the Pillow fallback). libjpeg-turbo's gray output here is the same,
    pixel for pixel, as :func:`hippomap.inputs.decode_jpeg`'s, which replay uses.

    OpenCV's decoder (like most) turns libjpeg's "corrupt data" *warnings* into gray or garbled
    blocks and returns an image anyway, so a frame whose middle was overwritten would be stored
    and learned. libjpeg-turbo's strict mode (through ``simplejpeg``) raises on them instead;
    without ``simplejpeg`` Pillow's full decode is the (weaker) fallback."""
    if image_kind(data) != "jpeg":
        return None
    try:
        import simplejpeg
    except ImportError:  # pragma: no cover - simplejpeg is a server dependency
        import io

        from PIL import Image

        try:
            with Image.open(io.BytesIO(data)) as im:
                im.load()
        except Exception as exc:  # noqa: BLE001 - any decoder complaint means a corrupt frame
            raise InputError(f"corrupt JPEG: {exc}") from None
        return None
    try:
        gray = simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=True)
    except (ValueError, RuntimeError) as exc:
        raise InputError(f"corrupt JPEG: {exc}") from None
    return np.ascontiguousarray(gray.reshape(gray.shape[0], gray.shape[1]))


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 images
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
