"""Real-time chunking from the mirror: per-robot batched guidance equals LeRobot's own RTC for
one robot, the engine serves it for π0.5, and policies without RTC are refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.engine import rtc
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.options import SCHEDULES, PolicyOptions
from lerobot_armory.engine.protocol import noise_seed
from tests.support.vla import observation


def _toy_denoiser(seed: int = 0):
    """A row-independent velocity field (like a policy's denoiser: rows never mix)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    w = torch.randn(4, 4, generator=g)

    def velocity(x, t):
        return torch.tanh(x @ w + t) - 0.3 * x

    return velocity


@pytest.mark.parametrize("schedule", SCHEDULES)
@pytest.mark.parametrize("time", [1.0, 0.7, 0.1])
def test_each_row_of_a_batched_step_is_lerobots_single_robot_step(schedule, time):
    import torch
    from lerobot.policies.rtc.modeling_rtc import RTCProcessor

    opts = rtc.RTCOptions(enabled=True, execution_horizon=6, max_guidance_weight=7.0, prefix_attention_schedule=schedule)
    ours = rtc.processor_class()(opts.lerobot_config())
    theirs = RTCProcessor(opts.lerobot_config())
    velocity = _toy_denoiser()
    rng = np.random.default_rng(1)
    x_t = torch.from_numpy(rng.standard_normal((4, 10, 4)).astype(np.float32))
    # Different delays, leftover lengths (one shorter than the horizon) and a narrower action
    # space than the model's (LeRobot pads both), and one robot without a prefix.
    prefixes = [
        rtc.Prefix(rng.standard_normal((10, 3)).astype(np.float32), 0),
        rtc.Prefix(rng.standard_normal((5, 3)).astype(np.float32), 3),
        None,
        rtc.Prefix(rng.standard_normal((3, 3)).astype(np.float32), 7),
    ]
    kwargs = rtc.guidance_kwargs(prefixes, 10, opts.execution_horizon, "cpu")
    batched = ours.denoise_step(
        x_t, kwargs["prev_chunk_left_over"], kwargs["inference_delay"], time, lambda x: velocity(x, time), None
    )
    assert ours.calls == 1
    for b, p in enumerate(prefixes):
        row = x_t[b : b + 1]
        if p is None:
            expected = velocity(row, time)
        else:
            expected = theirs.denoise_step(
                row, torch.from_numpy(p.leftover), p.inference_delay, time, lambda x: velocity(x, time), opts.execution_horizon
            )
        torch.testing.assert_close(batched[b : b + 1], expected, rtol=0, atol=1e-6)
    # And the guidance did something where a prefix was given.
    assert not torch.allclose(batched[1], velocity(x_t[1:2], time)[0])


def test_a_plain_delay_is_lerobots_processor_untouched():
    import torch
    from lerobot.policies.rtc.modeling_rtc import RTCProcessor

    opts = rtc.RTCOptions(enabled=True)
    velocity = _toy_denoiser(2)
    x_t = torch.randn(1, 10, 4, generator=torch.Generator().manual_seed(3))
    left = torch.randn(6, 4, generator=torch.Generator().manual_seed(4))
    ours = rtc.processor_class()(opts.lerobot_config()).denoise_step(x_t, left, 2, 0.5, lambda x: velocity(x, 0.5))
    theirs = RTCProcessor(opts.lerobot_config()).denoise_step(x_t, left, 2, 0.5, lambda x: velocity(x, 0.5))
    torch.testing.assert_close(ours, theirs, rtol=0, atol=0)


def test_the_delay_margin_is_added_to_each_predicted_delay():
    prefixes = [rtc.Prefix(np.zeros((10, 2), np.float32), 3), None, rtc.Prefix(np.zeros((4, 2), np.float32), 0)]
    rows = rtc.guidance_kwargs(prefixes, 10, 8, "cpu", delay_margin=1)["inference_delay"]
    assert rows.delays == (4, 0, 1) and rows.horizons == (8, 0, 4) and rows.lengths == (10, 0, 4)
    assert rtc.guidance_kwargs(prefixes, 10, 8, "cpu")["inference_delay"].delays == (3, 0, 0)


def test_options_are_checked():
    for bad in (
        rtc.RTCOptions(enabled=True, delay_margin=-1),
        rtc.RTCOptions(enabled=True, execution_horizon=0),
        rtc.RTCOptions(enabled=True, max_guidance_weight=0),
        rtc.RTCOptions(enabled=True, prefix_attention_schedule="cubic"),
    ):
        with pytest.raises(ConfigError):
            bad.validate()


@pytest.fixture(scope="module")
def guided(pi05_dir):
    import torch

    torch.set_num_threads(1)
    # No delay margin: the delays given are the delays LeRobot is given below.
    return PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), rtc.RTCOptions(enabled=True, execution_horizon=8, delay_margin=0))


