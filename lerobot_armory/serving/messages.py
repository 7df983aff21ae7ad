"""The serving core's own messages: what the fleet and the loop take in and hand out.

No wire format reaches the core. Each entrypoint translates at its edge: the gRPC service turns a
robot's protobuf messages into these and encodes what a robot's :class:`~.outbox.Outbox` holds on
the way out; the openpi endpoint reads a chunk's actions as they are, never encoded and decoded
again. The shapes mirror the robot protocol (``proto/armory.proto``) so that translation is one
line per field, but they are plain dataclasses: a new entrypoint needs no protobuf.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


class NoticeKind(enum.IntEnum):
    """Why the server tells a robot something (the robot protocol's ``Notice.Kind``, same values)."""

    INFO = 0
    REJECTED_OBSERVATION = 1  # the observation was dropped; the text says why; the stream goes on
    REJECTED_REPORT = 2
    INFERENCE_FAILED = 3  # the batch failed; the robot will be served again
    SHUTDOWN = 4  # the server is stopping; reconnect later
    DROPPED = 5  # the server ended this robot's session (the text says why); register again
    CLOCK = 6  # the robot's clock looked stepped or implausible; a sync request follows
    MOVED = 7  # a cluster moves the robot to another replica between two of its chunks


@dataclass(frozen=True)
class Notice:
    """A line of text for one robot (``index``: the observation concerned, -1: none)."""

    kind: NoticeKind
    message: str
    index: int = -1


@dataclass(frozen=True)
class ChunkOut:
    """An action chunk for one robot: ``actions`` is float32 ``(H, action_dim)``, in the robot's
    action space; ``i_start`` the index of the observation it was computed from."""

    chunk_id: int
    i_start: int
    actions: np.ndarray
    server_send_time: float
    obs_capture_time: float
    episode: int = 0  # the robot's episode the observation belonged to


@dataclass(frozen=True)
class SyncRequest:
    """The server asks for a clock exchange (stamped with the server's send time)."""

    sync_id: int
    server_send_time: float


# What a robot's outbox holds.
ServerMessage = ChunkOut | Notice | SyncRequest


@dataclass(frozen=True)
class ClockSync:
    """A robot's side of a clock exchange (robot clock). ``sync_id`` 0 completes the registration
    round trip; > 0 answers the server's :class:`SyncRequest` of that id."""

    sync_id: int
    client_send_time: float
    client_recv_time: float


@dataclass(frozen=True)
class Receipt:
    """One chunk's arrival on the robot (robot clock) and the offset of its first executed action
    (-1: never executed)."""

    chunk_id: int
    arrival_time: float
    first_executed_index: int


@dataclass(frozen=True)
class ExecutionReport:
    """A robot's execution report: its index at ``report_time`` (robot clock), its totals since
    the stream opened, and receipts of the chunks that arrived."""

    report_time: float
    index: int
    executed_steps: int
    starved_steps: int
    receipts: tuple[Receipt, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class Grant:
    """What the grant rules grant a registering robot (``rule``: the rule that matched:
    ``robot:ID``, ``token:NAME`` or ``default``)."""

    weight: float
    tier: str
    fps: float
    h_min: int
    h_max: int
    max_device_share: float = 1.0
    rule: str = "default"
