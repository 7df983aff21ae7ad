"""Which static sampler serves a policy: a registry of LeRobot ``config.type`` to sampler class
(π0.5 and π0 today). A new member of the π0 family is one subclass of
:class:`~lerobot_armory.policies.pi05_static.StaticPi05` and one line here."""

from __future__ import annotations

from typing import Any

from lerobot_armory.policies.pi0_static import StaticPi0
from lerobot_armory.policies.pi05_static import StaticPi05

SAMPLERS: dict[str, type[StaticPi05]] = {cls.kind: cls for cls in (StaticPi05, StaticPi0)}


def sampler_class(policy: Any) -> type[StaticPi05] | None:
    """The static sampler class for ``policy``'s type (None: it has none)."""
    return SAMPLERS.get(getattr(getattr(policy, "config", None), "type", ""))


def unsupported_reason(policy: Any) -> str | None:
    """Why no static sampler can run ``policy`` (None: one can)."""
    cls = sampler_class(policy)
    if cls is None:
        kind = getattr(getattr(policy, "config", None), "type", type(policy).__name__)
        return f"{kind} has no static sampler yet ({' and '.join(SAMPLERS)} only); it is served by LeRobot's own sampler"
    return cls.unsupported_reason(policy)


def make_static_sampler(policy: Any, **options: Any) -> StaticPi05:
    """The static sampler for ``policy`` (``options``: :class:`StaticPi05`'s keyword arguments).

    Raises:
        ValueError: no static sampler can run it (:func:`unsupported_reason`) or a bad option.
    """
    cls = sampler_class(policy)
    if cls is None:
        raise ValueError(unsupported_reason(policy))
    return cls(policy, **options)
