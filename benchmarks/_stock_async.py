"""LeRobot's own async inference (0.6.1), instrumented for ``benchmarks/vs_lerobot_async.py``.

Nothing of LeRobot is forked: this launcher imports ``lerobot.async_inference`` and wraps it.

- ``server --port=P [--no_filter] [--cpu_threads=T]`` runs the stock ``policy_server`` (its
  ``serve()`` entry point, its defaults: ``fps=30``, ``inference_latency=1/30`` s,
  ``obs_queue_timeout=2`` s). ``--no_filter`` patches the module's ``observations_similar`` so
  every observation counts as distinct (the "timestep already predicted" check stays).
  ``--environment_state`` adapts the stock server to a policy that reads
  ``observation.environment_state`` (a MetaWorld checkpoint): the stock client concatenates every
  float of the robot into ``observation.state`` and the stock server passes only that and the
  images on, so the adapter moves the robot's ``environment_state.*`` floats from the state into
  ``observation.environment_state`` — the split our client makes (``FeatureMap``). Nothing else
  changes; without it the stock server cannot run such a policy at all.
- ``client SPEC.json`` imports our robots (so the stock draccus parser knows
  ``--robot.type=armory_sim`` and ``metaworld``), parses the stock ``RobotClientConfig`` from
  command-line style arguments, and runs the stock ``RobotClient`` threads (``receive_actions``
  and ``control_loop``) for ``duration_s`` after a start signal (or until a robot with a number of
  episodes has run them). A subclass counts control ticks,
  starved ticks (the action queue was empty at the tick), chunks received, chunk latency
  (observation timestamp -> chunk deserialised, both the client's ``time.time()``) and chunks
  answering an observation this client never sent ("foreign" chunks). On a starved tick it calls
  the robot's ``hold()`` where it has one (MetaWorld: the world steps once a tick, as ours does).
  With ``"episode_reset": true`` in the spec it also gives the stock client what our protocol's
  episode boundary does (stock has none): when the robot's ``episode`` changes, the action queue
  is emptied and a chunk answering an observation taken before the reset is dropped.
  It writes a stats JSON, with the robot's task results (episodes, successes) where it has them.

The stock code logs to ``./logs/``: run both from a scratch directory.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

GO_TIMEOUT_S = 600.0


@dataclass
class Tally:
    """What the instrumented client counts."""

    ticks: int = 0
    starved: int = 0
    settle_chunks: int = 1  # ticks count as "after first" once this many chunks came (the spec's)
    ticks_after_first: int = 0
    starved_after_first: int = 0
    executed: int = 0
    chunks: int = 0
    foreign_chunks: int = 0
    observations_sent: int = 0
    latencies_s: list[float] = field(default_factory=list)
    first_chunk_time: float | None = None
    stale_dropped: int = 0  # chunks of a previous episode dropped (``episode_reset``)


def wait_for_go(ready: Path, go: Path, timeout_s: float = GO_TIMEOUT_S) -> None:
    """Say we are ready (``ready`` file), then wait for the benchmark's ``go`` file."""
    ready.write_text("ready\n")
    deadline = time.monotonic() + timeout_s
    while not go.exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no start signal ({go}) within {timeout_s:.0f} s")
        time.sleep(0.01)


def split_environment_state(convert: Any) -> Any:
    """``convert`` (the stock ``raw_observation_to_observation``) with the robot's
    ``environment_state.*`` floats moved out of ``observation.state`` into
    ``observation.environment_state`` (see the module's docstring)."""
    from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

    from lerobot_armory.robot.features import ENV_STATE_PREFIX

    def wrapped(raw_observation: Any, lerobot_features: dict, policy_image_features: Any) -> Any:
        observation = convert(raw_observation, lerobot_features, policy_image_features)
        names = list(lerobot_features[OBS_STATE]["names"])
        env = [k for k, name in enumerate(names) if name.startswith(ENV_STATE_PREFIX)]
        if env:
            keep = [k for k, name in enumerate(names) if not name.startswith(ENV_STATE_PREFIX)]
            state = observation[OBS_STATE]
            observation[OBS_STATE], observation[OBS_ENV_STATE] = state[:, keep], state[:, env]
        return observation

    return wrapped


