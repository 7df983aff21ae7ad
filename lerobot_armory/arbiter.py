"""One dispatch step across several policies sharing one device.

A batch holds robots of one policy (one model runs it); the device runs one batch at a time. Each
policy keeps its own :class:`~lerobot_armory.dispatch.Dispatcher` (its scheduler instance, its
``d_infer(b)`` and batch cap); the :class:`PolicyArbiter` decides whose batch runs next and books
it through that policy's dispatcher, so the mirrors see exactly one transition per batch, as with
one policy. The rule follows the schedulers' ``arbitration`` (they all share one type):

- ``rotate`` (RR): the policies with work take turns, as RR's robots do.
- ``deadline`` (EDF, Lookahead, Rollout): the policy whose most urgent useful robot has the
  soonest deadline — EDF across the whole fleet, each policy's batch then chosen by its own
  scheduler. Lookahead first arbitrated by its score (robot-seconds gained per device-second,
  each policy with its own ``d_infer``), but a cheap policy's batches always score high: in the
  simulator an ACT beside a π0.5 took 32 of 60 device-seconds in 3,201 small batches while the
  π0.5 robots starved 17.8 % (docs/results/multi_policy). Rollout's score is the robot time
  gained in its window by one policy's robots, which does not compare across policies either.
- ``score`` (a plugin scheduler that sets ``last_score`` to something comparable across
  policies): every policy proposes and the highest score wins.

Each deciding scheduler is shown the other policies (their robots, ``d_infer`` and cap) as
:attr:`~lerobot_armory.schedulers.base.Scheduler.peers` for that one decision: a scheduler that
plans later batches must count theirs (Rollout, planning as if the device were its own, starved
both policies of an ACT-heavy fleet: docs/results/multi_policy). The others ignore it.

With ``rotate`` and ``deadline`` only the picked policy's scheduler runs (its decision costs what
it costs alone, and RR's rotation advances only for the policy served). With one policy every rule
reduces to that policy's dispatcher: the same plans, bit for bit.

Pure, deterministic code with no clock and no I/O, like the dispatcher it drives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from lerobot_armory.dispatch import Dispatcher, Plan, Proposal
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers.base import DevicePeer

RULES = ("rotate", "deadline", "score")
# The name of the policy of a server or simulated fleet that serves one (``--policy.path``).
DEFAULT_POLICY = "default"


class PolicyArbiter:
    """Plans the next batch among several policies' robots (see the module docstring).

    Args:
        dispatchers: each policy's dispatcher, by policy name (the order is the rotation's).

    Raises:
        ValueError: no policy, or schedulers that arbitrate differently (one fleet, one type).
    """

    def __init__(self, dispatchers: Mapping[str, Dispatcher]) -> None:
        if not dispatchers:
            raise ValueError("an arbiter needs at least one policy")
        rules = {getattr(d.scheduler, "arbitration", "deadline") for d in dispatchers.values()}
        if len(rules) != 1 or not rules <= set(RULES):
            raise ValueError(f"the policies' schedulers must arbitrate alike, got {sorted(rules)}")
        self.dispatchers = dict(dispatchers)
        self.rule = rules.pop()
        self._last: str | None = None  # the policy served last (rotate)

    def has_work(self, mirrors: Mapping[str, Sequence[RobotMirror]]) -> bool:
        """Whether some robot of some policy has a useful request."""
        return any(Dispatcher.has_work(m) for m in mirrors.values())

    def plan(self, mirrors: Mapping[str, Sequence[RobotMirror]], now: float) -> tuple[str, Plan] | None:
        """The next batch: ``(policy name, plan)`` booked on that policy's dispatcher, or None
        when no robot has a useful request. ``mirrors`` maps each policy to its robots' mirrors
        (registration order); a policy missing from it has no robots now."""
        names = [n for n in self.dispatchers if Dispatcher.has_work(mirrors.get(n, ()))]
        if not names:
            for name, dispatcher in self.dispatchers.items():
                dispatcher.propose(mirrors.get(name, ()), now)  # ends a dispatcher's hold, books nothing
            return None
        shared = self._show_peers(mirrors)
        try:
            if len(names) == 1 or self.rule != "score":
                name = names[0] if len(names) == 1 else self._pick(names, mirrors)
                proposal = self.dispatchers[name].propose(mirrors[name], now)
            else:
                proposals = {n: self.dispatchers[n].propose(mirrors[n], now) for n in names}
                name = max(names, key=lambda n: _score(proposals[n]))  # the first of equals: registration order
                proposal = proposals[name]
            assert proposal is not None  # has_work held for this policy
            self._last = name
            return name, self.dispatchers[name].book(proposal, mirrors[name])
        finally:
            if shared:  # peers are one decision's view: never left for a later, unrelated call
                for dispatcher in self.dispatchers.values():
                    dispatcher.scheduler.peers = ()

    def complete(self, policy: str, plan: Plan, t_done: float) -> None:
        """The batch ``plan`` of ``policy`` finished at ``t_done``."""
        self.dispatchers[policy].complete(plan, t_done)

    def cancel(self, policy: str, plan: Plan) -> None:
        """The batch ``plan`` of ``policy`` will never be delivered."""
        self.dispatchers[policy].cancel(plan)

    def _show_peers(self, mirrors: Mapping[str, Sequence[RobotMirror]]) -> bool:
        """Tell each policy's scheduler which other policies' robots share the device now
        (:attr:`~lerobot_armory.schedulers.base.Scheduler.peers`). With one policy, or when the
        others have no robots, it sees none: it plans as it does alone."""
        if len(self.dispatchers) == 1:
            return False
        shared = False
        for name, dispatcher in self.dispatchers.items():
            peers = tuple(
                DevicePeer(mirrors[other], d.scheduler.d_infer, d.scheduler.max_batch_size)
                for other, d in self.dispatchers.items()
                if other != name and mirrors.get(other)
            )
            dispatcher.scheduler.peers = peers
            shared = shared or bool(peers)
        return shared

    def _pick(self, names: list[str], mirrors: Mapping[str, Sequence[RobotMirror]]) -> str:
        if self.rule == "rotate":
            order = list(self.dispatchers)
            start = order.index(self._last) + 1 if self._last in order else 0
            ring = order[start:] + order[:start]
            return next(n for n in ring if n in names)
        # deadline: the soonest deadline among each policy's useful robots
        return min(names, key=lambda n: min(m.deadline() for m in mirrors[n] if m.is_useful()))


def _score(proposal: Proposal | None) -> float:
    if proposal is None or not proposal.chosen:
        return float("-inf")
    return proposal.score if proposal.score is not None else float("-inf")
