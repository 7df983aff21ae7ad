"""Swapping the served checkpoint live (``lerobot-armory-admin swap``; issue 35, item 3).

:class:`PolicySwapper` owns the sequence; what loading means (a :class:`PolicyEngine` warmed up
and profiled for the batch cap) is the server's ``loader``, so the serving core neither builds
engines nor speaks gRPC:

1. **load beside** (default): the new checkpoint is loaded, warmed up and profiled on the calling
   thread (an admin RPC's) while the loop keeps serving the old one; both are in memory meanwhile.
2. **check**: what robots depend on must not change: the observation features they send (names,
   dtypes, shapes), the action dimension, the chunk size and the observation history. A
   difference refuses the swap with one line naming it, and the old policy keeps serving.
3. **switch** between two batches (:meth:`ServingLoop.switch`): the batch in flight finishes on
   the old engine and its chunks are queued; every later batch runs on the new engine, and the
   scheduler's ``d_infer`` table becomes the new engine's measured profile. Robots keep executing
   the chunks they hold; no chunk computed by the old checkpoint is queued after the switch.

With ``drain``, dispatching stops first (the in-flight batch completes and its chunks go out),
the old engine is released, and only then is the new one loaded: one policy in memory at a time,
at the price of a pause in service as long as the load and warm-up (robots see a delay, not an
error). If the new checkpoint then fails, the old one is loaded again and serves on.

A failed load (a broken directory, unreadable weights) leaves the old policy serving and answers
the operator with the reason. One swap at a time; a second one meanwhile is refused.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.engine.protocol import Engine
from lerobot_armory.feature_spec import FeatureSpec
from lerobot_armory.serving.loop import ServingLoop

log = logging.getLogger("lerobot_armory.swap")

# The switch happens at the loop's next batch boundary: at most one batch's time away.
SWITCH_TIMEOUT_S = 120.0
RESULTS = ("ok", "refused", "failed")


@dataclass(frozen=True)
class PolicyShape:
    """What robots depend on: a swap must not change any of it."""

    wire_features: tuple[FeatureSpec, ...]
    action_dim: int
    chunk_size: int
    history_steps: int = 1

    def differences(self, new: PolicyShape) -> list[str]:
        """Every way ``new`` differs from this (served) shape, one phrase each."""
        out = []
        old_f = {f.name: f for f in self.wire_features}
        new_f = {f.name: f for f in new.wire_features}
        for name in sorted(old_f.keys() - new_f.keys()):
            out.append(f"feature {name} is no longer read")
        for name in sorted(new_f.keys() - old_f.keys()):
            out.append(f"feature {name} is new ({new_f[name].describe()})")
        for name in sorted(old_f.keys() & new_f.keys()):
            if old_f[name] != new_f[name]:
                out.append(f"feature {name}: {old_f[name].describe()} -> {new_f[name].describe()}")
        if new.action_dim != self.action_dim:
            out.append(f"action dimension {self.action_dim} -> {new.action_dim}")
        if new.chunk_size != self.chunk_size:
            out.append(f"chunk size {self.chunk_size} -> {new.chunk_size}")
        if new.history_steps != self.history_steps:
            out.append(f"observation history {self.history_steps} -> {new.history_steps} steps")
        return out


@dataclass
class LoadedPolicy:
    """A policy ready to serve: the engine the loop runs, its shape and measured ``d_infer``.

    Attributes:
        options: what loaded it (``--policy.path``, device, overrides).
        engine: what the serving loop calls (may wrap the model, e.g. emulated latency).
        shape: what robots depend on.
        d_infer: seconds for b = 1..cap, the new scheduler table (None: keep the current one).
        description: one line for logs and the status view.
    """

    options: PolicyOptions
    engine: Engine
    shape: PolicyShape
    d_infer: list[float] | None
    description: str = ""

    @property
    def path(self) -> str:
        return self.options.path


@dataclass
class SwapResult:
    """The answer to one swap: ``result`` is ok, refused or failed; ``message`` one line."""

    result: str
    message: str
    old_path: str
    new_path: str
    seconds: float = 0.0
    switched_at_batch: int | None = None

    @property
    def ok(self) -> bool:
        return self.result == "ok"


@dataclass
class SwapCounts:
    """Swaps by result, the last one's time, for metrics and the status line."""

    by_result: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RESULTS, 0))
    last_seconds: float | None = None


class SwapRefused(Exception):
    """Raised by a loader for a checkpoint it will not load (it does not fit in device memory, say)."""


# loader(options, drain, max_batch_size): the cap is the served policy's at the time of the swap
# (an out-of-memory batch may have lowered it since start-up).
Loader = Callable[[PolicyOptions, bool, int], LoadedPolicy]


