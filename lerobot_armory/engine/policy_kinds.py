"""What the engine must know about each LeRobot policy type to serve it batched, per robot.

LeRobot's policies are written for one robot at a time: ``select_action`` keeps an observation
history and an action queue on the policy object, and some types' ``predict_action_chunk`` reads
that history instead of its argument. A server that puts several robots in one batch must give
every row its own history and its own noise. Each type is one :class:`Kind` in :data:`KINDS`:

- ``noise``: the shape of the initial noise ``predict_action_chunk(noise=...)`` takes, so that row
  k's randomness comes from its robot's seed alone (π0, π0.5, SmolVLA, diffusion);
- ``history``: how many consecutive observations a row needs (``n_obs_steps``); the serving core
  keeps each robot's last ones and the engine stacks them per row;
- ``inputs``: what ``predict_action_chunk`` reads. ``current``: its argument, one observation per
  row. ``stacked``: its argument with every observed feature ``(B, n_obs_steps, ...)`` (diffusion,
  even at ``n_obs_steps = 1``). ``queues``: ``policy._queues`` only (VQ-BeT, multi-task DiT): the
  engine fills those queues with the batch's per-row histories before every call, as
  ``select_action`` would for one robot, and empties them after;
- ``refuse``: why a type cannot be served correctly (one line, at start-up, exit 2).

A type we do not know (a ``lerobot_policy_*`` plugin) is served as stateless, and the log says
that batched = alone has not been checked for it; one with ``n_obs_steps > 1`` is refused.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


def _one(config: Any) -> int:
    return 1


@dataclass(frozen=True)
class Kind:
    """How one LeRobot policy type is served.

    Attributes:
        name: the LeRobot ``config.type``.
        noise: ``config -> (H, D)`` of the ``noise=`` argument (None: the type takes none).
        inputs: ``current``, ``stacked`` or ``queues`` (see the module docstring).
        history: ``config -> `` observations per row (1: the current one only).
        refuse: ``config -> `` why it cannot be served (None: it can).
        randomness: ``config -> `` how its chunks depend on chance, for the coverage table.
        known: a type whose per-robot behaviour was read and tested here.
    """

    name: str
    noise: Callable[[Any], tuple[int, int] | None] | None = None
    inputs: str = "current"
    history: Callable[[Any], int] = _one
    refuse: Callable[[Any], str | None] = lambda config: None
    randomness: Callable[[Any], str] = lambda config: "deterministic"
    known: bool = True


def _n_obs_steps(config: Any) -> int:
    return int(getattr(config, "n_obs_steps", 1) or 1)


def _flow_noise(config: Any) -> tuple[int, int] | None:
    """π0 / π0.5 / SmolVLA: ``(chunk_size, max_action_dim)`` (the noise is padded like the actions)."""
    h, d = getattr(config, "chunk_size", None), getattr(config, "max_action_dim", None)
    return (h, d) if isinstance(h, int) and isinstance(d, int) else None


def _diffusion_noise(config: Any) -> tuple[int, int] | None:
    action = config.output_features.get("action")
    return (int(config.horizon), int(action.shape[0])) if action is not None else None


def _diffusion_randomness(config: Any) -> str:
    if getattr(config, "noise_scheduler_type", "DDPM") == "DDIM":
        return "seeded per robot"
    # DDPM's scheduler adds fresh noise at every denoising step from torch's generator, drawn for
    # the whole batch: only the initial noise is the robot's own.
    return "initial noise seeded per robot; DDPM's per-step noise drawn per batch"


def _refuse_history(config: Any) -> str | None:
    n = _n_obs_steps(config)
    return None if n == 1 else f"n_obs_steps={n}: an observation history this type keeps in ways not checked per robot here"


def _refuse_tdmpc(config: Any) -> str | None:
    return (
        "tdmpc plans each chunk from the previous call's solution (_prev_mean, one for the whole batch), so a robot's "
        "chunk would depend on the robots served before it; it has no per-robot form"
    )


KINDS: dict[str, Kind] = {
    kind.name: kind
    for kind in (
        Kind("act"),
        Kind("pi05", noise=_flow_noise, randomness=lambda c: "seeded per robot"),
        Kind("pi0", noise=_flow_noise, randomness=lambda c: "seeded per robot"),
        Kind("smolvla", noise=_flow_noise, randomness=lambda c: "seeded per robot"),
        Kind("diffusion", noise=_diffusion_noise, inputs="stacked", history=_n_obs_steps, randomness=_diffusion_randomness),
        Kind("vqbet", inputs="queues", history=_n_obs_steps, randomness=lambda c: "drawn per batch (code sampling)"),
        Kind("multi_task_dit", inputs="queues", history=_n_obs_steps, randomness=lambda c: "drawn per batch (no noise argument)"),
        Kind("xvla", randomness=lambda c: "drawn per batch (the noise argument is ignored)"),
        Kind("pi0_fast", randomness=lambda c: "greedy decoding" if not getattr(c, "temperature", 0.0) else "drawn per batch"),
        Kind("tdmpc", refuse=_refuse_tdmpc),
        Kind(
            "gaussian_actor",
            refuse=lambda c: "gaussian_actor predicts one action per call (its predict_action_chunk is not implemented)",
        ),
        Kind(
            "lingbot_va",
            refuse=lambda c: "lingbot_va keeps a streaming KV cache and per-episode state inside the model: robots cannot share it",
        ),
        Kind("groot", randomness=lambda c: "drawn per batch"),
        Kind("wall_x", randomness=lambda c: "drawn per batch"),
        Kind("eo1", randomness=lambda c: "drawn per batch"),
        Kind("evo1", randomness=lambda c: "drawn per batch"),
        Kind("fastwam", randomness=lambda c: "drawn per batch"),
        Kind("molmoact2", randomness=lambda c: "drawn per batch"),
        Kind("vla_jepa", randomness=lambda c: "drawn per batch"),
        Kind("armory_planner"),
    )
}


def kind_of(config: Any) -> Kind:
    """The :class:`Kind` of a parsed LeRobot config; an unknown type is served as stateless if it
    has no observation history, refused if it has one."""
    kind = KINDS.get(config.type)
    if kind is not None:
        return kind
    return Kind(config.type, refuse=_refuse_history, randomness=lambda c: "not checked", known=False)


def refusal(config: Any) -> str | None:
    """Why ``config``'s policy cannot be served batched per robot (None: it can)."""
    kind = kind_of(config)
    why = kind.refuse(config)
    if why is None and kind.history is _one and _n_obs_steps(config) > 1:
        why = _refuse_history(config)
    return why
