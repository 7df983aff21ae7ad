"""A proven upper bound on any schedule of a deterministic episode: Lagrangian device pricing.

The exact branch-and-bound of :mod:`lerobot_armory.sim.optimal` solves 5 s episodes of lightly
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

where ``V_j(λ)`` is the best robot ``j`` could do *alone*, buying chunks at its observations (a
chunk bought in a batch of ``b`` costs ``λ·d(b)/b``; it is dispatched as soon as both its
observation has reached the server and the batch of the robot's previous chunk has completed,
from the latest observation at that instant, and lands ``d(b)`` plus the downlink later). Every
real schedule projects onto such a plan of equal or better value: the device runs one batch at a
time, so a robot's next batch starts after its previous one completed, and a real batch starts
at or after that instant with the latest observation, so its chunk lands no earlier in the
relaxation; by induction the relaxed robot's index is never behind, and an earlier arrival never
lowers executed steps (the transition follows the union of arrived chunks). The usefulness rule (``h_min``) is dropped in the relaxation
because it is not monotone under that projection, and the batch-synchronisation (robots of a
batch share its dispatch instant) is dropped too: that is what the bound gives away.

Each ``V_j`` is a small exact dynamic program over the robot's ticks, on the same canonical
queue states and the same :func:`~lerobot_armory.mirror.advance` transition as the exact
search; ``min_λ`` of the convex dual is found by golden-section search (any ``λ`` gives a valid
bound, so an imprecise minimum only loosens it). The bound holds for *every* schedule,
including ones that idle on purpose, so it also bounds the work-conserving optimum.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

from lerobot_armory.sim.optimal import FREE, Episode, _run, canonical


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


def robot_value(ep: Episode, j: int, price: float) -> float:
    """``V_j(λ)``: robot ``j``'s best ``w_j·executed - λ·Σ shares`` alone, from the cold start.

    Exact dynamic program over ticks. The state is the robot's queue relative to its index at
    the tick (the exact search's canonical form, so the transition is ``advance()``'s) and the
    time its last chunk's batch completes: one device runs batches one after the other, so a
    robot's next chunk is dispatched no earlier than that, from the latest observation then.
    """
    spec = ep.specs[j]
    wt = spec.weight / spec.fps
    nt = ep.n_ticks(j)
    h = spec.h_max
    shares = [price * d / b for b, d in enumerate(ep.d_infer_s, start=1)]
    arrive = [ep.obs_arrival(j, k) for k in range(nt + 1)]
    memo: dict[tuple[int, tuple, float], float] = {}

    def value(k: int, queue: tuple, busy: float) -> float:
        if k >= nt:
            return 0.0
        if busy <= arrive[k]:
            busy = -math.inf  # the device is free for this robot's next chunk
        else:
            # Rounded *down* to the grain: the relaxation may only get looser, and the memo
            # stays small (completion times are sums of latencies, nearly all distinct).
            busy = math.floor(busy / _GRAIN_S) * _GRAIN_S
        key = (k, queue, busy)
        hit = memo.get(key)
        if hit is not None:
            return hit
        choices: list[tuple[tuple, float, float]] = [(queue, 0.0, busy)]
        if busy < arrive[k + 1]:  # observation k is the latest one at some free instant
            start = max(arrive[k], busy)
            seen: dict[int, float] = {}
            for b, d in enumerate(ep.d_infer_s):
                a = ep.arrival_tick(j, start + d)
                # Same arrival tick, same coverage: only the cheapest share and earliest
                # completion matter (a bigger batch is never both earlier and cheaper here).
                if a < nt and (a not in seen or shares[b] < seen[a]):
                    seen[a] = shares[b]
                    choices.append((canonical([*queue, (0, h, a - k)]), shares[b], start + d))
        best = -math.inf
        for q, cost, done_at in choices:
            done, (q2, _) = _run((q, FREE), 1, 1)
            best = max(best, wt * done - cost + value(k + 1, q2, done_at))
        memo[key] = best
        return best

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 4 * nt + 1000))
    try:
        return value(0, (), -math.inf)
    finally:
        sys.setrecursionlimit(limit)


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
    # Identical robots (same spec apart from the id, same phase) have the same V_j.
    classes: dict[tuple, list[int]] = {}
    for j, s in enumerate(ep.specs):
        classes.setdefault((s.fps, s.h_max, s.weight, ep.phases_s[j]), []).append(j)
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
