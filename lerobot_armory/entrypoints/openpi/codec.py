"""openpi's wire format, decoded strictly: msgpack with numpy arrays as tagged maps. Never pickle.

openpi's ``msgpack_numpy`` packs an array as ``{b"__ndarray__": True, b"data": bytes, b"dtype":
"<f4", b"shape": [..]}`` and a numpy scalar as ``{b"__npgeneric__": True, b"data": value, b"dtype":
...}``. We read exactly that and nothing else: the dtype must be on :data:`ALLOWED_DTYPES` (no
object, void, complex or string arrays), the shape at most :data:`MAX_DIMS` non-negative ints, and
the byte length exactly ``prod(shape) * itemsize`` before ``np.frombuffer`` touches it. msgpack
extension types are refused; sizes of strings, binaries, maps and lists are bounded before they
are allocated (msgpack's own limits, checked as it parses).
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

from lerobot_armory.feature_spec import ALLOWED_DTYPES, MAX_DIMS, WireError

_ARRAY_KEYS = frozenset({b"__ndarray__", b"data", b"dtype", b"shape"})
_SCALAR_KEYS = frozenset({b"__npgeneric__", b"data", b"dtype"})
MAX_CONTAINER_LEN = 4096  # keys of a map / items of a list (an observation has a handful)


def _dtype(value: object) -> np.dtype:
    if not isinstance(value, str) or len(value) > 8:
        raise WireError(f"array dtype must be a short string like '<f4', got {str(value)[:20]!r}")
    try:
        dtype = np.dtype(value)
    except TypeError:
        raise WireError(f"unknown dtype {value!r}") from None
    if dtype.name not in ALLOWED_DTYPES:
        raise WireError(f"dtype {dtype.name} is not allowed (allowed: {', '.join(ALLOWED_DTYPES)})")
    if dtype.byteorder == ">":
        raise WireError(f"big-endian dtype {value!r} is not accepted: send little-endian arrays")
    return dtype


def _array(obj: dict) -> np.ndarray:
    if set(obj) != _ARRAY_KEYS:
        raise WireError(f"an __ndarray__ map must have exactly the keys data, dtype, shape; got {sorted(map(str, obj))[:6]}")
    dtype = _dtype(obj[b"dtype"])
    shape = obj[b"shape"]
    if not isinstance(shape, list | tuple) or len(shape) > MAX_DIMS or not all(isinstance(d, int) and d >= 0 for d in shape):
        raise WireError(f"array shape must be a list of at most {MAX_DIMS} non-negative ints, got {str(shape)[:40]}")
    data = obj[b"data"]
    if not isinstance(data, bytes):
        raise WireError("array data must be binary")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise WireError(f"array of {dtype.name}{list(shape)} needs {expected} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape).copy()  # writable, and not tied to the frame


def _scalar(obj: dict) -> np.generic:
    if set(obj) != _SCALAR_KEYS:
        raise WireError("an __npgeneric__ map must have exactly the keys data and dtype")
    dtype = _dtype(obj[b"dtype"])
    value = obj[b"data"]
    if not isinstance(value, bool | int | float):
        raise WireError("a numpy scalar's data must be a number")
    try:
        return dtype.type(value)
    except (OverflowError, ValueError) as exc:
        raise WireError(f"numpy scalar {value!r} does not fit {dtype.name}: {exc}") from None


def _object_hook(obj: dict) -> Any:
    if b"__ndarray__" in obj:
        return _array(obj)
    if b"__npgeneric__" in obj:
        return _scalar(obj)
    return obj


def _refuse_ext(code: int, data: bytes) -> Any:
    raise WireError(f"msgpack extension type {code} is not accepted")


def unpack(frame: bytes, max_bytes: int) -> Any:
    """Decode one openpi message (:class:`WireError` saying why it does not)."""
    if len(frame) > max_bytes:
        raise WireError(f"message of {len(frame)} bytes is over the limit of {max_bytes}")
    try:
        return msgpack.unpackb(
            frame,
            object_hook=_object_hook,
            ext_hook=_refuse_ext,
            raw=False,
            strict_map_key=True,
            max_str_len=max_bytes,
            max_bin_len=max_bytes,
            max_array_len=MAX_CONTAINER_LEN,
            max_map_len=MAX_CONTAINER_LEN,
            max_ext_len=0,
        )
    except WireError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException, msgpack.ExtraData, RecursionError) as exc:
        raise WireError(f"not a msgpack message openpi's client would send ({type(exc).__name__}: {str(exc)[:120]})") from None


def _default(obj: object) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.name not in ALLOWED_DTYPES:
            raise TypeError(f"cannot send dtype {obj.dtype}")
        arr = np.ascontiguousarray(obj, dtype=obj.dtype.newbyteorder("<"))
        return {b"__ndarray__": True, b"data": arr.tobytes(), b"dtype": arr.dtype.str, b"shape": list(arr.shape)}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send {type(obj).__name__}")


def pack(obj: Any) -> bytes:
    """Encode a reply as openpi's client reads it (``msgpack_numpy.unpackb``)."""
    return msgpack.packb(obj, default=_default, use_bin_type=True)
