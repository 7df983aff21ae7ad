"""Shared by the VLA tests (π0.5, π0, SmolVLA): armory_sim-shaped observations, robots with their own
prompt, the check that served chunks equal each robot's chunk computed alone, and the static
samplers' checks (equal to LeRobot's, padding-safe, one traced graph with no host sync)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.robot.connection import Connection
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.engine.emulation import EmulatedLatencyEngine
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine import rtc
from lerobot_armory.engine.protocol import noise_seed
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from tests.support.pusher import wait_for

STATE = "observation.state"
IMAGE = "observation.images.front"
TASKS = ("pick up the red block", "sort the bricks by colour", "reach the moving target")


def observation(robot: int, index: int) -> dict[str, np.ndarray]:
    """A distinct, reproducible armory_sim-shaped observation per (robot, index)."""
    rng = np.random.default_rng(1000 * robot + index)
    return {STATE: rng.uniform(-1, 1, 2).astype(np.float32), IMAGE: rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)}


def rtc_batch(b: int, seed: int = 0) -> tuple[list, list[str], list[int], list[rtc.Prefix | None]]:
    """b robots' observations, prompts (of different lengths), noise seeds and RTC prefixes (every
    third robot without one; leftovers of every length, delays 0..4)."""
    rng = np.random.default_rng(seed + b)
    obs = [observation(k + seed, k) for k in range(b)]
    tasks = [TASKS[k % 3] + " now" * k for k in range(b)]
    seeds = [noise_seed(f"robot{k}", seed) for k in range(b)]
    prefixes = [
        None if k % 3 == 0 else rtc.Prefix(rng.uniform(-1, 1, (int(rng.integers(1, 11)), 2)).astype(np.float32), int(rng.integers(0, 5)))
        for k in range(b)
    ]
    return obs, tasks, seeds, prefixes


def assert_static_equals_lerobot(lerobot: PolicyEngine, static: PolicyEngine, b: int) -> None:
    """``static`` (a static sampler, buckets padding b) serves :func:`rtc_batch` (b) as ``lerobot``
    (LeRobot's sampler) does, fp32, 1e-5: unguided, guided per row, and the guidance did something."""
    obs, tasks, seeds, prefixes = rtc_batch(b)
    np.testing.assert_allclose(static.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5, rtol=0)
    actions, model_actions = static.infer_guided(obs, tasks, seeds, prefixes)
    want_actions, want_model = lerobot.infer_guided(obs, tasks, seeds, prefixes)
    np.testing.assert_allclose(model_actions, want_model, atol=1e-5, rtol=0)
    np.testing.assert_allclose(actions, want_actions, atol=1e-5, rtol=0)
    if any(p is not None for p in prefixes):  # the guidance did something
        assert np.abs(static.infer(obs, tasks, seeds) - actions).max() > 1e-3


def sampler_inputs(engine: PolicyEngine, b: int, seed: int = 0, guided: bool = True, horizon: int = 8) -> Any:
    """The static sampler's inputs for :func:`rtc_batch` (b, seed) as ``engine`` builds them (RTC
    inputs when ``guided``, else none)."""
    obs, tasks, seeds, prefixes = rtc_batch(b, seed)
    kwargs = {"noise": engine._noise(seeds)}
    if guided:
        kwargs.update(rtc.guidance_kwargs(prefixes, engine.chunk_size, horizon, "cpu"))
    inputs = engine._sampler_inputs(engine.preprocessor({**engine.to_batch(obs), "task": tasks}), kwargs)
    if not guided:
        inputs.rtc_weights = inputs.rtc_leftover = None
    return inputs


@contextlib.contextmanager
def nan_allocations() -> Iterator[None]:
    """Every floating-point tensor made by ``torch.empty`` or ``Tensor.new_empty`` inside comes
    filled with NaN (what a GPU's reused memory may hold): a sampler that reads memory it never
    wrote gives NaN or other chunks."""
    import torch

    empty, new_empty = torch.empty, torch.Tensor.new_empty

    def nan(t: Any) -> Any:
        return t.fill_(float("nan")) if t.is_floating_point() else t

    torch.empty = lambda *a, **kw: nan(empty(*a, **kw))
    torch.Tensor.new_empty = lambda self, *a, **kw: nan(new_empty(self, *a, **kw))
    try:
        yield
    finally:
        torch.empty, torch.Tensor.new_empty = empty, new_empty


def assert_unwritten_memory_never_reaches_a_chunk(sampler: Any, lerobots_order: Any, inputs: Any) -> None:
    """``sampler``'s chunks for ``inputs`` are the same bit for bit with every fresh allocation
    filled with NaN (:func:`nan_allocations`), and within 1e-5 of ``lerobots_order``'s."""
    import torch

    with torch.no_grad():
        expected = sampler.sample(inputs)  # the per-policy constants made too, before memory turns to NaN
        with nan_allocations():
            chunks = sampler.sample(inputs)
        reference = lerobots_order.sample(inputs)
    assert torch.isfinite(chunks).all()
    torch.testing.assert_close(chunks, expected, atol=0, rtol=0)
    torch.testing.assert_close(chunks, reference, atol=1e-5, rtol=0)


def assert_padding_never_changes_a_real_row(static: PolicyEngine) -> None:
    """Three real rows padded to 4 with their own last row, with another robot's row, or with a
    row of extreme values (state, image, noise, RTC leftover and weight): the real rows' chunks
    are bit for bit the same."""
    import torch

    inputs = sampler_inputs(static, 4, seed=9)
    sample = static.sampler.sample
    with torch.inference_mode():
        own = sample(inputs.with_tensors([t[:3] for t in inputs.tensors()]).padded(4))[:3]
        wild = inputs.with_tensors([t.clone() for t in inputs.tensors()])
        assert wild.rtc_leftover is not None and wild.rtc_weights is not None
        wild.noise[3], wild.images[0][3] = 1e4, 1.0
        wild.rtc_leftover[3], wild.rtc_weights[3] = -1e4, 1.0
        if wild.state is not None:
            wild.state[3] = 1e6
        assert torch.equal(own, sample(inputs)[:3]) and torch.equal(own, sample(wild)[:3])


@contextlib.contextmanager
def three_steps(policy: Any) -> Iterator[None]:
    """The policy's config asks for three denoising steps while a sampler is built inside (π0 /
    π0.5's ``num_inference_steps``, SmolVLA's ``num_steps``): the first, a middle and the last
    step, each the same operations, unrolled in a trace. Ten cost the trace tests ~25 s each."""
    name = "num_steps" if hasattr(policy.config, "num_steps") else "num_inference_steps"
    old = getattr(policy.config, name)
    setattr(policy.config, name, 3)
    try:
        yield
    finally:
        setattr(policy.config, name, old)


def assert_traces_as_one_graph_with_no_host_sync(sampler: Any, static: PolicyEngine, lerobot: PolicyEngine, guided: bool) -> None:
    """What predicts a CUDA graph capture, on the CPU: for every bucket 1, 2, 4, 8, dynamo traces
    ``sampler.sample`` (vision tower, prefix, every step, RTC when ``guided``) as one graph with no
    break, its compiled form gives the same chunks, and no op in it waits for the host; LeRobot's
    own sampler, counted the same way, waits (so the check can fail)."""
    import torch
    import torch._dynamo

    from lerobot_armory.acceleration.op_trace import OpTrace

    sampler.prepare()  # the constants exist before the region is traced or recorded
    for b in (1, 2, 4, 8):
        inputs = sampler_inputs(static, b, guided=guided)
        torch._dynamo.reset()
        graphs: list[Any] = []

        def counted(gm: Any, _example_inputs: Any) -> Any:
            graphs.append(gm)
            return gm.forward  # run as traced (dynamo's "eager" backend)

        # One trace a bucket: fullgraph=True raises at the first graph break, with its reason, and
        # the backend counts the graphs dynamo hands over (``torch._dynamo.explain`` traced twice).
        with torch.inference_mode():
            compiled = torch.compile(sampler.sample, fullgraph=True, backend=counted, dynamic=False)
            traced = compiled(inputs)
            with OpTrace() as trace:
                eager = sampler.sample(inputs)
        assert len(graphs) == 1, graphs
        torch.testing.assert_close(traced, eager, atol=0, rtol=0)
        assert not trace.host_syncs, dict(trace.host_syncs)
        assert trace.launches > 100
    obs, tasks, seeds, _ = rtc_batch(2)
    with torch.inference_mode(), OpTrace() as theirs:
        lerobot.forward(lerobot.preprocessor({**lerobot.to_batch(obs), "task": tasks}), {"noise": lerobot._noise(seeds)})
    assert theirs.host_syncs["aten.lift_fresh.default"] >= 2 * sampler.num_steps  # torch.tensor(list) per step


class PromptRobot:
    """A robot double with its own prompt that pushes reproducible observations and keeps chunks."""

    def __init__(self, address: str, engine: PolicyEngine, k: int, task: str) -> None:
        self.k, self.task, self.robot_id = k, task, f"prompt{k}"
        self.conn = Connection(address)
        features = {f.name: (f.dtype, f.shape) for f in engine.wire_features}
        self.conn.register(self.robot_id, features, fps=30, h_min=1, h_max=10, task=task)
        self.chunks = []
        self.conn.open_stream(self.chunks.append)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # An honest robot: its index moves only over actions it received (the server caps an index
        # that runs ahead of the chunks it sent), at most once per tick of its 30 fps.
        index = 0
        while not self._stop.is_set():
            self.conn.send_observation(index, observation(self.k, index))
            if any(c.i_start <= index < c.i_start + 10 for c in list(self.chunks)):
                index += 1
            time.sleep(0.035)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.conn.close()


def serve_prompt_robots(engine: PolicyEngine, tasks: list[str], max_batch_size: int = 3) -> tuple[ArmoryServer, list[PromptRobot]]:
    """A real server and one :class:`PromptRobot` per task, run until at least 3 batches held
    several robots; returns the stopped server (with its batch log) and the robots.

    Every batch is held to at least 60 ms (emulated latency, longer than a robot's 35 ms between
    observations), so every robot has a new observation waiting when the device frees: batches
    are shared however fast the model runs on this machine (the tiny π0.5 takes ~5 ms, and robots
    served one by one never share a batch)."""
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    profile = LatencyProfile("test", tuple(60.0 + 5.0 * b for b in range(max_batch_size)))
    slow = EmulatedLatencyEngine(engine, profile)
    server = ArmoryServer(slow, info, profile, EarliestDeadlineConfig(), max_batch_size, port=0).start()
    robots = [PromptRobot(server.address, engine, k, task) for k, task in enumerate(tasks)]
    try:
        assert wait_for(lambda: sum(len(b.robots) >= 2 for b in server.batch_log) >= 3, timeout=60), "batches were not shared"
    finally:
        for r in robots:
            r.stop()
        server.stop(grace_s=0.5)
    return server, robots


def assert_shared_chunks_equal_alone(engine: PolicyEngine, server: ArmoryServer, robots: list[PromptRobot], only=None) -> int:
    """Every chunk that was computed in a batch shared with another robot equals the chunk of that
    robot's observation, prompt and noise computed alone. Returns how many were checked (> 0)."""
    by_id = {r.robot_id: r for r in robots if only is None or r.robot_id in only}
    checked = 0
    for record in server.batch_log:
        if len(record.robots) < 2 or not record.ok:
            continue
        for robot_id, i_start in zip(record.robots, record.i_starts, strict=True):
            robot = by_id.get(robot_id)
            chunk = next((c for c in robot.chunks if c.i_start == i_start), None) if robot else None
            if chunk is None:
                continue  # a robot not checked, or a chunk still on its way when the robot stopped
            seed = noise_seed(robot.robot_id, chunk.chunk_id)
            alone = engine.infer([observation(robot.k, i_start)], [robot.task], [seed])[0]
            np.testing.assert_allclose(chunk.actions, alone, atol=1e-5)
            checked += 1
    assert checked > 0, "no chunk from a shared batch was checked"
    return checked


def assert_batched_equals_alone(engine: PolicyEngine) -> None:
    """Three robots' rows, batched, equal each row computed alone with its own prompt and noise,
    and in any order and company (prompts of other lengths pad the batch differently)."""
    obs = [observation(k, 3) for k in range(3)]
    seeds = [noise_seed(f"robot{k}", 5) for k in range(3)]
    together = engine.infer(obs, list(TASKS), seeds)
    for k in range(3):
        alone = engine.infer([obs[k]], [TASKS[k]], [seeds[k]])[0]
        np.testing.assert_allclose(together[k], alone, atol=1e-5)
    mixed = engine.infer([obs[2], obs[0]], [TASKS[2], TASKS[0]], [seeds[2], seeds[0]])
    np.testing.assert_allclose(mixed[0], together[2], atol=1e-5)


def assert_prompt_and_noise_change_the_chunk(engine: PolicyEngine) -> None:
    """Two prompts, and two robots' noise at the same chunk number, give different chunks; the
    same request twice gives the same chunk."""
    obs = observation(0, 0)
    seed = noise_seed("robot0", 1)
    a, b = engine.infer([obs, obs], [TASKS[0], TASKS[1]], [seed, seed])
    assert np.abs(a - b).max() > 1e-4, "two prompts gave the same chunk"
    c, d = engine.infer([obs, obs], [TASKS[0], TASKS[0]], [noise_seed("robot0", 1), noise_seed("robot1", 1)])
    assert np.abs(c - d).max() > 1e-3, "two noise seeds gave the same chunk"
    np.testing.assert_array_equal(engine.infer([obs], [TASKS[0]], [seed]), engine.infer([obs], [TASKS[0]], [seed]))
