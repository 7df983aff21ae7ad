"""A proven upper bound on any schedule of a deterministic episode: Lagrangian device pricing.

The exact branch-and-bound of :mod:`armory_research.optimal` solves 5 s episodes of lightly
loaded fleets in seconds, but an overloaded fleet's search is exponential in the horizon. For
those this module gives a *proven upper bound* at the full horizon, so every scheduler can be
scored as a fraction of it (a fraction of a bound understates a scheduler: the optimum lies
between the best schedule found and the bound).

The relaxation. One device is the only thing robots share. Charge every chunk its share of the
device, ``d(b) / b`` for a chunk dispatched in a batch of ``b``; the shares of the chunks that
land before the horizon add up to at most the device time between the first observation's
arrival and the last useful completion, ``τ = horizon - 2·net``. Dualise that single constraint
with a price ``λ`` per device-second:

    value(S) = Σ_j w_j·exec_j(S)
             ≤ Σ_j [w_j·exec_j(S) - λ·cost_j(S)] + λ·τ
             ≤ Σ_j V_j(λ) + λ·τ              for every λ >= 0 and every schedule S,

where ``V_j(λ)`` is the best robot ``j`` could do *alone*, buying chunks at its observations: a
chunk made from observation ``k`` in a batch of ``b`` is dispatched at some instant ``s`` after
that observation reached the server and before the next one did (later, the real batch would
use the newer one), and no earlier than the completion of the robot's previous chunk's batch (one
device runs one batch at a time); it costs ``λ·d(b)/b`` and lands ``d(b)`` plus the downlink
after ``s``. The chunks robot ``j`` receives in any real schedule form such a plan, with the same
observations, instants and batch sizes, hence the same executed steps and cost. For each
observation and landing tick the dynamic program keeps the cheapest cost and the earliest
completion over the instants that land there, which can only add value (an earlier arrival or
an earlier free device never executes fewer steps: the transition follows the union of arrived
chunks). The usefulness rule (``h_min``) is dropped, and so is the batch synchronisation (robots
of a batch share its dispatch instant and batch size): that is what the bound gives away.

Each ``V_j`` is a small exact dynamic program over the robot's ticks, on the same canonical
queue states and the same :func:`~lerobot_armory.transition.advance` transition as the exact
search; ``min_λ`` of the convex dual is found by golden-section search (any ``λ`` gives a valid
bound, so an imprecise minimum only loosens it). The bound holds for *every* schedule,
including ones that idle on purpose, so it also bounds the work-conserving optimum.

Per-slot prices (:func:`time_priced_bound`). The single constraint can be split in time: at every
instant the shares ``1/b`` of the chunks being computed add up to at most 1. A price ``λ(t)`` per
5 ms slot charges each chunk ``∫λ/b`` over its own run window, and the dual adds ``∫λ``. The flat
price is the special case, and per-slot prices can charge the instants every robot wants (just
after the observations land) more than the others, which recovers part of the synchronisation.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from armory_research.optimal import FREE, Episode, _run, canonical


# Completion times in the dynamic program's state are rounded down to this grain.
_GRAIN_S = 0.005


@dataclass(frozen=True)
class BoundResult:
    """A Lagrangian upper bound (weighted executed seconds of the whole horizon).

    Attributes:
        upper_bound: ``min`` over the prices tried of ``Σ_j V_j(λ) + λ·τ``.
        price: the price ``λ`` (weighted robot-seconds per device-second) that gave it.
        evaluations: dual evaluations (one DP per class of identical robots each).
        seconds: wall time.
    """

    upper_bound: float
    price: float
    evaluations: int
    seconds: float


class DevicePrices:
    """``λ(t)``: a price per device-second, constant on consecutive slots of ``slot_s`` from 0.

    The flat price is one value on every slot of the device window (:meth:`flat`); the
    time-priced bound has one price per 5 ms slot. Zero after the last slot (no chunk that lands
    before the horizon runs there).
    """

    def __init__(self, values: Sequence[float], slot_s: float) -> None:
        self.values = np.maximum(np.asarray(values, dtype=float), 0.0)
        self.slot_s = float(slot_s)
        self._cum = np.concatenate(([0.0], np.cumsum(self.values) * self.slot_s))
        self._memo: dict[tuple[float, float, float], tuple[float, float]] = {}

    @classmethod
    def flat(cls, price: float, ep: Episode) -> DevicePrices:
        """``λ`` on the device window ``[net, horizon - net]``, the single-price relaxation."""
        slot = ep.net_s if ep.net_s > 0 else ep.horizon_s
        n = math.ceil(ep.horizon_s / slot - 1e-9)
        values = [price if ep.net_s - 1e-9 <= i * slot and (i + 1) * slot <= ep.horizon_s - ep.net_s + 1e-9 else 0.0 for i in range(n)]
        return cls(values, slot)

    def integral(self, t: float) -> float:
        """``∫_0^t λ``."""
        if t <= 0:
            return 0.0
        i = min(int(t / self.slot_s), len(self.values))
        rest = self.values[i] * (t - i * self.slot_s) if i < len(self.values) else 0.0
        return float(self._cum[i] + rest)

    def total(self) -> float:
        """``∫ λ``: the dual's capacity term (one device-second per second)."""
        return float(self._cum[-1])

    def cheapest(self, lo: float, hi: float, d: float) -> tuple[float, float]:
        """``min`` over ``s`` in ``[lo, hi]`` of ``∫_s^{s+d} λ`` and the ``s`` that attains it.

        The integral is piecewise linear in ``s``, with breaks where ``s`` or ``s + d`` crosses a
        slot boundary, so its minimum is at one of those or an end.
        """
        key = (lo, hi, d)
        hit = self._memo.get(key)
        if hit is not None:
            return hit
        g = self.slot_s
        points = {lo, hi}
        for shift in (0.0, d):
            u = math.ceil((lo + shift) / g) * g
            while u - shift < hi:
                points.add(u - shift)
                u += g
        best = min((self.integral(s + d) - self.integral(s), s) for s in points)
        self._memo[key] = best
        return best

    def load(self, plan: Iterable[tuple[float, float, int]], times: int = 1) -> np.ndarray:
        """Mean device share in each slot (1 = the device fully used) of ``times`` copies of a
        robot's plan, each chunk counting ``1/b`` while it runs."""
        out = np.zeros(len(self.values))
        g = self.slot_s
        for s, d, b in plan:
            first, last = int(s / g), min(int((s + d) / g), len(out) - 1)
            for i in range(first, last + 1):
                out[i] += (min(s + d, (i + 1) * g) - max(s, i * g)) / b
        return out * times / g