def run_server(port: int, no_filter: bool, cpu_threads: int, environment_state: bool = False) -> None:
    """The stock policy server on 127.0.0.1:``port`` (blocks until killed)."""
    if cpu_threads:
        os.environ["OMP_NUM_THREADS"] = str(cpu_threads)  # OpenMP's count is per thread: set it for all
        import torch

        torch.set_num_threads(cpu_threads)
    from lerobot.async_inference import policy_server

    try:  # a π0.5 directory of ours may name a tiny size LeRobot does not ship (a no-op for its own)
        from lerobot_armory.policies import pi05_variants

        pi05_variants.register()
    except ImportError:
        pass
    if no_filter:
        policy_server.observations_similar = lambda *args, **kwargs: False  # type: ignore[assignment]
    if environment_state:
        policy_server.raw_observation_to_observation = split_environment_state(  # type: ignore[assignment]
            policy_server.raw_observation_to_observation
        )
    sys.argv = [sys.argv[0], "--host=127.0.0.1", f"--port={port}"]
    policy_server.serve()


def make_client_class() -> type:
    """``RobotClient`` with counters (a class built after LeRobot is imported)."""
    from lerobot.async_inference.robot_client import RobotClient

    class InstrumentedClient(RobotClient):
        """The stock client; the overrides only count, then call the stock method."""

        def __init__(self, config: Any) -> None:
            super().__init__(config)
            self.tally = Tally()
            self._tally_lock = threading.Lock()
            self._sent: set[tuple[int, float]] = set()
            self.episode_reset = False  # set from the spec: emulate an episode boundary (see the module)
            self._episode = getattr(self.robot, "episode", None)
            self._reset_at = 0.0  # time.time() of the robot's last reset seen

        def send_observation(self, obs: Any) -> bool:
            key = (obs.get_timestep(), obs.get_timestamp())
            with self._tally_lock:
                self._sent.add(key)  # before sending: the answer may come back at once
                self.tally.observations_sent += 1
            return super().send_observation(obs)

        def _aggregate_action_queues(self, incoming_actions: list, aggregate_fn: Any = None) -> None:
            now = time.time()
            if self.episode_reset and incoming_actions and incoming_actions[0].get_timestamp() < self._reset_at:
                with self._tally_lock:
                    self.tally.stale_dropped += 1
                return  # computed from the previous episode's world
            if incoming_actions:
                first = incoming_actions[0]
                with self._tally_lock:
                    t = self.tally
                    t.chunks += 1
                    t.latencies_s.append(now - first.get_timestamp())
                    if (first.get_timestep(), first.get_timestamp()) not in self._sent:
                        t.foreign_chunks += 1
                    if t.first_chunk_time is None:
                        t.first_chunk_time = time.monotonic()
            super()._aggregate_action_queues(incoming_actions, aggregate_fn)

        def actions_available(self) -> bool:
            # Called once per control tick, before the tick's action is taken from the queue.
            if self.episode_reset and getattr(self.robot, "episode", None) != self._episode:
                self._episode = self.robot.episode
                self._reset_at = time.time()
                with self.action_queue_lock:
                    self.action_queue = type(self.action_queue)()  # the old episode's actions: dropped
                self.must_go.set()
            available = super().actions_available()
            if not available and hasattr(self.robot, "hold"):
                self.robot.hold()  # the world does not wait: a starved tick steps it, the arm held
            with self._tally_lock:
                t = self.tally
                t.ticks += 1
                t.starved += not available
                t.executed += available
                if t.chunks >= t.settle_chunks:
                    t.ticks_after_first += 1
                    t.starved_after_first += not available
            return available

    return InstrumentedClient


def robot_args(spec: dict[str, Any]) -> list[str]:
    """The ``--robot.*`` options of this robot (``armory_sim`` unless the spec names ``metaworld``)."""
    if spec.get("robot_kind", "armory_sim") == "metaworld":
        kind = ["--robot.type=metaworld", f"--robot.task={spec['task']}", f"--robot.episodes={spec.get('episodes', 0)}"]
    else:
        kind = ["--robot.type=armory_sim", f"--robot.scene={spec['scene']}", f"--robot.image_size={spec['image_size']}"]
    return [*kind, f"--robot.id={spec['robot_id']}", f"--robot.seed={spec['seed']}"]


