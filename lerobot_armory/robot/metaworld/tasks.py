"""MetaWorld tasks as episodes a robot runs: a real MuJoCo simulator nobody here wrote.

Each task wraps one MetaWorld v3 environment (``metaworld.MT1``: the goal is observable) and
adds what a fleet needs of it: an episode with a time limit in control ticks, success, a scripted
expert that solves the task *from the live state* (it makes the demonstrations a policy is
trained on), and the observation split as a LeRobot policy consumes it:

- ``observation.state``: the hand's position and the gripper's opening (MetaWorld's first 4
  values, what LeRobot's own MetaWorld env calls ``agent_pos``);
- ``observation.environment_state``: the full 39-value MetaWorld state (hand, objects, their
  previous frame, the goal), plus, on the dynamic task, the target's velocity.

Two tasks, one static and one dynamic (the reference paper's distinction):

- ``push`` (static): MetaWorld's push-v3, push the puck onto the goal. A stale action costs time.
- ``reach-moving`` (dynamic): MetaWorld's reach-v3 whose target circles its sampled position
  during the episode (the paper's turntable); success is holding the hand within
  ``HOLD_RADIUS_M`` of the moving target for ``HOLD_TICKS`` ticks in a row. An action computed from
  an old observation aims where the target *was*, so stale chunks miss.

Importing this module needs no simulator; :func:`make_task` says in one line what is missing
(``metaworld`` and ``mujoco==3.3.2``: metaworld 3.0.0 breaks on newer MuJoCo).
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

ACTION_NAMES = ("dx", "dy", "dz", "grip")  # MetaWorld's action: hand displacement and grip effort
STATE_NAMES = ("hand.x", "hand.y", "hand.z", "gripper")
MUJOCO_OK = "3.3.2"  # metaworld 3.0.0's reset_mocap_welds fails on mujoco 3.17 (eq_data shape)

# The dynamic task: the target circles at TARGET_SPEED_M (metres per tick; the hand moves at most
# 0.01 m a tick) on a circle of CIRCLE_RADIUS_M around its sampled position.
CIRCLE_RADIUS_M = 0.08
TARGET_SPEED_M = 0.004
HOLD_RADIUS_M = 0.03
HOLD_TICKS = 8


# metaworld.MT1 draws its tasks from numpy's global generator (seeded, then sampled): two robots
# of one process building theirs at once interleave the draws ("Only generated 49 unique goals").
_BUILD_LOCK = threading.Lock()


class SimulatorUnavailable(RuntimeError):
    """The simulator (or its renderer) cannot run here; the message is one line saying why and how."""


@dataclass(frozen=True)
class TaskSpec:
    """A task's identity and limits."""

    name: str
    env_name: str  # the MetaWorld environment
    kind: str  # "static" or "dynamic"
    max_ticks: int  # the episode's time limit, in control ticks
    description: str  # the language instruction (the dataset's and the server's task text)
    env_state_dim: int


TASKS: dict[str, TaskSpec] = {
    "push": TaskSpec("push", "push-v3", "static", 200, "push the puck to the goal", 39),
    "reach-moving": TaskSpec("reach-moving", "reach-v3", "dynamic", 200, "reach the moving target and hold it", 42),
}