def test_a_guided_pi05_batch_equals_lerobots_rtc_for_each_robot_alone(pi05_dir, guided):
    """The whole forward pass: a batch of three robots (two prefixes, one without) against
    LeRobot's stock π0.5 with its stock RTCProcessor, one robot per call."""
    import torch

    from lerobot_armory.engine.loading import load_policy

    obs = [observation(k, k) for k in range(3)]
    tasks = ["touch the target", "hold still", "touch the target"]
    seeds = [noise_seed(f"r{k}", 5) for k in range(3)]
    rng = np.random.default_rng(7)
    prefixes = [
        rtc.Prefix(rng.uniform(-1, 1, (10, 2)).astype(np.float32), 3),
        None,
        rtc.Prefix(rng.uniform(-1, 1, (4, 2)).astype(np.float32), 1),
    ]
    actions, model_actions = guided.infer_guided(obs, tasks, seeds, prefixes)
    assert actions.shape == model_actions.shape == (3, 10, 2)

    config, policy, pre, post = load_policy(str(pi05_dir), "cpu")
    config.rtc_config = rtc.RTCOptions(enabled=True, execution_horizon=8).lerobot_config()
    policy.init_rtc_processor()  # LeRobot's own processor
    assert type(policy.model.rtc_processor).__name__ == "RTCProcessor"
    for k in range(3):
        batch = guided.to_batch([obs[k]])
        batch["task"] = [tasks[k]]
        kwargs = {"noise": guided._noise([seeds[k]])}
        if prefixes[k] is not None:
            kwargs |= {"inference_delay": prefixes[k].inference_delay, "prev_chunk_left_over": torch.from_numpy(prefixes[k].leftover)}
        with torch.no_grad():
            alone = policy.predict_action_chunk(pre(batch), **kwargs)
        np.testing.assert_allclose(model_actions[k], alone[0].numpy(), atol=2e-5)
        np.testing.assert_allclose(actions[k], post(alone)[0].numpy(), atol=2e-5)
    # The guidance pulled the delayed steps onto the leftover (the point of it all).
    first = prefixes[0]
    assert np.abs(model_actions[0, :3] - first.leftover[:3]).max() < 0.05
    unguided = guided.infer(obs[:1], tasks[:1], seeds[:1])
    assert np.abs(unguided[0, :3] - actions[0, :3]).max() > 0.05


def test_guided_profiling_includes_the_guidance(guided):
    profile = guided.profile(2, warmup=0, reps=1, log_progress=False)
    assert profile.name == "profiled:pi05+rtc"
    assert len(profile.latency_ms) == 2 and all(ms > 0 for ms in profile.latency_ms)
    before = guided.rtc.calls
    guided.profile(1, warmup=0, reps=1, log_progress=False)
    assert guided.rtc.calls > before  # profiled batches were guided ones


def test_rtc_on_a_policy_without_it_is_refused_in_one_line(demo_policy_dir):
    with pytest.raises(ConfigError) as err:
        PolicyEngine(PolicyOptions(str(demo_policy_dir), "cpu"), rtc.RTCOptions(enabled=True))
    message = str(err.value)
    assert "act policies do not support real-time chunking" in message and "\n" not in message