def client_args(spec: dict[str, Any]) -> list[str]:
    """The stock client's command line for this robot."""
    return [
        *robot_args(spec),
        f"--server_address={spec['address']}",
        f"--policy_type={spec['policy_type']}",
        f"--pretrained_name_or_path={spec['policy_path']}",
        f"--policy_device={spec['device']}",
        f"--actions_per_chunk={spec['actions_per_chunk']}",
        f"--chunk_size_threshold={spec['chunk_size_threshold']}",
        f"--fps={spec['fps']}",
        f"--aggregate_fn_name={spec.get('aggregate_fn_name', 'weighted_average')}",
    ]


def stats_of(tally: Tally, robot_id: str, wall_s: float, start: float) -> dict[str, Any]:
    """The stats JSON of one stock robot (same keys as the armory side's)."""
    return {
        "robot_id": robot_id,
        "wall_s": wall_s,
        "ticks": tally.ticks,
        "starved_steps": tally.starved,
        "executed_steps": tally.executed,
        "starvation_pct_all": 100.0 * tally.starved / tally.ticks if tally.ticks else 100.0,
        "settle_chunks": tally.settle_chunks,
        "ticks_after_first": tally.ticks_after_first,
        "starved_after_first": tally.starved_after_first,
        "starvation_pct": 100.0 * tally.starved_after_first / tally.ticks_after_first
        if tally.ticks_after_first
        else 100.0,
        "chunks_received": tally.chunks,
        "foreign_chunks": tally.foreign_chunks,
        "stale_episode_chunks": tally.stale_dropped,
        "observations_sent": tally.observations_sent,
        "first_chunk_s": (tally.first_chunk_time - start) if tally.first_chunk_time is not None else None,
        "latency_ms": [1000.0 * x for x in tally.latencies_s],
    }


def run_client(spec_path: str) -> None:
    """One stock robot client, driven by the benchmark's spec file; writes its stats JSON."""
    import draccus
    from lerobot.async_inference.configs import RobotClientConfig

    import lerobot_armory.robot.armory_sim  # noqa: F401  registers --robot.type=armory_sim
    import lerobot_armory.robot.metaworld  # noqa: F401  registers --robot.type=metaworld

    spec = json.loads(Path(spec_path).read_text())
    cfg = draccus.parse(RobotClientConfig, args=client_args(spec))
    client = make_client_class()(cfg)
    client.tally.settle_chunks = int(spec.get("settle_chunks", 1))
    client.episode_reset = bool(spec.get("episode_reset", False))
    if not client.start():
        raise SystemExit(f"stock client {spec['robot_id']}: could not reach the policy server at {spec['address']}")
    wait_for_go(Path(spec["ready_path"]), Path(spec["go_path"]))
    receiver = threading.Thread(target=client.receive_actions, daemon=True)
    control = threading.Thread(target=client.control_loop, kwargs={"task": ""}, daemon=True)
    start = time.monotonic()
    receiver.start()
    control.start()
    deadline = start + spec["duration_s"]
    while time.monotonic() < deadline and not getattr(client.robot, "finished", False):
        time.sleep(0.05)  # polls the robot: a metaworld robot is finished after its episodes
    client.shutdown_event.set()
    control.join(timeout=5.0)
    wall = time.monotonic() - start
    with client._tally_lock:
        stats = stats_of(client.tally, spec["robot_id"], wall, start)
    if hasattr(client.robot, "task_stats"):
        stats.update(client.robot.task_stats())
    Path(spec["stats_path"]).write_text(json.dumps(stats) + "\n")
    client.stop()
    receiver.join(timeout=3.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    srv = sub.add_parser("server", help="the stock policy server")
    srv.add_argument("--port", type=int, required=True)
    srv.add_argument("--no_filter", action="store_true", help="treat every observation as distinct")
    srv.add_argument("--cpu_threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    srv.add_argument(
        "--environment_state", action="store_true", help="pass the robot's environment_state.* floats as the policy's"
    )
    cli = sub.add_parser("client", help="one instrumented stock robot client")
    cli.add_argument("spec", help="JSON spec written by vs_lerobot_async.py")
    args = ap.parse_args()
    if args.what == "server":
        run_server(args.port, args.no_filter, args.cpu_threads, args.environment_state)
    else:
        run_client(args.spec)
        sys.stdout.flush()
        os._exit(0)  # the stock receiver thread may sit in a gRPC call; the stats are written


if __name__ == "__main__":
    main()
