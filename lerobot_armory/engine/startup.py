"""An engine that starts itself for serving: load, warm up every batch size, profile ``d_infer(b)``.

One call, :func:`start_engine`, used by the server at start-up (each policy of ``--policies``),
by every replica of a cluster (they build their server the same way) and by a live swap (which
loads the new checkpoint for the policy's batch cap *at the time of the swap*). A failure on the
device (out of memory at the largest batch, say) is one line naming the batch cap.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from lerobot_armory.engine.emulation import EmulatedLatencyEngine
from lerobot_armory.engine.options import EngineOptions, PolicyOptions, RTCOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.protocol import Engine
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import BUILTIN_PROFILES, LatencyProfile, load_profile

log = logging.getLogger("lerobot_armory.server")
T = TypeVar("T")


@dataclass
class StartedEngine:
    """A policy ready to serve.

    Attributes:
        engine: the loaded policy (its features, chunk size, description).
        serving: what the serving loop calls: ``engine``, or it wrapped in an emulated profile.
        profile: its ``d_infer(b)`` for b = 1..cap (measured, loaded or emulated).
        note: a note for the start-up summary ("" or " (emulated latency)").
    """

    engine: PolicyEngine
    serving: Engine
    profile: LatencyProfile
    note: str = ""


def on_startup_device(what: str, fn: Callable[..., T], *args: object) -> T:
    """Run a start-up pass over every batch size; a failure (CUDA out of memory at the largest
    batch, say) is one line naming the batch cap, not a traceback."""
    try:
        return fn(*args)
    except ConfigError:
        raise
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError("max_batch_size", f"{what} failed: {type(exc).__name__}: {first}") from None


def start_engine(
    options: PolicyOptions,
    max_batch_size: int,
    rtc: RTCOptions | None = None,
    engine_options: EngineOptions | None = None,
    profile_reps: int = 5,
    emulate_profile: str | None = None,
    latency_profile: str | None = None,
    quiet: bool = False,
) -> StartedEngine:
    """Load ``options``' policy, warm up b = 1..``max_batch_size`` and give it its ``d_infer``.

    ``d_infer`` is, in this order: ``emulate_profile`` (every batch then takes exactly its
    time), ``latency_profile`` when it names a built-in profile or an existing file, else measured
    (``profile_reps`` each; saved to ``latency_profile`` when that names a new file). ``quiet``:
    no progress lines (a swap, logged by its own lines).
    """
    say = log.debug if quiet else log.info
    say("loading policy %s ...", options.path)
    engine = PolicyEngine(options, rtc, dataclasses.replace(engine_options) if engine_options else None)
    say("warming up b = 1..%d ...", max_batch_size)
    on_startup_device(f"warming up b = 1..{max_batch_size}", lambda: engine.warmup(max_batch_size, log_progress=not quiet))
    if emulate_profile:
        profile = load_profile(emulate_profile)
        say("emulating latency profile %s: every batch takes exactly d_infer(b)", profile.name)
        return StartedEngine(engine, EmulatedLatencyEngine(engine, profile), profile, " (emulated latency)")
    if latency_profile and (latency_profile in BUILTIN_PROFILES or Path(latency_profile).is_file()):
        profile = load_profile(latency_profile)
        say("latency profile loaded from %s", latency_profile)
        if engine.rtc is not None and not profile.name.endswith("+rtc"):
            log.warning(
                "--rtc.enabled=true with a latency profile not measured with RTC (%s): RTC's guidance makes every "
                "batch slower, so the scheduler will expect chunks too early; profile again with RTC on",
                profile.name,
            )
        return StartedEngine(engine, engine, profile)
    say("profiling d_infer(b) for b = 1..%d (%d reps each)...", max_batch_size, profile_reps)
    profile = on_startup_device(
        f"profiling b = 1..{max_batch_size}", lambda: engine.profile(max_batch_size, 0, profile_reps, log_progress=not quiet)
    )
    if latency_profile:
        profile.save(latency_profile)
        say("latency profile saved to %s", latency_profile)
    return StartedEngine(engine, engine, profile)