def test_infer_guided_needs_rtc(engine):
    with pytest.raises(RuntimeError, match="rtc.enabled"):
        engine.infer_guided([engine.example_observation(0)], ["x"], None, [None])


# ---- the mirror's prediction of each request's prefix (pure) ----------------------------------


def _mirror(fps: float = 10.0, h_max: int = 10):
    from lerobot_armory.mirror import RobotMirror
    from lerobot_armory.robot_spec import RobotSpec

    return RobotMirror(RobotSpec("r", fps, 10, 1, h_max))


def _book(m, index: int, t: float, arrival: float):
    """Observation ``index`` captured and received at ``t``; its chunk dispatched at once and
    predicted to arrive at ``arrival``."""
    assert m.on_observation(index, t, t)
    chunk = m.on_dispatch(t)
    m.on_complete(chunk, t)
    chunk.t_arrival = arrival
    return chunk


def test_prefix_follows_the_chunk_in_hand_until_the_new_one_arrives():
    m = _mirror()
    a = _book(m, 0, 0.0, 0.0)  # in hand from the start: covers 0..9
    c = _book(m, 3, 0.3, 0.3 + 0.25)  # arrives 2.5 ticks later: at the 3rd tick
    p = m.prefix_of(c)
    assert p.inference_delay == 3  # indices 3, 4, 5 come from A
    assert p.segments == ((a.chunk_id, 3, 7),)  # and A would go on to its end


def test_prefix_switches_to_a_chunk_in_flight_as_the_robot_will():
    m = _mirror()
    a = _book(m, 0, 0.0, 0.0)  # covers 0..9
    b = _book(m, 4, 0.4, 0.75)  # covers 4..13, lands before tick 2 of the next grid
    c = _book(m, 6, 0.6, 1.0)  # lands at tick 4
    p = m.prefix_of(c)
    assert p.inference_delay == 4
    # Index 6 from A (B not there yet at tick 0, nor at tick 1), then B from index 8 to its end.
    assert p.segments == ((a.chunk_id, 6, 2), (b.chunk_id, 4, 6))
    assert p.length == 8


def test_prefix_of_a_robot_that_runs_dry_first():
    m = _mirror(h_max=5)
    a = _book(m, 0, 0.0, 0.0)  # the robot may execute 0..4 of it
    c = _book(m, 3, 0.3, 1.0)  # arrives 7 ticks later: the robot starves after index 4
    p = m.prefix_of(c)
    assert p.inference_delay == 2 and p.segments == ((a.chunk_id, 3, 2),)


def test_no_prefix_for_a_first_chunk_and_none_taken_late():
    m = _mirror()
    c = _book(m, 0, 0.0, 0.2)
    assert m.prefix_of(c) is None
    assert m.on_observation(2, 0.3, 0.3)
    with pytest.raises(ValueError):
        m.prefix_of(c)


# ---- served live: each robot's prefix comes from what the server sent it ----------------------


class _Recording:
    """The guided engine, recording every guided batch (the loop only sees ``rtc`` and the calls)."""

    history_steps = 1
    unrecorded_batches = 0

    def __init__(self, engine: PolicyEngine) -> None:
        self.engine, self.rtc, self.batches = engine, engine.rtc, []

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        return self.engine.infer(observations, tasks, noise_seeds, history)

    def infer_guided(self, observations, tasks, noise_seeds, prefixes):
        out = self.engine.infer_guided(observations, tasks, noise_seeds, prefixes)
        self.batches.append((list(observations), list(tasks), list(noise_seeds), list(prefixes), out))
        return out


