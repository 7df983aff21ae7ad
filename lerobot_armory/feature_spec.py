"""What a policy's observation features look like as tensors: name, dtype, shape.

Plain types, no wire format: the engine states what it expects with them, the serving core keeps
what each robot declared, and the wire (:mod:`lerobot_armory.wire`) converts them to and from
protobuf at the edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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

    def describe(self) -> str:
        return f"{self.dtype}{list(self.shape)}"


def check_features(declared: Sequence[FeatureSpec], expected: Sequence[FeatureSpec]) -> list[str]:
    """Every mismatch between a robot's declared features and the policy's inputs (empty: OK).

    The server checks registrations with it. It lives beside :class:`FeatureSpec` rather than in
    the server so that anything holding a policy's expected features (a robot reading its
    ``RegisterResponse``, the engine, a test) can run the same check without importing the server.

    Images may be declared as uint8 (H, W, 3) or as float32 (3, H, W) in [0, 1].
    """
    problems = []
    exp = {s.name: s for s in expected}
    seen = set()
    for spec in declared:
        if spec.name in seen:
            problems.append(f"feature {spec.name!r} declared twice")
            continue
        seen.add(spec.name)
        want = exp.get(spec.name)
        if want is None:
            problems.append(f"unexpected feature {spec.name!r} {spec.describe()}: the policy does not use it")
            continue
        ok = spec == want
        if not ok and want.dtype == "uint8" and len(want.shape) == 3:  # image: CHW float also fine
            h, w, c = want.shape
            ok = spec.dtype == "float32" and spec.shape == (c, h, w)
        if not ok:
            problems.append(f"feature {spec.name!r}: declared {spec.describe()}, the policy needs {want.describe()}")
    for name in exp:
        if name not in seen:
            problems.append(f"missing feature {name!r}: the policy needs {exp[name].describe()}")
    return problems