def task_spec(name: str) -> TaskSpec:
    """The task named ``name``; ValueError naming the known tasks otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown MetaWorld task {name!r}: known tasks are {', '.join(sorted(TASKS))}")
    return TASKS[name]


def _import_metaworld() -> Any:
    """MetaWorld, or one line saying what is missing (the package, the right MuJoCo, a renderer)."""
    try:
        import mujoco
    except ImportError:
        raise SimulatorUnavailable(
            "the metaworld robot needs MuJoCo: pip install 'lerobot-armory[metaworld]' (metaworld==3.0.0, mujoco==3.3.2)"
        ) from None
    except Exception as exc:  # noqa: BLE001 - e.g. MUJOCO_GL naming a backend that does not exist
        raise SimulatorUnavailable(f"MuJoCo cannot start: {_first_line(exc)} (MUJOCO_GL=egl renders offscreen without a display)") from None
    try:
        import metaworld
    except ImportError:
        raise SimulatorUnavailable(
            "the metaworld robot needs MetaWorld: pip install 'lerobot-armory[metaworld]' (metaworld==3.0.0, mujoco==3.3.2)"
        ) from None
    if mujoco.__version__ != MUJOCO_OK:
        raise SimulatorUnavailable(
            f"metaworld 3.0.0 fails on mujoco {mujoco.__version__} (reset_mocap_welds); install mujoco=={MUJOCO_OK}"
        )
    return metaworld


@dataclass
class StepResult:
    success: bool  # the task was solved at this tick
    done: bool  # the episode ended (success or time limit)


class MetaWorldTask:
    """One task's episodes in one MuJoCo simulator.

    ``reset(seed)`` starts an episode whose layout (object, goal, target path) is drawn from
    ``seed`` alone; :meth:`step` applies one action (one control tick); :meth:`expert_action`
    is the scripted expert's action for the live state.
    """

    def __init__(self, name: str, render_size: int = 0) -> None:
        self.spec = task_spec(name)
        self.render_size = render_size
        if render_size:
            os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen, no display needed (read when MuJoCo is imported)
        metaworld = _import_metaworld()
        kwargs: dict[str, Any] = {}
        if render_size:
            kwargs = {"render_mode": "rgb_array", "camera_name": "corner2", "width": render_size, "height": render_size}
        with _BUILD_LOCK:
            mt1 = metaworld.MT1(self.spec.env_name, seed=0)
            env = mt1.train_classes[self.spec.env_name](**kwargs)
            env.set_task(mt1.train_tasks[0])
        env._freeze_rand_vec = False  # each reset draws a new layout ...
        env.seeded_rand_vec = True  # ... from the env's own seeded generator (reset(seed) decides it)
        self.env = env
        from metaworld.policies import SawyerPushV3Policy

        self._push_expert = SawyerPushV3Policy()
        self._raw = np.zeros(39)
        self.ticks = 0
        self.hold = 0
        self._centre = np.zeros(3)
        self._phase = 0.0
        self._direction = 1.0
        self.success = False

    # ---- episodes ----------------------------------------------------------------------------

    def reset(self, seed: int) -> None:
        """Start an episode whose layout is drawn from ``seed``."""
        self.env.seed(int(seed))
        self._raw, _ = self.env.reset()
        self.ticks = 0
        self.hold = 0
        self.success = False
        if self.spec.kind == "dynamic":
            rng = np.random.default_rng(int(seed))
            self._centre = np.array(self.env._target_pos, dtype=np.float64)
            self._phase = float(rng.uniform(0.0, 2.0 * math.pi))
            self._direction = 1.0 if rng.random() < 0.5 else -1.0
            self._move_target(0)

    def step(self, action: np.ndarray) -> StepResult:
        """Apply one action for one tick (the world moves on whatever the action)."""
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        if a.shape != (4,) or not np.all(np.isfinite(a)):
            raise ValueError(f"a MetaWorld action is 4 finite values ({', '.join(ACTION_NAMES)}), got {action!r}")
        self._raw, _, _, _, info = self.env.step(a.astype(np.float32))
        self.ticks += 1
        if self.spec.kind == "dynamic":
            self._move_target(self.ticks)
            near = float(np.linalg.norm(self.env.tcp_center - self.env._target_pos)) <= HOLD_RADIUS_M
            self.hold = self.hold + 1 if near else 0
            solved = self.hold >= HOLD_TICKS
        else:
            solved = bool(info.get("success", 0.0))
        self.success = self.success or solved
        return StepResult(solved, solved or self.ticks >= self.spec.max_ticks)

    def _move_target(self, tick: int) -> None:
        omega = TARGET_SPEED_M / CIRCLE_RADIUS_M
        angle = self._phase + self._direction * omega * tick
        pos = self._centre + CIRCLE_RADIUS_M * np.array([math.cos(angle), math.sin(angle), 0.0])
        self.env._target_pos = pos
        self.env.model.site("goal").pos = pos
        self._raw[-3:] = pos  # the observation shows the target where it is now

    def _target_velocity(self) -> np.ndarray:
        omega = TARGET_SPEED_M / CIRCLE_RADIUS_M
        angle = self._phase + self._direction * omega * self.ticks
        return self._direction * TARGET_SPEED_M * np.array([-math.sin(angle), math.cos(angle), 0.0])

    # ---- what the robot reports --------------------------------------------------------------

    def agent_state(self) -> np.ndarray:
        """``observation.state``: hand xyz and gripper opening (float32, 4)."""
        return self._raw[:4].astype(np.float32)

    def environment_state(self) -> np.ndarray:
        """``observation.environment_state``: MetaWorld's 39 values (+ target velocity when dynamic)."""
        if self.spec.kind == "dynamic":
            return np.concatenate([self._raw, self._target_velocity() * 100.0]).astype(np.float32)
        return self._raw.astype(np.float32)

    def render(self) -> np.ndarray:
        """The corner camera's RGB frame (uint8, upright); needs ``render_size``."""
        if not self.render_size:
            raise SimulatorUnavailable("this task was made without a camera (render_size=0)")
        try:
            frame = self.env.render()
        except Exception as exc:  # noqa: BLE001 - the renderer's own error, in one line
            raise SimulatorUnavailable(
                f"MuJoCo cannot render here ({_first_line(exc)}); set MUJOCO_GL=egl or osmesa, or run state-only (image_size=0)"
            ) from None
        return np.ascontiguousarray(np.flip(frame, (0, 1)))  # MetaWorld's corner2 camera is upside down

    def close(self) -> None:
        """Release the simulator (and its renderer's context, which otherwise complains at exit)."""
        try:
            self.env.close()
        except Exception:  # noqa: BLE001 - a renderer that never started has nothing to close
            pass

    # ---- the scripted expert -----------------------------------------------------------------

    def expert_action(self) -> np.ndarray:
        """The scripted expert's action for the live state (what the demonstrations record)."""
        if self.spec.kind == "static":
            return np.clip(self._push_expert.get_action(self._raw), -1.0, 1.0).astype(np.float32)
        # Track the target: aim where it will be one tick ahead, proportional gain.
        hand = self.env.tcp_center
        aim = self.env._target_pos + self._target_velocity()
        delta = np.clip((aim - hand) * 40.0, -1.0, 1.0)
        return np.array([*delta, 0.0], dtype=np.float32)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__
