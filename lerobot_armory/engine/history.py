"""Per-robot observation histories through one batched ``predict_action_chunk``.

For policies whose chunk depends on the last ``n_obs_steps`` observations (diffusion, VQ-BeT,
multi-task DiT), each row of a batch brings its own ``n`` observations, oldest first. The engine
pre-processes the ``B * n`` observations as one flat batch (the pre-processor is per row), and
this module folds them back to ``(B, n, ...)`` and hands them to the policy the way its own
``select_action`` would have for one robot: as stacked inputs (diffusion's offline mode) or in
its observation queues (see :mod:`lerobot_armory.engine.policy_kinds`). The policy object keeps
nothing between calls: its queues are emptied before and after each one.
"""

from __future__ import annotations

from typing import Any

from lerobot_armory.engine.policy_kinds import Kind

OBS_IMAGES = "observation.images"  # where LeRobot's select_action stacks the cameras
ACTION = "action"


def fold(processed: dict[str, Any], rows: int, steps: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split a pre-processed flat batch of ``rows * steps`` into (every tensor as ``(rows, steps,
    ...)``, the current step's values: the last observation of each row, lists cut alike)."""
    import torch

    stacked: dict[str, Any] = {}
    current: dict[str, Any] = {}
    for key, value in processed.items():
        if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == rows * steps:
            stacked[key] = value.reshape(rows, steps, *value.shape[1:])
            current[key] = stacked[key][:, -1]
        elif isinstance(value, list) and len(value) == rows * steps:
            current[key] = value[steps - 1 :: steps]
        else:
            current[key] = value
    return stacked, current


def predict(policy: Any, kind: Kind, processed: dict[str, Any], rows: int, steps: int, kwargs: dict[str, Any]) -> Any:
    """``policy.predict_action_chunk`` on ``rows`` robots with ``steps`` observations each
    (``processed`` is their flat pre-processed batch, oldest first within a row)."""
    import torch

    stacked, current = fold(processed, rows, steps)
    observed = [k for k in policy.config.input_features if k in stacked]
    cameras = [k for k in policy.config.image_features if k in stacked]
    policy.reset()  # empty queues: diffusion then reads its argument; queue readers get only ours
    try:
        # LeRobot's processors leave an empty "action" entry: a queue reader would read its queue.
        batch = {k: v for k, v in current.items() if k != ACTION}
        if kind.inputs == "stacked":
            batch.update({k: stacked[k] for k in observed})
            return policy.predict_action_chunk(batch, **kwargs)
        if kind.inputs != "queues":
            raise ValueError(f"{kind.name}: inputs {kind.inputs!r} take no history")
        for t in range(steps):
            step = {k: stacked[k][:, t] for k in observed}
            if cameras:
                step[OBS_IMAGES] = torch.stack([step[k] for k in cameras], dim=-4)
            for key, queue in policy._queues.items():
                if key != ACTION and key in step:
                    queue.append(step[key])
        if cameras:
            batch[OBS_IMAGES] = torch.stack([current[k] for k in cameras], dim=-4)
        return policy.predict_action_chunk(batch, **kwargs)
    finally:
        policy.reset()  # no robot's observations stay on the shared policy object