class RobotProgram:
    """Robot ``j``'s exact dynamic program alone under device prices: ``V_j(λ)`` from any state.

    A chunk made in a batch of ``b`` and run over ``[s, s + d(b))`` costs ``∫λ / b`` over that
    window. The program runs over ticks. Its state is the robot's queue relative to its index at
    the tick (the exact search's canonical form, so the transition is ``advance()``'s) and the
    time its last chunk's batch completes: one device runs batches one after the other, so a
    robot's next chunk is dispatched no earlier than that. A chunk made from observation ``k`` is
    dispatched at some ``s`` between that observation's arrival and the next one's; the program
    may pick, per landing tick, the cheapest window and the earliest completion of that range
    (both only loosen the relaxation). Values are memoised per state.
    """

    def __init__(self, ep: Episode, j: int, prices: DevicePrices) -> None:
        self.ep, self.j, self.prices = ep, j, prices
        spec = ep.specs[j]
        self.wt = spec.weight / spec.fps
        self.nt = ep.n_ticks(j)
        self.h = spec.h_max
        self.arrive = [ep.obs_arrival(j, k) for k in range(self.nt + 1)]
        self.tick_s = 1.0 / spec.fps
        self.memo: dict[tuple[int, tuple, float], tuple[float, tuple | None]] = {}

    def _options(self, k: int, busy: float) -> list[tuple[int, float, float, float, int]]:
        """``(landing tick, cost, completion, s, b)`` of every undominated chunk from obs ``k``."""
        ep, j = self.ep, self.j
        lo, hi = max(self.arrive[k], busy), self.arrive[k + 1]
        found = []
        for b, d in enumerate(ep.d_infer_s, start=1):
            a0 = ep.arrival_tick(j, lo + d)
            # Dispatching later in [lo, hi) lands one tick later past this instant.
            cut = min(hi, ep.phases_s[j] + a0 * self.tick_s - d - ep.net_s)
            segments = [(a0, lo, max(lo, cut))]
            if cut < hi:
                segments.append((a0 + 1, cut, hi))
            for a, s_lo, s_hi in segments:
                if a < self.nt:
                    cost, s = self.prices.cheapest(s_lo, s_hi, d)
                    found.append((a, cost / b, s_lo + d, s, b))
        # Keep an option only if it is cheaper than every one landing no later and completing
        # no later (an earlier arrival never executes fewer steps).
        found.sort(key=lambda o: (o[0], o[2], o[1]))
        kept: list[tuple[int, float, float, float, int]] = []
        for o in found:
            if all(o[1] < p[1] for p in kept if p[2] <= o[2]):
                kept.append(o)
        return kept

    def _key(self, k: int, queue: tuple, busy: float) -> tuple[int, tuple, float]:
        if busy <= self.arrive[k]:
            busy = -math.inf  # the device is free for this robot's next chunk
        else:
            # Rounded *down* to the grain: the relaxation may only get looser, and the memo
            # stays small (completion times are sums of latencies, nearly all distinct).
            busy = math.floor(busy / _GRAIN_S) * _GRAIN_S
        return (k, queue, busy)

    def value(self, k: int, queue: tuple, busy: float) -> float:
        """Best ``w_j·executed - Σ cost`` from tick ``k`` on (``queue`` relative to the index
        before tick ``k``; no chunk dispatched before ``busy``)."""
        limit = sys.getrecursionlimit()
        sys.setrecursionlimit(max(limit, 4 * self.nt + 1000))
        try:
            return self._value(*self._key(k, queue, busy))
        finally:
            sys.setrecursionlimit(limit)

    def _value(self, k: int, queue: tuple, busy: float) -> float:
        if k >= self.nt:
            return 0.0
        key = (k, queue, busy)
        hit = self.memo.get(key)
        if hit is not None:
            return hit[0]
        choices: list[tuple[tuple, float, float, tuple | None]] = [(queue, 0.0, busy, None)]
        if busy < self.arrive[k + 1]:  # observation k is the latest one at some free instant
            for a, cost, done_at, s, b in self._options(k, busy):
                chunk = (s, self.ep.d_infer_s[b - 1], b)
                choices.append((canonical([*queue, (0, self.h, a - k)]), cost, done_at, chunk))
        best, best_next = -math.inf, None
        for q, cost, done_at, chunk in choices:
            done, (q2, _) = _run((q, FREE), 1, 1)
            v = self.wt * done - cost + self._value(*self._key(k + 1, q2, done_at))
            if v > best:
                best, best_next = v, (chunk, q2, done_at)
        self.memo[key] = (best, best_next)
        return best

    def plan(self) -> tuple[float, list[tuple[float, float, int]]]:
        """``V_j`` from the cold start and a plan attaining it: ``(s, d, b)`` per chunk bought."""
        total = self.value(0, (), -math.inf)
        plan: list[tuple[float, float, int]] = []
        k, queue, busy = 0, (), -math.inf
        while k < self.nt:
            chunk, queue, busy = self.memo[self._key(k, queue, busy)][1]
            if chunk is not None:
                plan.append(chunk)
            k += 1
        return total, plan


