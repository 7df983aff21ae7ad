"""Tensors on the wire: dtype + shape + raw bytes (or JPEG for uint8 RGB images). Never pickle.

Decoding trusts nothing: the dtype must be on a short allow-list, the shape must match what the
robot registered, and the byte length must be exactly ``prod(shape) * itemsize`` before
``np.frombuffer`` touches it. JPEG payloads are checked for their pixel size *before* they are
decoded, so a small file cannot expand into a huge image.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from lerobot_armory.proto import armory_pb2 as pb

# dtypes a tensor may declare; anything else (object, void, strings...) is refused.
ALLOWED_DTYPES = ("float32", "float64", "float16", "uint8", "int8", "int16", "int32", "int64", "bool")
MAX_DIMS = 8


class WireError(ValueError):
    """A tensor or message that does not decode; the message says what is wrong."""


@dataclass(frozen=True)
class FeatureSpec:
    """What one observation feature looks like on the wire."""

    name: str
    dtype: str
    shape: tuple[int, ...]

    def to_proto(self) -> pb.TensorSpec:
        return pb.TensorSpec(name=self.name, dtype=self.dtype, shape=list(self.shape))

    @classmethod
    def from_proto(cls, msg: pb.TensorSpec) -> FeatureSpec:
        return cls(msg.name, msg.dtype, tuple(int(d) for d in msg.shape))

    def describe(self) -> str:
        return f"{self.dtype}{list(self.shape)}"


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
    if msg.dtype != "uint8" or len(shape) != 3 or shape[2] != 3:
        raise WireError(f"{name}: a JPEG tensor must be declared uint8 (H, W, 3), got {msg.dtype}{list(shape)}")
    from PIL import Image, UnidentifiedImageError

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
    return [s.to_proto() for s in specs]
