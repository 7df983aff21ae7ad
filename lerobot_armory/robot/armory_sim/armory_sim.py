"""``ArmorySim``: the simulated world as a LeRobot ``Robot`` (``--robot.type=armory_sim``)."""

from __future__ import annotations

import time
from collections import deque
from functools import cached_property
from typing import Any

import numpy as np

from lerobot_armory.robot.armory_sim.config_armory_sim import ArmorySimConfig
from lerobot_armory.robot.armory_sim.world import ArmorySimEnv, WorldParams
from lerobot_armory.robot.simulated import SimulatedRobot

# Longest stretch integrated in one go: a stalled process must not teleport the target.
MAX_DT_S = 0.2


class ArmorySim(SimulatedRobot):
    """Observation: ``x.pos``, ``y.pos`` (effector, workspace units) and one camera image.
    Action: ``x.pos``, ``y.pos`` (where the effector should go). The world advances in real time
    at every :meth:`get_observation`, whether or not an action came (a starving robot's target
    keeps moving)."""

    config_class = ArmorySimConfig
    name = "armory_sim"

    def __init__(self, config: ArmorySimConfig) -> None:
        super().__init__(config)
        self.config = config
        params = WorldParams(
            config.scene, config.image_size, config.max_speed, config.target_speed, config.success_radius, config.attempt_s
        )
        self.env = ArmorySimEnv(params, seed=config.seed)
        self._connected = False
        self._last_time: float | None = None
        self.clock = time.monotonic
        # Action jerk: the third difference of successive commanded actions (per step³, so it
        # does not depend on the control rate); a chunk switch that jumps shows up in it.
        self._recent: deque[np.ndarray] = deque(maxlen=4)
        self._jerk_sum = 0.0
        self._jerk_n = 0
        self._jerk_max = 0.0

    @cached_property
    def observation_features(self) -> dict[str, Any]:
        s = self.config.image_size
        return {"x.pos": float, "y.pos": float, self.config.camera: (s, s, 3)}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return {"x.pos": float, "y.pos": float}

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self.env.reset(seed=self.config.seed)
        self._last_time = self.clock()
        self._connected = True

    def get_observation(self) -> dict[str, Any]:
        self._require_connected()
        now = self.clock()
        self.env.advance(min(MAX_DT_S, now - (self._last_time or now)))
        self._last_time = now
        x, y = self.env.effector
        return {"x.pos": float(x), "y.pos": float(y), self.config.camera: self.env.render()}

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        self._require_connected()
        goal = np.array([float(action["x.pos"]), float(action["y.pos"])])
        self.env.set_goal(goal)
        self._recent.append(goal)
        if len(self._recent) == 4:
            a0, a1, a2, a3 = self._recent
            jerk = float(np.linalg.norm(a3 - 3 * a2 + 3 * a1 - a0))
            self._jerk_sum += jerk
            self._jerk_n += 1
            self._jerk_max = max(self._jerk_max, jerk)
        x, y = self.env.goal
        return {"x.pos": float(x), "y.pos": float(y)}

    def disconnect(self) -> None:
        self._connected = False

    def task_stats(self) -> dict[str, float | None]:
        """Successes and attempts so far, and the commanded actions' jerk (mean and max of
        ‖a_t − 3a_{t−1} + 3a_{t−2} − a_{t−3}‖ over every four successive actions; None before
        four); the client adds them to its stats."""
        return {
            "successes": self.env.successes,
            "attempts": self.env.attempts,
            "action_jerk_mean": self._jerk_sum / self._jerk_n if self._jerk_n else None,
            "action_jerk_max": self._jerk_max if self._jerk_n else None,
        }

    def _require_connected(self) -> None:
        if not self._connected:
            raise ConnectionError("armory_sim robot is not connected")
