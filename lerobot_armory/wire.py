"""Tensors on the wire: dtype + shape + raw bytes (or JPEG for uint8 RGB images). Never pickle.

Decoding trusts nothing: the dtype must be on a short allow-list, the shape must match what the
robot registered, and the byte length must be exactly ``prod(shape) * itemsize`` before
``np.frombuffer`` touches it. JPEG payloads are checked for their pixel size *before* they are
decoded, so a small file cannot expand into a huge image, and for their structure (one frame, a
bounded number of header segments and scans), so a small file cannot cost seconds of CPU either.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from lerobot_armory.feature_spec import ALLOWED_DTYPES, MAX_DIMS, FeatureSpec, WireError, check_features
from lerobot_armory.proto import armory_pb2 as pb

__all__ = [
    "ALLOWED_DTYPES", "MAX_DIMS", "FeatureSpec", "WireError", "check_features", "decode", "decode_all", "encode",
    "spec_from_proto", "spec_to_proto",
]  # fmt: skip

# Scans a JPEG may have. A baseline JPEG has 1 (3 when non-interleaved), libjpeg's progressive
# script (PIL ``progressive=True``, OpenCV ``IMWRITE_JPEG_PROGRESSIVE``, ``cjpeg -progressive``)
# has 10 for colour, and optimised scripts (mozjpeg, ``jpegtran -optimize``) stay in the low tens.
# libjpeg walks every block of the image once per scan, even an empty one (~0.2 ms a scan at
# 640x480), and has no scan limit: 100k empty 12-byte scans (1.2 MB) cost 19 s of CPU at 640x480.
# 64 accepts every real encoder's output and caps that work at ~12 ms, about a normal decode's.
MAX_JPEG_SCANS = 64
# Marker segments (APPn, DQT, DHT, COM, ...) before the first scan. Real files have ~5-20 (an ICC
# profile split over many APP2 chunks adds a few). PIL parses this header in Python, one segment
# per loop turn: 4M empty COM segments in a 16 MB message cost it ~3.4 s, so the count is capped.
MAX_JPEG_HEADER_SEGMENTS = 512
# 0xFF fill bytes allowed before one header marker; encoders write none, PIL skips each one in Python.
_MAX_JPEG_FILL = 16
_JPEG_MARKER = re.compile(rb"\xff{1,%d}([^\xff\x00])" % _MAX_JPEG_FILL, re.DOTALL)
# Start-of-frame markers: 0xC0-0xCF except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7 (SOI only ever comes first).
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})
_JPEG_SOS, _JPEG_EOI = 0xDA, 0xD9


def spec_to_proto(spec: FeatureSpec) -> pb.TensorSpec:
    """A feature spec as the wire's ``TensorSpec``."""
    return pb.TensorSpec(name=spec.name, dtype=spec.dtype, shape=list(spec.shape))


def spec_from_proto(msg: pb.TensorSpec) -> FeatureSpec:
    """A wire ``TensorSpec`` as a feature spec (its shape is checked by whoever uses it)."""
    return FeatureSpec(msg.name, msg.dtype, tuple(int(d) for d in msg.shape))


def encode(name: str, array: np.ndarray, jpeg_quality: int | None = None) -> pb.Tensor:
    """Encode an array; ``jpeg_quality`` (1-100) JPEG-encodes a uint8 (H, W, 3) image."""
    array = np.asarray(array)
    if jpeg_quality is not None:
        if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
            raise WireError(f"{name}: JPEG needs a uint8 (H, W, 3) image, got {array.dtype}{list(array.shape)}")
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(array, "RGB").save(buf, format="JPEG", quality=int(jpeg_quality))
        return pb.Tensor(name=name, dtype="uint8", shape=list(array.shape), data=buf.getvalue(), encoding=pb.JPEG)
    if array.dtype.name not in ALLOWED_DTYPES:
        raise WireError(f"{name}: dtype {array.dtype} cannot travel; use one of {', '.join(ALLOWED_DTYPES)}")
    data = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<")).tobytes()
    return pb.Tensor(name=name, dtype=array.dtype.name, shape=list(array.shape), data=data, encoding=pb.RAW)


def decode(msg: pb.Tensor, expected: FeatureSpec | None = None) -> np.ndarray:
    """Decode a tensor, checking it against ``expected`` (name, dtype and shape) when given.

    Returns a read-only array that does not copy the message's bytes for RAW tensors.
    """
    name = msg.name or "<unnamed>"
    shape = tuple(int(d) for d in msg.shape)
    if len(shape) > MAX_DIMS or any(d < 0 for d in shape):
        raise WireError(f"{name}: invalid shape {list(shape)}")
    if msg.dtype not in ALLOWED_DTYPES:
        raise WireError(f"{name}: dtype {msg.dtype!r} is not allowed (allowed: {', '.join(ALLOWED_DTYPES)})")
    if expected is not None:
        if msg.dtype != expected.dtype or shape != expected.shape:
            raise WireError(
                f"{name}: got {msg.dtype}{list(shape)}, registered {expected.dtype}{list(expected.shape)}"
            )
    if msg.encoding == pb.JPEG:
        return _decode_jpeg(name, msg, shape)
    if msg.encoding != pb.RAW:
        raise WireError(f"{name}: unknown encoding {msg.encoding}")
    dtype = np.dtype(msg.dtype).newbyteorder("<")
    need = math.prod(shape) * dtype.itemsize
    if len(msg.data) != need:
        raise WireError(f"{name}: {len(msg.data)} bytes for {msg.dtype}{list(shape)}, expected {need}")
    array = np.frombuffer(msg.data, dtype=dtype).reshape(shape)
    return array if dtype.isnative else array.astype(dtype.newbyteorder("="))