def test_served_chunks_are_guided_by_what_each_robot_was_sent(guided):
    from lerobot_armory.inference_latency import LatencyProfile
    from lerobot_armory.schedulers import EarliestDeadlineConfig
    from lerobot_armory.entrypoints.server import ArmoryServer
    from lerobot_armory.entrypoints.grpc.service import PolicyInfo
    from tests.support.pusher import wait_for
    from tests.support.vla import PromptRobot

    recording = _Recording(guided)
    info = PolicyInfo(guided.description, guided.wire_features, guided.action_names, guided.chunk_size)
    profile = LatencyProfile("test", (30.0, 35.0, 40.0))
    server = ArmoryServer(recording, info, profile, EarliestDeadlineConfig(), 3, port=0).start()
    robots = [PromptRobot(server.address, guided, k, "touch the target") for k in range(3)]
    try:
        assert wait_for(lambda: sum(p is not None for b in recording.batches for p in b[3]) >= 12, timeout=90)
    finally:
        for r in robots:
            r.stop()
        server.stop(grace_s=0.5)
    # Every robot's chunks in the order sent, with the policy-space actions the server kept.
    sent: dict[int, list[tuple[int, np.ndarray]]] = {}
    by_seed = {noise_seed(r.robot_id, c): (r, c) for r in robots for c in range(500)}
    checked = shared = 0
    for obs, tasks, seeds, prefixes, (actions, model_actions) in recording.batches:
        shared += len(seeds) > 1 and any(p is not None for p in prefixes)
        for k, (seed, prefix) in enumerate(zip(seeds, prefixes, strict=True)):
            robot, chunk_id = by_seed[seed]
            received = next((c for c in robot.chunks if c.chunk_id == chunk_id), None)
            i_start = received.i_start if received is not None else None  # None: still on its way at the stop
            history = sent.setdefault(robot.k, [])
            if prefix is not None and i_start is not None:
                # Row 0 of the leftover is the action at i_start of a chunk this robot was sent.
                candidates = [m[i_start - s] for s, m in history if s <= i_start < s + len(m)]
                assert any(np.allclose(prefix.leftover[0], c) for c in candidates)
                assert 0 <= prefix.inference_delay <= guided.chunk_size
                # And the served chunk is that robot's guided chunk computed alone.
                alone, _ = guided.infer_guided([obs[k]], [tasks[k]], [seed], [prefix])
                np.testing.assert_allclose(actions[k], alone[0], atol=2e-5)
                checked += 1
            if i_start is not None:
                history.append((i_start, model_actions[k]))
    assert checked >= 6 and shared >= 1


def test_the_planner_blends_the_leftover_into_its_plan_as_rtc_weighs_it(tmp_path):
    """armory_planner's RTC contract: the delayed steps are the leftover's, then a linear fade
    to the fresh (closed-loop) plan at the execution horizon, per row."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    path = tmp_path / "planner"
    make_demo_policy(DemoPolicyConfig(output=str(path), kind="planner", chunk_size=10, image_size=32))
    engine = PolicyEngine(PolicyOptions(str(path), "cpu"), rtc.RTCOptions(enabled=True, execution_horizon=6, delay_margin=0))
    obs = engine.example_observation(0)
    leftover = np.stack([np.linspace(0.1, 0.5, 10), np.zeros(10)], axis=1).astype(np.float32)
    actions, model = engine.infer_guided([obs, obs], ["t", "t"], None, [rtc.Prefix(leftover, 3), None])
    plain = engine.infer([obs], ["t"])[0]
    np.testing.assert_allclose(actions[0, :3], leftover[:3], atol=1e-6)  # held: executed anyway
    for k, w in ((3, 3 / 4), (4, 2 / 4), (5, 1 / 4)):  # LeRobot's LINEAR ramp from d = 3 to horizon 6
        np.testing.assert_allclose(actions[0, k], w * leftover[k] + (1 - w) * plain[k], atol=1e-6)
    np.testing.assert_allclose(actions[0, 6:], plain[6:], atol=1e-6)  # closed loop again
    np.testing.assert_allclose(actions[1], plain, atol=1e-6)  # the row without a prefix: unchanged
    np.testing.assert_allclose(model, actions, atol=1e-6)  # identity normalisation
