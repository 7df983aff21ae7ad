"""Mapping between a LeRobot robot's raw observation/action dicts and policy features.

LeRobot robots report motors as ``"<motor>.pos": float`` and cameras as ``"<name>": (h, w, 3)``;
policies consume ``observation.state`` (the motor values in the robot's feature order) and
``observation.images.<name>``, and produce one action vector whose entries follow the robot's
``action_features`` order — the same convention LeRobot's datasets use.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

STATE = "observation.state"
IMAGES = "observation.images."


@dataclass(frozen=True)
class FeatureMap:
    """How one robot's dicts become wire arrays and back."""

    state_keys: tuple[str, ...]
    cameras: dict[str, tuple[int, int, int]]
    action_keys: tuple[str, ...]

    @classmethod
    def for_robot(cls, observation_features: Mapping[str, Any], action_features: Mapping[str, Any]) -> FeatureMap:
        state = tuple(k for k, v in observation_features.items() if v is float)
        cams = {k: tuple(int(d) for d in v) for k, v in observation_features.items() if isinstance(v, tuple)}
        actions = tuple(k for k, v in action_features.items() if v is float)
        if not actions:
            raise ValueError("the robot declares no float action features")
        return cls(state, cams, actions)

    def wire_features(self) -> dict[str, tuple[str, tuple[int, ...]]]:
        """``{feature name: (dtype, shape)}`` to declare at registration."""
        out: dict[str, tuple[str, tuple[int, ...]]] = {}
        if self.state_keys:
            out[STATE] = ("float32", (len(self.state_keys),))
        for name, shape in self.cameras.items():
            out[IMAGES + name] = ("uint8", shape)
        return out

    def to_wire(self, raw: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """A raw robot observation as wire arrays."""
        out: dict[str, np.ndarray] = {}
        if self.state_keys:
            out[STATE] = np.array([raw[k] for k in self.state_keys], dtype=np.float32)
        for name in self.cameras:
            out[IMAGES + name] = np.ascontiguousarray(raw[name], dtype=np.uint8)
        return out

    def to_action(self, vector: np.ndarray) -> dict[str, float]:
        """One policy action vector as the robot's action dict."""
        if vector.shape[-1] != len(self.action_keys):
            raise ValueError(f"the policy's actions have {vector.shape[-1]} dims, the robot takes {len(self.action_keys)}")
        return {k: float(v) for k, v in zip(self.action_keys, vector, strict=True)}