def robot_plan(ep: Episode, j: int, prices: DevicePrices) -> tuple[float, list[tuple[float, float, int]]]:
    """``V_j(λ)`` from the cold start and a plan attaining it (see :class:`RobotProgram`)."""
    return RobotProgram(ep, j, prices).plan()


def robot_value(ep: Episode, j: int, price: float) -> float:
    """``V_j(λ)`` for one flat price ``λ`` (see :func:`robot_plan`)."""
    return robot_plan(ep, j, DevicePrices.flat(price, ep))[0]


def device_time(ep: Episode) -> float:
    """``τ``: device time between the first observation's arrival and the last useful completion."""
    return max(0.0, ep.horizon_s - 2 * ep.net_s)


def lagrangian_bound(ep: Episode, tolerance: float = 2e-3, max_evaluations: int = 16) -> BoundResult:
    """Upper bound on the weighted executed time of any schedule of ``ep`` (see the module doc).

    Only the cold start without warm-up is supported (``ep.warmup_s == 0``).
    """
    if ep.warmup_s:
        raise ValueError("lagrangian_bound scores the whole episode; use warmup_s = 0")
    start = time.perf_counter()
    tau = device_time(ep)
    classes = _classes(ep)
    tried: dict[float, float] = {}  # price -> dual value; every one is a valid bound

    def dual(price: float) -> float:
        tried[price] = price * tau + sum(len(m) * robot_value(ep, m[0], price) for m in classes.values())
        return tried[price]

    # Above this price no chunk pays for itself (it adds at most h_max steps).
    min_share = min(d / b for b, d in enumerate(ep.d_infer_s, start=1))
    lo, hi = 0.0, max(s.weight / s.fps * s.h_max for s in ep.specs) / min_share
    dual(lo)
    g = (math.sqrt(5) - 1) / 2
    a, b = lo + (1 - g) * (hi - lo), lo + g * (hi - lo)
    fa, fb = dual(a), dual(b)
    while hi - lo > tolerance * max(1.0, hi) and len(tried) < max_evaluations:
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - g) * (hi - lo)
            fa = dual(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = dual(b)
    best_price = min(tried, key=tried.__getitem__)
    return BoundResult(tried[best_price], best_price, len(tried), time.perf_counter() - start)


def time_priced_bound(
    ep: Episode,
    lower: float,
    start: BoundResult | None = None,
    slot_s: float = _GRAIN_S,
    iterations: int = 200,
    patience: int = 6,
    progress: bool = False,
) -> BoundResult:
    """A tighter bound: one device price per ``slot_s`` instead of one for the whole horizon.

    The device runs at most one batch at a time, so at every instant the shares ``1/b`` of the
    chunks being computed add up to at most 1. Dualising that constraint per slot charges each
    chunk ``∫λ/b`` over its own run window and adds ``∫λ``; for every price curve ``λ >= 0`` the
    result bounds every schedule, exactly as the flat price does (which is the special case of one
    price on ``[net, horizon - net]``, the starting point). Unlike one flat price, per-slot prices
    can charge the instants every robot wants (right after an observation arrives) more than the
    ones nobody wants: that is the batch synchronisation the flat bound gives away.

    Projected subgradient descent with Polyak's step towards ``lower`` (a schedule's value,
    e.g. the best one found), halving the step after ``patience`` iterations without progress;
    every iterate is a valid bound, the least is returned (``price`` is the flat price it started
    from). Still a relaxation: a chunk may claim a share ``1/b`` of a batch whose other robots run
    at other instants, so staggered "fluid" batches remain possible.
    """
    if ep.warmup_s:
        raise ValueError("time_priced_bound scores the whole episode; use warmup_s = 0")
    t0 = time.perf_counter()
    start = start or lagrangian_bound(ep)
    n = math.ceil(ep.horizon_s / slot_s - 1e-9)
    mid = (np.arange(n) + 0.5) * slot_s
    values = np.where((mid > ep.net_s) & (mid < ep.horizon_s - ep.net_s), start.price, 0.0)
    classes = _classes(ep)
    best, step, stall = start.upper_bound, 1.0, 0
    for it in range(iterations):
        prices = DevicePrices(values, slot_s)
        total, load = prices.total(), np.zeros(n)
        for members in classes.values():
            v, plan = robot_plan(ep, members[0], prices)
            total += len(members) * v
            load += prices.load(plan, len(members))
        if total < best - 1e-12:
            best, stall = total, 0
        else:
            stall += 1
            if stall >= patience:  # Held-Karp: halve the step after a stall
                step, stall = step / 2, 0
        if progress:
            print(f"  time-priced bound: iteration {it + 1}/{iterations}: {total:.4f} (best {best:.4f})", file=sys.stderr)
        grad = (1.0 - load) * slot_s  # d(dual)/d(price of each slot)
        norm = float(grad @ grad)
        if norm == 0 or best - lower <= 1e-9 or step < 1e-3:
            break  # prices balance the device exactly / the bound is met / the steps vanished
        values = np.maximum(values - step * (total - lower) / norm * grad, 0.0)
    return BoundResult(best, start.price, start.evaluations + it + 1, time.perf_counter() - t0)


def _classes(ep: Episode) -> dict[tuple, list[int]]:
    """Identical robots (same spec apart from the id, same phase) have the same ``V_j``."""
    classes: dict[tuple, list[int]] = {}
    for j, s in enumerate(ep.specs):
        classes.setdefault((s.fps, s.h_max, s.weight, ep.phases_s[j]), []).append(j)
    return classes
