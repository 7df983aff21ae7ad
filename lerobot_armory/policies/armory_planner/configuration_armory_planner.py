"""Config of the ``armory_planner`` policy type."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamConfig


@PreTrainedConfig.register_subclass("armory_planner")
@dataclass
class ArmoryPlannerConfig(PreTrainedConfig):
    """An analytic planner for ``armory_sim``: finds the red target in the camera image and
    plans a chunk of waypoints that moves the effector onto it.

    It sees one frame, so it aims where the target *is*: served on time it touches static and
    moving targets alike; served late, its chunk chases where a moving target used to be. That
    makes the dynamic task's success a direct measure of chunk freshness.

    Attributes:
        chunk_size: H, waypoints per chunk.
        n_action_steps: actions executed per chunk when used through ``select_action``.
        fps: control rate the waypoints are spaced for.
        max_speed: effector speed the waypoints assume (workspace units per second).
        camera: image feature to look at.
    """

    chunk_size: int = 20
    n_action_steps: int = 20
    fps: float = 30.0
    max_speed: float = 1.5
    camera: str = "observation.images.front"
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.chunk_size < 1 or not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(f"need 1 <= n_action_steps ({self.n_action_steps}) <= chunk_size ({self.chunk_size})")
        if not (self.fps > 0 and self.max_speed > 0):
            raise ValueError("fps and max_speed must be > 0")

    def validate_features(self) -> None:
        if self.camera not in self.input_features:
            raise ValueError(f"the planner needs the image feature {self.camera!r}")
        if "observation.state" not in self.input_features:
            raise ValueError("the planner needs observation.state (effector x, y)")

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=0.0)  # nothing to train: the planner is analytic

    def get_scheduler_preset(self) -> None:
        return None

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None
