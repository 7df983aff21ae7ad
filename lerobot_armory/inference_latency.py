"""Batched-inference latency profiles ``d_infer(b)``.

A profile is a table of milliseconds by batch size ``1..n``. The published tables of docs/spec.md §5 ship
as named profiles; any other profile is a JSON file::

    {"name": "my-gpu", "device": "H100", "latency_ms": [42.3, 56.0, 66.1]}

(``latency_ms`` may also be an object keyed by batch size: ``{"1": 42.3, "2": 56.0}``.) For
batch sizes beyond the table the latency is extrapolated linearly from the last two points
(:meth:`LatencyProfile.is_extrapolated` says when that happens, and every report says so).

A profile measured once at start-up can be wrong for the rest of the run (a busy machine, another
process on the GPU, thermal throttling). :class:`OnlineLatency` starts from such a profile and
learns ``d_infer(b)`` from the batches the server actually serves; like the mirror and the
schedulers it is pure code with no clock of its own: whoever measures a batch feeds it.
"""

from __future__ import annotations

import json
import math
import statistics
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot_armory.errors import ConfigError

# docs/spec.md §5: π0.5 / GR00T N1.7 inference latency measured by the reference system, ms by batch size;
# then our engine's own, measured on a GPU.
BUILTIN_PROFILES: dict[str, dict[str, Any]] = {
    "l40s-pi05": {"device": "NVIDIA L40S", "policy": "pi0.5", "latency_ms": [73.0, 109.8, 142.4, 177.5, 211.1]},
    "h100-pi05": {"device": "NVIDIA H100", "policy": "pi0.5", "latency_ms": [42.3, 56.0, 66.1, 79.3, 87.2]},
    "l40s-groot": {"device": "NVIDIA L40S", "policy": "GR00T N1.7", "latency_ms": [71.8, 76.5, 83.5, 91.8, 100.9]},
    # Our own engine (static sampler, CUDA graphs, the defaults of 2026-11-27), LIBERO inputs, random
    # weights, measured through the engine by benchmarks/gpu_profile.py (docs/results/gpu/h200_*.json);
    # π0's with its vision tower still float32 (bf16 became the default after that run).
    "h200-pi05-graphs": {"device": "NVIDIA H200", "policy": "pi0.5 (armory graphs)", "latency_ms": [27.16, 32.95, 39.93, 45.5, 53.02, 62.89, 67.54, 74.33]},
    "h200-pi0-graphs": {"device": "NVIDIA H200", "policy": "pi0 (armory graphs)", "latency_ms": [28.0, 37.38, 45.78, 55.01, 65.03, 70.4, 77.95, 86.56]},
    "h200-smolvla-graphs": {"device": "NVIDIA H200", "policy": "SmolVLA (armory graphs)", "latency_ms": [20.2, 26.48, 31.61, 35.84, 40.42, 46.39, 50.98, 56.64]},
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


@dataclass(frozen=True)
class LatencyDrift:
    """One batch size: the start-up ``d_infer(b)`` against the estimate the scheduler uses now.

    Attributes:
        batch_size: b.
        startup_ms: the start-up profile's value.
        current_ms: the current estimate.
        samples: accepted samples of this size in the estimator's window.
        measured: True if ``current_ms`` comes from this size's own recent samples; False if it is
            fitted from other sizes (or still the start-up value).
    """

    batch_size: int
    startup_ms: float
    current_ms: float
    samples: int
    measured: bool

    @property
    def pct(self) -> float:
        """Relative change from start-up, in % (positive: slower than profiled)."""
        return 100.0 * (self.current_ms - self.startup_ms) / self.startup_ms


class OnlineLatency:
    """``d_infer(b)`` for b = 1..cap, learnt online from served batches and seeded with a profile.

    Feed :meth:`observe` with every successfully served batch; read :meth:`table_s`. The estimate:

    * **per size**: the median of the last ``window`` accepted samples, used once a size has
      ``min_samples`` of them and has been served within the last ``stale_after`` batches;
    * **outliers**: a sample more than ``outlier_factor`` times above (or below) its size's median
      is held aside, so one hiccup never moves the table. Only ``confirm`` consecutive outliers in
      the same direction are taken as a real change of speed: they replace the window. A milder
      change moves the median after ``window // 2 + 1`` samples. Either way a genuine step change
      is followed within a bounded number of batches of that size;
    * **other sizes**: sizes without a usable estimate are fitted. With one measured size the
      start-up profile is rescaled to it (its shape kept); with two or more, a Theil-Sen line
      ``a + slope * b`` through the measured sizes (median of pairwise slopes: robust to one bad
      size). Fitted values are clipped between their measured neighbours, and below the smallest
      measured size to at least ``d(b_min) * b / b_min`` (a smaller batch never costs more per
      robot), which keeps them positive;
    * the table is **positive and non-decreasing** in b (measured medians are raised to their
      predecessor, as start-up profiling does), as :func:`validate_latencies` and the schedulers
      require;
    * the **published** table (what :meth:`table_s` returns) changes only when some entry moved by
      more than ``tolerance`` (relative), so the scheduler is not rewritten for noise.

    Deterministic: the same sample stream gives the same tables. Not thread-safe for writers (one
    thread feeds it); readers get the published table as one immutable snapshot.
    """

    def __init__(
        self,
        profile: LatencyProfile,
        max_batch_size: int,
        window: int = 21,
        min_samples: int = 3,
        outlier_factor: float = 3.0,
        confirm: int = 5,
        stale_after: int = 1000,
        tolerance: float = 0.02,
    ) -> None:
        if max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
        if not 1 <= min_samples <= confirm <= window:
            raise ValueError(f"need 1 <= min_samples <= confirm <= window, got {min_samples}, {confirm}, {window}")
        if not outlier_factor > 1.0 or stale_after < 1 or tolerance < 0:
            raise ValueError("outlier_factor must be > 1, stale_after >= 1, tolerance >= 0")
        self.profile = profile
        self.max_batch_size = max_batch_size
        self.min_samples, self.outlier_factor, self.confirm = min_samples, outlier_factor, confirm
        self.stale_after, self.tolerance = stale_after, tolerance
        self.startup_ms: tuple[float, ...] = tuple(profile.latency_ms_for(b) for b in range(1, max_batch_size + 1))
        self._window: list[deque[float]] = [deque(maxlen=window) for _ in range(max_batch_size)]
        self._suspects: list[list[float]] = [[] for _ in range(max_batch_size)]
        self._last_seen = [-math.inf] * max_batch_size  # observation number of the latest sample
        self._count = 0
        self.rejected = 0  # samples held aside as outliers (some may later confirm a change)
        self._table_ms = self.startup_ms  # published; replaced whole, never mutated
        self._measured: frozenset[int] = frozenset()

    def restart(self, profile: LatencyProfile) -> None:
        """Start over from ``profile`` (a new policy was swapped in: the old samples say nothing)."""
        self.__init__(  # type: ignore[misc]
            profile, self.max_batch_size, self._window[0].maxlen or 21, self.min_samples, self.outlier_factor, self.confirm,
            self.stale_after, self.tolerance,
        )  # fmt: skip

    def lower_cap(self, cap: int) -> None:
        """Cover b = 1..``cap`` only, from now on (the batch cap was lowered: out of memory at a
        larger batch); what was learnt for those sizes is kept."""
        if not 1 <= cap < self.max_batch_size:
            return
        self.max_batch_size = cap
        self.startup_ms = self.startup_ms[:cap]
        del self._window[cap:], self._suspects[cap:], self._last_seen[cap:]
        self._table_ms = self._table_ms[:cap]
        self._measured = frozenset(b for b in self._measured if b <= cap)

    @property
    def observed(self) -> int:
        """Batches fed so far."""
        return self._count

    def observe(self, batch_size: int, seconds: float) -> bool:
        """Record one served batch of ``batch_size`` robots that took ``seconds``.

        Returns True when the published table changed (the caller then copies :meth:`table_s`
        into the scheduler). A non-positive or non-finite time is ignored (it says nothing).
        """
        if not 1 <= batch_size <= self.max_batch_size:
            raise ValueError(f"batch size {batch_size} outside 1..{self.max_batch_size}")
        if not (math.isfinite(seconds) and seconds > 0):
            return False
        ms = seconds * 1000.0
        k = batch_size - 1
        window, suspects = self._window[k], self._suspects[k]
        self._count += 1
        if self._count - self._last_seen[k] > self.stale_after:
            # Not served for long: its old samples describe another machine state; start afresh.
            window.clear()
            suspects.clear()
        self._last_seen[k] = self._count
        if len(window) >= self.min_samples:
            ref = statistics.median(window)
            high, low = ms > ref * self.outlier_factor, ms < ref / self.outlier_factor
        else:
            ref, high, low = ms, False, False  # too few samples to call anything an outlier
        if high or low:
            self.rejected += 1
            if suspects and (suspects[0] > ref) != high:
                suspects.clear()  # the run of outliers changed direction: start counting again
            suspects.append(ms)
            if len(suspects) >= self.confirm:
                # Consecutive outliers all on one side: the machine really changed speed.
                window.clear()
                window.extend(suspects)
                suspects.clear()
        else:
            suspects.clear()
            window.append(ms)
        return self._publish()

    def _fit(self) -> tuple[list[float], frozenset[int]]:
        """The full table in ms from the current windows, and the sizes measured directly."""
        n = self.max_batch_size
        measured: dict[int, float] = {}
        for b in range(1, n + 1):
            window = self._window[b - 1]
            if len(window) >= self.min_samples and self._count - self._last_seen[b - 1] <= self.stale_after:
                # Raised to the previous measured size: a larger batch is never scheduled as cheaper.
                measured[b] = max(statistics.median(window), max(measured.values(), default=0.0))
        if not measured:
            return list(self.startup_ms), frozenset()
        sizes = sorted(measured)
        if len(sizes) == 1:
            scale = measured[sizes[0]] / self.startup_ms[sizes[0] - 1]
            guess = [s * scale for s in self.startup_ms]
        else:
            slope = max(0.0, statistics.median(
                (measured[j] - measured[i]) / (j - i) for x, i in enumerate(sizes) for j in sizes[x + 1 :]
            ))  # fmt: skip
            intercept = statistics.median(measured[b] - slope * b for b in sizes)
            guess = [intercept + slope * b for b in range(1, n + 1)]
        table = []
        b_min = sizes[0]
        for b in range(1, n + 1):
            if b in measured:
                table.append(measured[b])
                continue
            below = [s for s in sizes if s < b]
            above = [s for s in sizes if s > b]
            lo = measured[below[-1]] if below else measured[b_min] * b / b_min
            hi = measured[above[0]] if above else math.inf
            table.append(min(max(guess[b - 1], lo), hi))
        return table, frozenset(sizes)

    def _publish(self) -> bool:
        table, self._measured = self._fit()
        old = self._table_ms
        if all(abs(new - cur) <= self.tolerance * cur for new, cur in zip(table, old, strict=True)):
            return False
        self._table_ms = tuple(table)
        return True

    def table_ms(self) -> tuple[float, ...]:
        """The published ``d_infer(b)`` in ms, b = 1..cap."""
        return self._table_ms

    def table_s(self) -> list[float]:
        """The published ``d_infer(b)`` in seconds, index b-1 (the scheduler's layout)."""
        return [ms / 1000.0 for ms in self._table_ms]

    def drift(self) -> list[LatencyDrift]:
        """Start-up vs current estimate for every batch size."""
        table, measured = self._table_ms, self._measured
        return [
            LatencyDrift(b, self.startup_ms[b - 1], table[b - 1], len(self._window[b - 1]), b in measured)
            for b in range(1, self.max_batch_size + 1)
        ]

    def max_drift(self) -> LatencyDrift:
        """The batch size whose estimate moved furthest from start-up (relative; first on ties)."""
        return max(self.drift(), key=lambda d: abs(d.pct))
