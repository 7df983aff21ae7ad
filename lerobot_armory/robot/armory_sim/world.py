"""A light 2-D reaching world for simulated robots (gymnasium API, numpy only, no display).

An effector (green) moves in the square ``[-1, 1]²`` toward the position the last action asked
for, at most ``max_speed`` units per second. A target (red) must be touched (distance below
``success_radius``); each target is one *attempt*, with ``attempt_s`` seconds to succeed.

- ``static`` scene: targets sit still (reach/sort fixed targets): stale actions only cost time.
- ``dynamic`` scene: targets drift at ``target_speed`` and bounce off the walls (intercept a moving
  target): an action computed from an old observation aims where the target *was*, so a robot
  that starves or executes stale chunks misses.

Time is real time: :meth:`ArmorySimEnv.advance` integrates the motion over the seconds that
actually elapsed, so the world keeps moving while the robot starves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

SCENES = ("static", "dynamic")


@dataclass
class WorldParams:
    """Physics and task parameters."""

    scene: str = "static"
    image_size: int = 64
    max_speed: float = 1.5  # effector, units/s
    target_speed: float = 0.5  # dynamic targets, units/s
    success_radius: float = 0.12
    attempt_s: float = 4.0


class ArmorySimEnv(gym.Env):
    """The world; observations are ``{"state": (2,) float32, "image": (S, S, 3) uint8}``."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, params: WorldParams, seed: int = 0) -> None:
        if params.scene not in SCENES:
            raise ValueError(f"scene must be one of {', '.join(SCENES)}, got {params.scene!r}")
        self.params = params
        s = params.image_size
        self.observation_space = gym.spaces.Dict(
            {
                "state": gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
                "image": gym.spaces.Box(0, 255, (s, s, 3), np.uint8),
            }
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._rng = np.random.default_rng(seed)
        coords = (np.arange(s) + 0.5) / s * 2.0 - 1.0
        self._gx, self._gy = np.meshgrid(coords, -coords)  # image row 0 is y = +1
        self.effector = np.zeros(2)
        self.goal = np.zeros(2)
        self.target = np.zeros(2)
        self.target_vel = np.zeros(2)
        self.attempt_time = 0.0
        self.successes = 0
        self.attempts = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.effector = np.zeros(2)
        self.goal = self.effector.copy()
        self.successes = 0
        self.attempts = 0
        self._new_target()
        return self.observation(), {}

    def _new_target(self) -> None:
        self.attempts += 1
        self.attempt_time = 0.0
        while True:
            self.target = self._rng.uniform(-0.8, 0.8, 2)
            if np.linalg.norm(self.target - self.effector) > 0.5:
                break
        if self.params.scene == "dynamic":
            angle = self._rng.uniform(0, 2 * math.pi)
            self.target_vel = self.params.target_speed * np.array([math.cos(angle), math.sin(angle)])
        else:
            self.target_vel = np.zeros(2)

    def set_goal(self, action: np.ndarray) -> None:
        """The position the effector now moves toward (clipped to the workspace)."""
        self.goal = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)

    def advance(self, dt: float) -> bool:
        """Integrate ``dt`` seconds; returns True if the target was touched (a success)."""
        p = self.params
        dt = max(0.0, dt)
        delta = self.goal - self.effector
        dist = float(np.linalg.norm(delta))
        step = p.max_speed * dt
        self.effector = self.goal.copy() if dist <= step else self.effector + delta / dist * step
        if p.scene == "dynamic":
            self.target = self.target + self.target_vel * dt
            for k in range(2):  # bounce off the walls
                if abs(self.target[k]) > 0.9:
                    self.target[k] = math.copysign(0.9, self.target[k])
                    self.target_vel[k] = -self.target_vel[k]
        self.attempt_time += dt
        if np.linalg.norm(self.target - self.effector) < p.success_radius:
            self.successes += 1
            self._new_target()
            return True
        if self.attempt_time > p.attempt_s:
            self._new_target()
        return False

    def step(self, action):
        """Gymnasium step of one nominal 1/30 s (the robot adapter uses :meth:`advance`)."""
        self.set_goal(action)
        success = self.advance(1.0 / 30.0)
        return self.observation(), float(success), False, False, {"successes": self.successes}

    def observation(self) -> dict[str, np.ndarray]:
        return {"state": self.effector.astype(np.float32), "image": self.render()}

    def render(self) -> np.ndarray:
        """RGB image: dark background, red target, green effector."""
        s = self.params.image_size
        img = np.full((s, s, 3), 30, dtype=np.uint8)
        r = max(self.params.success_radius, 2.5 / s)
        for pos, color in ((self.target, (230, 40, 40)), (self.effector, (40, 220, 60))):
            mask = (self._gx - pos[0]) ** 2 + (self._gy - pos[1]) ** 2 < r * r
            img[mask] = color
        return img
