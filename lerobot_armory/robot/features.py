"""Mapping between a LeRobot robot's raw observation/action dicts and policy features.

LeRobot robots declare every scalar as ``"<key>": float`` and every camera as ``"<name>": (h, w, c)``;
the keys are not always motor positions: a mobile base reports velocities (LeKiwi's ``x.vel``,
``theta.vel``; Reachy 2's ``mobile_base.vx``), bimanual robots prefix each arm (``left_joint_1.pos``),
a rover reports IMU and GPS values. Policies consume ``observation.state`` (*every* float
observation, in the robot's declared order) and ``observation.images.<name>`` (every tuple
feature), and produce one action vector whose entries follow the robot's float
``action_features`` order — exactly how LeRobot's ``hw_to_dataset_features`` builds a dataset's
``observation.state`` and ``action`` names, so a policy trained on a LeRobot dataset of the robot
lines up entry by entry.

A simulated robot may also report the world's state (``environment_state.<k>`` floats: object
poses, the goal), which goes out as ``observation.environment_state`` in declared order, the
feature LeRobot's state-based policies (ACT, diffusion) read beside or instead of images.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

STATE = "observation.state"
ENV_STATE = "observation.environment_state"
IMAGES = "observation.images."
# Float features named with this prefix are a simulator's privileged state (object poses, the
# goal): LeRobot's policies read them as ``observation.environment_state``, not as robot state.
ENV_STATE_PREFIX = "environment_state."


@dataclass(frozen=True)
class FeatureMap:
    """How one robot's dicts become wire arrays and back."""

    state_keys: tuple[str, ...]
    cameras: dict[str, tuple[int, int, int]]
    action_keys: tuple[str, ...]
    env_state_keys: tuple[str, ...] = ()

    @classmethod
    def for_robot(cls, observation_features: Mapping[str, Any], action_features: Mapping[str, Any]) -> FeatureMap:
        """Read a robot's declared features (after ``connect()``: cameras may learn their size then)."""
        floats = [k for k, v in observation_features.items() if v is float]
        state = tuple(k for k in floats if not k.startswith(ENV_STATE_PREFIX))
        env_state = tuple(k for k in floats if k.startswith(ENV_STATE_PREFIX))
        cams: dict[str, tuple[int, int, int]] = {}
        for k, v in observation_features.items():
            if isinstance(v, tuple):
                if len(v) != 3 or any(d is None for d in v):
                    raise ValueError(
                        f"camera {k!r} has no definite (height, width, channels), got {v}: set its width and height"
                    )
                cams[k] = (int(v[0]), int(v[1]), int(v[2]))
        actions = tuple(k for k, v in action_features.items() if v is float)
        if not actions:
            raise ValueError("the robot declares no float action features")
        return cls(state, cams, actions, env_state)

    def action_mismatch(self, policy_action_dim: int, robot: str) -> str | None:
        """Why a policy with actions of ``policy_action_dim`` cannot drive this robot (None: it can)."""
        if policy_action_dim == len(self.action_keys):
            return None
        return (
            f"the policy's actions have {policy_action_dim} dims, robot {robot} takes {len(self.action_keys)} "
            f"({', '.join(self.action_keys)})"
        )

    def wire_features(self) -> dict[str, tuple[str, tuple[int, ...]]]:
        """``{feature name: (dtype, shape)}`` to declare at registration."""
        out: dict[str, tuple[str, tuple[int, ...]]] = {}
        if self.state_keys:
            out[STATE] = ("float32", (len(self.state_keys),))
        if self.env_state_keys:
            out[ENV_STATE] = ("float32", (len(self.env_state_keys),))
        for name, shape in self.cameras.items():
            out[IMAGES + name] = ("uint8", shape)
        return out

    def to_wire(self, raw: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """A raw robot observation as wire arrays."""
        out: dict[str, np.ndarray] = {}
        if self.state_keys:
            out[STATE] = np.array([raw[k] for k in self.state_keys], dtype=np.float32)
        if self.env_state_keys:
            out[ENV_STATE] = np.array([raw[k] for k in self.env_state_keys], dtype=np.float32)
        for name in self.cameras:
            frame = np.asarray(raw[name])
            if frame.dtype != np.uint8:
                # Casting would wrap a uint16 depth map (millimetres) modulo 256: refuse instead.
                raise ValueError(f"camera {name!r} gives {frame.dtype} frames; images go to the policy as uint8")
            out[IMAGES + name] = np.ascontiguousarray(frame)
        return out

    def to_action(self, vector: np.ndarray) -> dict[str, float]:
        """One policy action vector as the robot's action dict."""
        if vector.shape[-1] != len(self.action_keys):
            raise ValueError(f"the policy's actions have {vector.shape[-1]} dims, the robot takes {len(self.action_keys)}")
        return {k: float(v) for k, v in zip(self.action_keys, vector, strict=True)}