class PolicySwapper:
    """Swaps the policy the serving loop runs (see the module docstring).

    Args:
        loop: the serving loop.
        current: the policy being served.
        loader: ``loader(options, drain, max_batch_size)`` loads, warms up and profiles a
            checkpoint for the policy's batch cap at the time of the swap; raises
            :class:`SwapRefused` (refused: the checkpoint does not fit, say) or anything else
            (failed: a broken directory).
        on_swap: called with the new :class:`LoadedPolicy` right after the switch.
        policy: the name of the policy it swaps, where the loop serves several (None: the first).
    """

    def __init__(
        self,
        loop: ServingLoop,
        current: LoadedPolicy,
        loader: Loader,
        on_swap: Callable[[LoadedPolicy], None] | None = None,
        policy: str | None = None,
    ) -> None:
        self.loop = loop
        self.policy = policy
        self.current = current
        self.loader = loader
        self.on_swap = on_swap
        self.counts = SwapCounts()
        self.listeners: list[Callable[[SwapResult], None]] = []
        self._lock = threading.Lock()  # one swap at a time

    def swap(self, path: str, overrides: list[str] | None = None, drain: bool = False) -> SwapResult:
        """Load ``path`` (with ``--policy.<field>`` ``overrides``) and serve it from the next batch."""
        old = self.current.path
        if not self._lock.acquire(blocking=False):
            return self._done(SwapResult("refused", "another swap is in progress", old, path))
        try:
            t0 = time.monotonic()
            result = self._swap(path, list(overrides or []), drain)
            result.seconds = time.monotonic() - t0
            return self._done(result)
        finally:
            self._lock.release()

    def _swap(self, path: str, overrides: list[str], drain: bool) -> SwapResult:
        old = self.current
        if not path:
            return SwapResult("refused", "no policy path given", old.path, path)
        options = PolicyOptions(path, old.options.device, old.options.cpu_threads, overrides)
        if not drain:
            new, refusal = self._load(options, drain=False)
            if new is None:
                assert refusal is not None
                return SwapResult(refusal[0], f"{refusal[1]}; {old.path} keeps serving", old.path, path)
            return self._switch(old, new)
        if not self.loop.hold(SWITCH_TIMEOUT_S):
            self.loop.resume()
            return SwapResult("failed", "the in-flight batch did not finish; nothing changed", old.path, path)
        try:
            log.info("swap with drain: dispatching paused, releasing %s before loading %s", old.path, path)
            # The loop lets go of the old engine (it dispatches nothing while held), and so does this object.
            self.loop.switch(_Released(old.engine), None, SWITCH_TIMEOUT_S, self.policy)
            self.current = dataclasses.replace(old, engine=_Released(old.engine))
            old_options, old_shape, old_d_infer, old_description = old.options, old.shape, old.d_infer, old.description
            del old
            gc.collect()
            new, refusal = self._load(options, drain=True)
            if new is not None:
                return self._switch(self.current, new)
            assert refusal is not None
            log.warning("swap to %s %s (%s); loading %s again", path, refusal[0], refusal[1], old_options.path)
            try:
                restored = self.loader(old_options, True, self.loop.cap_of(self.policy))
            except Exception as exc:  # noqa: BLE001 - nothing left to serve with: stop, a supervisor restarts
                why = f"{refusal[1]}; reloading {old_options.path} failed too ({type(exc).__name__}: {exc}): the server stops"
                self.loop.error = RuntimeError(why)
                self.loop.fleet.stop()
                return SwapResult("failed", why, old_options.path, path)
            restored = dataclasses.replace(restored, shape=old_shape, d_infer=restored.d_infer or old_d_infer,
                                           description=restored.description or old_description)  # fmt: skip
            self._switch(self.current, restored)
            return SwapResult(refusal[0], f"{refusal[1]}; {old_options.path} serves again", old_options.path, path)
        finally:
            self.loop.resume()

    def _switch(self, old: LoadedPolicy, new: LoadedPolicy) -> SwapResult:
        switched = self.loop.switch(new.engine, new.d_infer, SWITCH_TIMEOUT_S, self.policy)
        if switched is None:
            return SwapResult("failed", "the serving loop stopped before the switch", old.path, new.path)
        self.current = new
        old_path = old.path
        del old
        gc.collect()  # the old engine's memory goes now, not at the next collection
        if self.on_swap is not None:
            self.on_swap(new)
        return SwapResult("ok", f"serving {new.path} ({new.description})", old_path, new.path, 0.0, switched)

    def _load(self, options: PolicyOptions, drain: bool) -> tuple[LoadedPolicy | None, tuple[str, str] | None]:
        """Load and check; (policy, None) or (None, (result, reason))."""
        try:
            new = self.loader(options, drain, self.loop.cap_of(self.policy))
        except SwapRefused as exc:
            return None, ("refused", str(exc))
        except Exception as exc:  # noqa: BLE001 - any load failure leaves the old policy serving
            first = (str(exc).strip().splitlines() or [""])[0][:300]
            return None, ("failed", f"cannot load {options.path}: {type(exc).__name__}: {first}")
        problems = self.current.shape.differences(new.shape)
        if problems:
            return None, ("refused", f"{options.path} does not fit the robots served: " + "; ".join(problems))
        return new, None

    def _done(self, result: SwapResult) -> SwapResult:
        self.counts.by_result[result.result] += 1
        if result.ok:
            self.counts.last_seconds = result.seconds
            log.info("policy swapped: %s -> %s in %.2f s", result.old_path, result.new_path, result.seconds)
        else:
            log.warning("policy swap %s: %s -> %s: %s", result.result, result.old_path, result.new_path, result.message)
        for listener in self.listeners:
            listener(result)
        return result


class _Released:
    """Stands in for a released engine while a drain holds the loop (never asked to infer)."""

    def __init__(self, engine: Engine) -> None:
        self.rtc = None
        self.history_steps = engine.history_steps
        self.unrecorded_batches = 0

    def infer(self, *args: object, **kwargs: object):
        raise RuntimeError("no policy is loaded (a swap with drain is loading one)")

    infer_guided = infer