def _decode_jpeg(name: str, msg: pb.Tensor, shape: tuple[int, ...]) -> np.ndarray:
    """Decode a JPEG tensor after checking its declaration, structure and pixel size (all before decoding)."""
    if msg.dtype != "uint8" or len(shape) != 3 or shape[2] != 3:
        raise WireError(f"{name}: a JPEG tensor must be declared uint8 (H, W, 3), got {msg.dtype}{list(shape)}")
    from PIL import Image, UnidentifiedImageError

    if msg.data[:2] == b"\xff\xd8":  # anything else is not a JPEG: PIL names what it is below
        _check_jpeg_structure(name, msg.data)
    try:
        img = Image.open(io.BytesIO(msg.data))  # lazy: reads the header only
        if img.format != "JPEG":
            raise WireError(f"{name}: encoding says JPEG but the data is {img.format or 'not an image'}")
        if img.size != (shape[1], shape[0]):
            raise WireError(f"{name}: JPEG is {img.size[0]}x{img.size[1]}, declared {shape[1]}x{shape[0]}")
        array = np.asarray(img.convert("RGB"))
    except WireError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        raise WireError(f"{name}: cannot decode JPEG: {exc}") from None
    return array


def _check_jpeg_structure(name: str, data: bytes) -> None:
    """Refuse a JPEG (``data`` starts with SOI) that would be expensive to parse or decode; never decodes it.

    Walks the marker segments up to the first scan (SOS), refusing junk between them, more than
    :data:`MAX_JPEG_HEADER_SEGMENTS` of them, and more than one frame header (SOF), then counts the
    scans. Counting SOS markers as the bytes ``FF DA`` is exact enough: inside entropy-coded data a
    0xFF byte is always stuffed as ``FF 00``, so ``FF DA`` there is a marker; elsewhere (a DHT table
    between scans) it can only over-count, never let a scan through uncounted.

    Raises:
        WireError: naming what is wrong (and the count, for too many segments or scans).
    """
    pos, frames = 2, 0
    for _ in range(MAX_JPEG_HEADER_SEGMENTS + 1):
        found = _JPEG_MARKER.match(data, pos)
        if found is None:
            raise WireError(f"{name}: malformed JPEG: no marker at byte {pos}")
        marker, pos = found.group(1)[0], found.end()
        if marker == _JPEG_SOS:
            break
        if marker == _JPEG_EOI:
            raise WireError(f"{name}: malformed JPEG: it ends before its first scan")
        frames += marker in _JPEG_SOF
        if frames > 1:
            raise WireError(f"{name}: JPEG has more than one frame header before its first scan")
        if marker not in _JPEG_STANDALONE:
            length = int.from_bytes(data[pos : pos + 2], "big")
            if length < 2 or pos + length > len(data):
                raise WireError(f"{name}: malformed JPEG: bad segment length {length} at byte {pos}")
            pos += length
    else:
        raise WireError(f"{name}: JPEG has more than {MAX_JPEG_HEADER_SEGMENTS} marker segments before its first scan")
    if frames == 0:
        raise WireError(f"{name}: malformed JPEG: no frame header before its first scan")
    scans = data.count(b"\xff\xda", pos - 2)
    if scans > MAX_JPEG_SCANS:
        raise WireError(f"{name}: JPEG has {scans} scans, more than the {MAX_JPEG_SCANS} allowed")


def decode_all(tensors: Iterable[pb.Tensor], expected: Mapping[str, FeatureSpec]) -> dict[str, np.ndarray]:
    """Decode an observation's tensors: exactly the registered features, each as registered."""
    out: dict[str, np.ndarray] = {}
    for msg in tensors:
        if msg.name not in expected:
            raise WireError(f"unexpected feature {msg.name!r} (registered: {', '.join(sorted(expected))})")
        if msg.name in out:
            raise WireError(f"feature {msg.name!r} sent twice")
        out[msg.name] = decode(msg, expected[msg.name])
    missing = sorted(set(expected) - set(out))
    if missing:
        raise WireError(f"missing feature(s): {', '.join(missing)}")
    return out


def specs_to_proto(specs: Sequence[FeatureSpec]) -> list[pb.TensorSpec]:
    return [spec_to_proto(s) for s in specs]
