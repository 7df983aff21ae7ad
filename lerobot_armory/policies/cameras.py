"""Which of a policy's cameras a robot sends: LeRobot's π0, π0.5 and SmolVLA configs add
``empty_cameras`` placeholder image features, which their own image step fills when a batch lacks
them (−1 pixels, mask 0) and which no robot has. No heavy imports: the engine reads it for every
policy type."""

from __future__ import annotations

from typing import Any

# LeRobot's π0, π0.5 and SmolVLA configs add ``empty_cameras`` placeholder image features under
# these names; their image step fills a missing one (−1 pixels, mask 0), which a robot cannot send.
PLACEHOLDER_CAMERA = "observation.images.empty_camera_{}"
FILLS_PLACEHOLDERS = ("pi0", "pi05", "smolvla")


def placeholder_cameras(config: Any) -> set[str]:
    """The image features of ``config`` that are ``empty_cameras`` placeholders: not sent by a
    robot, filled by the policy's own image step (π0, π0.5, SmolVLA; none for other types)."""
    if getattr(config, "type", None) not in FILLS_PLACEHOLDERS:
        return set()
    return {PLACEHOLDER_CAMERA.format(i) for i in range(int(getattr(config, "empty_cameras", 0) or 0))}


def served_cameras(config: Any) -> tuple[str, ...]:
    """The cameras a batch carries, in the policy's order (its image features less the placeholders)."""
    placeholders = placeholder_cameras(config)
    return tuple(k for k in config.image_features if k not in placeholders)
