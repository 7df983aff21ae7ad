"""The one Engine protocol: what the serving loop calls, and nothing else."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from lerobot_armory.engine.emulation import EmulatedLatencyEngine
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.protocol import Engine, UnguidedEngine, noise_seed
from lerobot_armory.inference_latency import LatencyProfile
from tests.support.echo import EchoEngine


@pytest.mark.parametrize("engine_class", [PolicyEngine, EmulatedLatencyEngine, EchoEngine])
def test_every_engine_has_the_whole_protocol_with_its_signatures(engine_class):
    for name in ("infer", "infer_guided"):
        ours = list(inspect.signature(getattr(engine_class, name)).parameters)[1:]
        assert ours == list(inspect.signature(getattr(Engine, name)).parameters)[1:], (engine_class.__name__, name)


def test_every_engine_states_whether_it_guides_chunks(engine):
    """``rtc`` is part of the protocol (the loop reads it, never probes for it)."""
    profile = LatencyProfile("p", (1.0,))
    for instance in (engine, EchoEngine(), EmulatedLatencyEngine(EchoEngine(), profile), EmulatedLatencyEngine(engine, profile)):
        assert instance.rtc is None, type(instance).__name__  # none of these was built with --rtc.enabled


def test_every_engine_states_how_many_observations_a_row_needs(engine):
    """``history_steps`` is part of the protocol too: the fleet keeps that many per robot."""
    profile = LatencyProfile("p", (1.0,))
    for instance in (engine, EchoEngine(), EmulatedLatencyEngine(EchoEngine(), profile), EmulatedLatencyEngine(engine, profile)):
        assert instance.history_steps == 1, type(instance).__name__  # none of these reads a history


def test_an_unguided_engine_says_why_it_cannot_guide():
    echo = EchoEngine()
    assert echo.rtc is None
    with pytest.raises(RuntimeError, match="EchoEngine does not guide chunks"):
        echo.infer_guided([], [], None, [])
    assert isinstance(echo, UnguidedEngine)


def test_the_emulated_engine_passes_seeds_and_rtc_through():
    seen = []

    class Seeded(UnguidedEngine):
        def infer(self, observations, tasks, noise_seeds=None, history=None):
            seen.append(list(noise_seeds))
            return np.zeros((len(observations), 2, 1), np.float32)

    engine = EmulatedLatencyEngine(Seeded(), LatencyProfile("p", (1.0, 1.0)), sleep=lambda s: None)
    assert engine.rtc is None
    engine.infer([{}, {}], ["", ""], [noise_seed("a", 1), noise_seed("b", 1)])
    assert seen == [[noise_seed("a", 1), noise_seed("b", 1)]]
    assert noise_seed("a", 1) != noise_seed("b", 1) and 0 <= noise_seed("a", 1) < 2**32
