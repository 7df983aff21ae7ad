"""``MetaWorldRobot``: a MetaWorld task as a LeRobot ``Robot`` (``--robot.type=metaworld``).

It behaves as a real arm under a fleet's control loop: every control tick the world steps once,
with the action sent that tick or, when none came (the robot starved), with a *hold* (no motion,
the gripper as last commanded) — the world does not wait for the server. After success or the
task's time limit the episode ends, its result is recorded and the next episode starts with the
next seed; :attr:`episode` counts them, so the control loop can tell its server that the world
was reset (:meth:`lerobot_armory.robot.client.ArmoryClient.new_episode`).

Being a LeRobot ``Robot`` (registered as a RobotConfig choice), LeRobot's own async
``robot_client`` can drive it too, which the side-by-side benchmark uses.
"""

from __future__ import annotations

import time
from functools import cached_property
from typing import Any

import numpy as np

from lerobot_armory.robot.features import ENV_STATE_PREFIX
from lerobot_armory.robot.metaworld.config_metaworld import MetaWorldRobotConfig
from lerobot_armory.robot.metaworld.tasks import ACTION_NAMES, STATE_NAMES, MetaWorldTask
from lerobot_armory.robot.simulated import SimulatedRobot


class MetaWorldRobot(SimulatedRobot):
    """Observation: hand xyz and gripper (``observation.state``), the simulator's full state
    (``observation.environment_state``) and, with ``image_size``, the corner camera. Action:
    ``dx, dy, dz, grip`` (MetaWorld's, in [-1, 1])."""

    config_class = MetaWorldRobotConfig
    name = "metaworld"

    def __init__(self, config: MetaWorldRobotConfig) -> None:
        super().__init__(config)
        self.config = config
        self.task: MetaWorldTask | None = None
        self._connected = False
        self._acted = True  # no hold before the first observation
        self._grip = 0.0
        self.episode = 0  # episodes started (the current one's number)
        self.finished = False  # every episode asked for is done: the arm holds
        self.results: list[dict[str, Any]] = []  # one per finished episode: seed, success, ticks
        self.clock = time.monotonic
        self._episode_start = 0.0

    @cached_property
    def observation_features(self) -> dict[str, Any]:
        from lerobot_armory.robot.metaworld.tasks import task_spec

        spec = task_spec(self.config.task)
        feats: dict[str, Any] = {name: float for name in STATE_NAMES}
        feats.update({f"{ENV_STATE_PREFIX}{k}": float for k in range(spec.env_state_dim)})
        if self.config.image_size:
            s = self.config.image_size
            feats[self.config.camera] = (s, s, 3)
        return feats

    @cached_property
    def action_features(self) -> dict[str, type]:
        return {name: float for name in ACTION_NAMES}

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self.task = MetaWorldTask(self.config.task, render_size=self.config.image_size)
        if self.config.image_size:
            self.task.reset(self.config.seed)
            self.task.render()  # a missing renderer fails here, in one line, not mid-run
        self._start_episode()
        self._connected = True

    @property
    def seed(self) -> int:
        """The current episode's seed."""
        return self.config.seed + self.episode

    def _start_episode(self) -> None:
        assert self.task is not None
        self.task.reset(self.seed)
        self._grip = 0.0
        self._episode_start = self.clock()

    def get_observation(self) -> dict[str, Any]:
        task = self._require_connected()
        if not self._acted:
            self.hold()  # no action since the last observation: the robot starved a tick
        self._acted = False
        out: dict[str, Any] = dict(zip(STATE_NAMES, map(float, task.agent_state()), strict=True))
        out.update({f"{ENV_STATE_PREFIX}{k}": float(v) for k, v in enumerate(task.environment_state())})
        if self.config.image_size:
            out[self.config.camera] = task.render()
        return out

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        self._require_connected()
        vector = np.array([float(action[name]) for name in ACTION_NAMES])
        if not np.all(np.isfinite(vector)):
            raise ValueError(f"metaworld robot: action has NaN or inf: {action}")
        vector = np.clip(vector, -1.0, 1.0)
        self._step(vector)
        self._acted = True
        return dict(zip(ACTION_NAMES, map(float, vector), strict=True))

    def hold(self) -> None:
        """One control tick without an action (the robot starved): the world steps, the arm holds
        still with the gripper as last commanded.

        :meth:`get_observation` calls it when no action came since the previous observation, which
        covers a loop that observes every tick (ours). A loop that observes only some ticks
        (LeRobot's async ``robot_client``) calls it on each tick it has no action for.
        """
        self._require_connected()
        self._step(np.array([0.0, 0.0, 0.0, self._grip]))
        self._acted = True

    def _step(self, vector: np.ndarray) -> None:
        task = self.task
        assert task is not None
        if self.finished:
            return  # every episode is done: the arm stays where it is
        self._grip = float(vector[3])
        result = task.step(vector)
        if not result.done:
            return
        self.results.append({
            "episode": self.episode, "seed": self.seed, "success": bool(task.success), "ticks": task.ticks,
            "seconds": self.clock() - self._episode_start,
        })  # fmt: skip
        if self.config.episodes and len(self.results) >= self.config.episodes:
            self.finished = True
            return
        self.episode += 1
        self._start_episode()

    def disconnect(self) -> None:
        self._connected = False
        if self.task is not None:
            self.task.close()
            self.task = None

    def task_stats(self) -> dict[str, Any]:
        """Episodes finished, successes, the success rate, and each episode's result."""
        n = len(self.results)
        wins = sum(r["success"] for r in self.results)
        return {
            "task": self.config.task,
            "episodes_done": n,
            "successes": wins,
            "success_rate": wins / n if n else None,
            "episode_results": list(self.results),
        }

    def _require_connected(self) -> MetaWorldTask:
        if not self._connected or self.task is None:
            raise ConnectionError("metaworld robot is not connected")
        return self.task
