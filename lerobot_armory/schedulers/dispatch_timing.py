"""Dispatch timing: when the device is free, should it wait for an observation about to land?

Every scheduler decides *whom* to serve; a work-conserving device dispatches that batch the
moment it is free. But the instant matters too (the offline study, ``research/``, found the
best schedules idle on purpose). A chunk is usable from the first control tick after it lands,
so two dispatch instants whose chunks land before the same tick deliver equally early; the later
one can carry a *fresher* observation, whose chunk reaches one step (or more) further into the
future. Concretely, on libero (20 fps, π0.5 on an L40S): a batch of 3 takes 142.4 ms, plus 2 ×
3.75 ms network = 149.9 ms, just inside three ticks. Dispatched the moment an observation lands,
its chunk arrives before the same tick as a batch dispatched a few ms earlier on the previous
observation, and covers one more step.

The rule (:func:`hold_until`), all predictions from the mirrors, no I/O:

- The candidates are the predicted landing instants of the batch members' *next* observations
  within ``max_wait_s``.
- Waiting until candidate ``c`` must cost no member anything: dispatched as late as
  ``c + margin_s`` (the margin absorbs latency and network error), every member's chunk lands
  before the same tick as dispatched now, or before the member's queue runs dry anyway.
- It must cost the *next* batch nothing either: every other robot whose queue runs dry before
  that batch's chunk could reach it still gets that chunk in time (or no later than without the
  wait, counted in ticks). This is what keeps the rule from idling an overloaded device.
- Among the candidates that pass, the latest is taken (it makes the most members fresher).

The device waits until then, or less: the driver plans again as soon as any observation lands
(the awaited one usually), and the dispatcher caps the total wait per free device at
``max_wait_s``. A late observation therefore costs at most the margin: re-planned at ``c +
margin_s``, the rule sees the observation overdue and dispatches.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from lerobot_armory.mirror import RobotMirror
from lerobot_armory.transition import tick_of

# An observation landing at ``now`` (to float rounding) is held already, not a reason to wait.
_EPS = 1e-9


def next_observation_at(mirror: RobotMirror) -> float:
    """Predicted server time at which the robot's next observation (one tick after the latest
    held) lands: its capture tick plus the estimated one-way delay."""
    return mirror.obs_anchor + 1.0 / mirror.spec.fps + mirror.estimator.one_way_s


def arrival_tick(mirror: RobotMirror, t_done: float) -> int:
    """Tick (counted from the latest observation's tick) from which a chunk whose batch
    finishes at ``t_done`` is usable (the mirror's own arrival prediction)."""
    return tick_of(t_done + mirror.estimator.one_way_s, mirror.obs_anchor, mirror.spec.fps)


def dry_tick_on_grid(mirror: RobotMirror) -> int:
    """Tick (same grid) at which the robot runs dry with the chunks it holds or awaits."""
    return tick_of(mirror.deadline(), mirror.obs_anchor, mirror.spec.fps)


def hold_until(
    robots: Sequence[RobotMirror],
    batch: Sequence[RobotMirror],
    now: float,
    d_infer: Sequence[float],
    max_wait_s: float,
    margin_s: float,
) -> float | None:
    """The instant to wait for before dispatching ``batch``, or None to dispatch now.

    Args:
        robots: every robot the scheduler saw (registration order).
        batch: the scheduler's choice at ``now``.
        now: decision time (server clock).
        d_infer: ``d_infer(b)`` in seconds, index ``b - 1``.
        max_wait_s: no candidate later than ``now + max_wait_s``.
        margin_s: the wait must pay off even if the dispatch happens this much later.
    """
    if not batch or max_wait_s <= 0:
        return None
    d_b, d_1 = d_infer[len(batch) - 1], d_infer[0]
    members = {id(m) for m in batch}
    candidates = sorted(
        c for m in batch if now + _EPS < (c := next_observation_at(m)) <= now + max_wait_s
    )
    if not candidates:
        return None
    dry = {id(m): dry_tick_on_grid(m) for m in robots if m.obs_index is not None}
    # Each member's arrival now, and the tick by which it must land to cost nothing.
    limit = {id(m): max(arrival_tick(m, now + d_b), dry[id(m)]) for m in batch}
    others = [m for m in robots if id(m) not in members and m.obs_index is not None]
    # The next batch could at best go out when this one is done; its chunk of one lands then.
    others_limit = {id(m): max(arrival_tick(m, now + d_b + d_1), dry[id(m)]) for m in others}
    best = None
    for c in candidates:
        late = c + margin_s
        if any(arrival_tick(m, late + d_b) > limit[id(m)] for m in batch):
            break  # later candidates only land later
        if any(arrival_tick(m, late + d_b + d_1) > others_limit[id(m)] for m in others):
            break
        best = c
    if best is None:
        return None
    return best + margin_s


def check_timing(seconds: float) -> None:
    """Raise ValueError for a wait or margin no rule can honour (negative, NaN, infinite)."""
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"must be a finite number >= 0, got {seconds * 1000:g} ms")
