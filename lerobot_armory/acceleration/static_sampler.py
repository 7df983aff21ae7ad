"""Which static sampler serves a policy: a registry of LeRobot ``config.type`` to sampler class
(π0.5, π0 and SmolVLA today). A new member of the π0 family is one subclass of
:class:`~lerobot_armory.acceleration.pi05_static.StaticPi05` and one line here; another model is one
class with the same interface (``smolvla_static.StaticSmolVLA``)."""

from __future__ import annotations

from typing import Any

from lerobot_armory.acceleration.pi0_static import StaticPi0
from lerobot_armory.acceleration.pi05_static import StaticPi05, policy_type
from lerobot_armory.acceleration.smolvla_static import StaticSmolVLA

SAMPLERS: dict[str, Any] = {cls.kind: cls for cls in (StaticPi05, StaticPi0, StaticSmolVLA)}


def sampler_class(policy: Any) -> Any:
    """The static sampler class for ``policy``'s type (None: it has none)."""
    return SAMPLERS.get(policy_type(policy))


def unsupported_reason(policy: Any) -> str | None:
    """Why no static sampler can run ``policy`` (None: one can)."""
    cls = sampler_class(policy)
    if cls is None:
        return f"{policy_type(policy)} has no static sampler yet ({', '.join(SAMPLERS)} only); it is served by LeRobot's own sampler"
    return cls.unsupported_reason(policy)


def make_static_sampler(policy: Any, **options: Any) -> Any:
    """The static sampler for ``policy`` (``options``: :class:`StaticPi05`'s keyword arguments).

    Raises:
        ValueError: no static sampler can run it (:func:`unsupported_reason`) or a bad option.
    """
    cls = sampler_class(policy)
    if cls is None:
        raise ValueError(unsupported_reason(policy))
    return cls(policy, **options)
