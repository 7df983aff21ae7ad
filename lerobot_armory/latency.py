"""Batched-inference latency profiles ``d_infer(b)``.

A profile is a table of milliseconds by batch size ``1..n``. The published tables of SPEC §5 ship
as named profiles; any other profile is a JSON file::

    {"name": "my-gpu", "device": "H100", "latency_ms": [42.3, 56.0, 66.1]}

(``latency_ms`` may also be an object keyed by batch size: ``{"1": 42.3, "2": 56.0}``.) For
batch sizes beyond the table the latency is extrapolated linearly from the last two points
(:meth:`LatencyProfile.is_extrapolated` says when that happens, and every report says so).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot_armory.errors import ConfigError

# SPEC §5: π0.5 / GR00T N1.7 inference latency measured by the reference system, ms by batch size.
BUILTIN_PROFILES: dict[str, dict[str, Any]] = {
    "l40s-pi05": {"device": "NVIDIA L40S", "policy": "pi0.5", "latency_ms": [73.0, 109.8, 142.4, 177.5, 211.1]},
    "h100-pi05": {"device": "NVIDIA H100", "policy": "pi0.5", "latency_ms": [42.3, 56.0, 66.1, 79.3, 87.2]},
    "l40s-groot": {"device": "NVIDIA L40S", "policy": "GR00T N1.7", "latency_ms": [71.8, 76.5, 83.5, 91.8, 100.9]},
}


@dataclass(frozen=True)
class LatencyProfile:
    """``d_infer(b)`` for batch sizes ``1..len(latency_ms)``, extrapolated linearly beyond.

    Attributes:
        name: profile name (built-in name or file path).
        latency_ms: latency in milliseconds for b = 1, 2, ...; positive and not decreasing.
        device: free text describing where it was measured.
        source: ``builtin``, a file path, or ``profiled`` (measured by the engine).
    """

    name: str
    latency_ms: tuple[float, ...]
    device: str = ""
    source: str = "builtin"

    def __post_init__(self) -> None:
        validate_latencies(self.latency_ms, field="latency_profile")

    @property
    def measured_sizes(self) -> int:
        """Largest batch size that was measured (not extrapolated)."""
        return len(self.latency_ms)

    def is_extrapolated(self, batch_size: int) -> bool:
        """True if ``d_infer(batch_size)`` is extrapolated rather than measured."""
        return batch_size > len(self.latency_ms)

    def latency_s(self, batch_size: int) -> float:
        """``d_infer(b)`` in seconds."""
        return self.latency_ms_for(batch_size) / 1000.0

    def latency_ms_for(self, batch_size: int) -> float:
        """``d_infer(b)`` in milliseconds (linear extrapolation past the table)."""
        if batch_size < 1:
            raise ValueError(f"batch size must be >= 1, got {batch_size}")
        table = self.latency_ms
        if batch_size <= len(table):
            return table[batch_size - 1]
        if len(table) == 1:
            return table[0] * batch_size  # one point: assume no batching gain
        slope = table[-1] - table[-2]
        return table[-1] + slope * (batch_size - len(table))

    def table_s(self, max_batch_size: int) -> list[float]:
        """``[d_infer(1), ..., d_infer(max_batch_size)]`` in seconds (hot paths index this)."""
        return [self.latency_s(b) for b in range(1, max_batch_size + 1)]

    def describe(self, max_batch_size: int) -> str:
        """One line per batch size, marking extrapolated entries."""
        rows = []
        for b in range(1, max_batch_size + 1):
            note = "  (extrapolated linearly from the last two measured points)" if self.is_extrapolated(b) else ""
            rows.append(f"  b={b:<3d} {self.latency_ms_for(b):8.1f} ms{note}")
        return f"latency profile {self.name} ({self.device or 'unknown device'}):\n" + "\n".join(rows)

    def to_json(self) -> dict[str, Any]:
        """The JSON form that :func:`load_profile` reads back."""
        return {"name": self.name, "device": self.device, "latency_ms": list(self.latency_ms)}

    def save(self, path: str | Path) -> None:
        """Write the profile as JSON."""
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")


def validate_latencies(values: Sequence[Any], field: str) -> None:
    """Raise :class:`ConfigError` unless ``values`` are positive finite and not decreasing."""
    if len(values) == 0:
        raise ConfigError(field, "the latency table is empty (need one entry per batch size from 1)")
    for b, v in enumerate(values, start=1):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ConfigError(field, f"latency for batch size {b} must be a positive number of ms, got {v!r}")
    for b in range(1, len(values)):
        if values[b] < values[b - 1]:
            raise ConfigError(
                field,
                f"latency must not decrease with batch size: b={b + 1} ({values[b]} ms) < b={b} ({values[b - 1]} ms)",
            )


def load_profile(name_or_path: str) -> LatencyProfile:
    """A built-in profile by name, or a JSON profile file by path.

    Raises:
        ConfigError: unknown name, unreadable or malformed file, or an invalid table.
    """
    field = "latency_profile"
    if name_or_path in BUILTIN_PROFILES:
        entry = BUILTIN_PROFILES[name_or_path]
        return LatencyProfile(name_or_path, tuple(entry["latency_ms"]), entry["device"], "builtin")
    path = Path(name_or_path)
    if not path.is_file():
        raise ConfigError(
            field,
            f"{name_or_path!r} is neither a built-in profile ({', '.join(BUILTIN_PROFILES)}) nor a JSON file",
        )
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(field, f"cannot read {path} as JSON: {exc}") from None
    if not isinstance(data, dict) or "latency_ms" not in data:
        raise ConfigError(field, f"{path}: expected an object with a 'latency_ms' list or object")
    raw = data["latency_ms"]
    if isinstance(raw, dict):
        by_size: dict[int, Any] = {}
        for key, value in raw.items():
            try:
                size = int(key)
            except ValueError:
                raise ConfigError(field, f"{path}: latency_ms keys must be batch sizes (integers), got {key!r}") from None
            if size in by_size:
                raise ConfigError(field, f"{path}: batch size {size} appears twice in latency_ms")
            by_size[size] = value
        sizes = sorted(by_size)
        if sizes != list(range(1, len(sizes) + 1)):
            raise ConfigError(field, f"{path}: latency_ms must cover batch sizes 1..n without gaps, got {sizes}")
        values = [by_size[b] for b in sizes]
    elif isinstance(raw, list):
        values = raw
    else:
        raise ConfigError(field, f"{path}: latency_ms must be a list or an object, got {type(raw).__name__}")
    validate_latencies(values, field)
    return LatencyProfile(str(data.get("name") or path.stem), tuple(float(v) for v in values), str(data.get("device", "")), str(path))
