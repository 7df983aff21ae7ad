"""The robot protocol's protobuf messages <-> the serving core's own (:mod:`lerobot_armory.serving.messages`).

The only place the two meet: the service calls these at its edge, in both directions.
"""

from __future__ import annotations

import numpy as np

from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.serving.messages import (
    ChunkOut,
    ClockSync,
    ExecutionReport,
    Grant,
    Notice,
    Receipt,
    ServerMessage,
    SyncRequest,
)
from lerobot_armory.wire import encode


def to_wire(msg: ServerMessage) -> pb.ServerMessage:
    """An outbox message as the robot's stream carries it (a chunk's actions as raw float32)."""
    if isinstance(msg, ChunkOut):
        chunk = pb.ActionChunk(
            chunk_id=msg.chunk_id,
            i_start=msg.i_start,
            actions=encode("action", np.ascontiguousarray(msg.actions, dtype=np.float32)),
            server_send_time=msg.server_send_time,
            obs_capture_time=msg.obs_capture_time,
            episode=msg.episode,
        )
        return pb.ServerMessage(chunk=chunk)
    if isinstance(msg, Notice):
        return pb.ServerMessage(notice=pb.Notice(kind=int(msg.kind), message=msg.message, index=msg.index))
    if isinstance(msg, SyncRequest):
        return pb.ServerMessage(sync_request=pb.ClockSyncRequest(sync_id=msg.sync_id, server_send_time=msg.server_send_time))
    raise TypeError(f"not a server message: {type(msg).__name__}")


def clock_sync_from_wire(msg: pb.ClockSync) -> ClockSync:
    """A robot's clock exchange (the server stamps it echoes are not used)."""
    return ClockSync(int(msg.sync_id), float(msg.client_send_time), float(msg.client_recv_time))


def report_from_wire(msg: pb.ExecutionReport, max_receipts: int) -> ExecutionReport:
    """An execution report with at most its first ``max_receipts`` receipts (no more can mean anything)."""
    receipts = tuple(
        Receipt(int(c.chunk_id), float(c.arrival_time), int(c.first_executed_index)) for c in msg.chunks[:max_receipts]
    )
    return ExecutionReport(float(msg.report_time), int(msg.index), int(msg.executed_steps), int(msg.starved_steps), receipts)


def grant_to_wire(grant: Grant) -> pb.Grant:
    """What registration tells the robot it was granted."""
    return pb.Grant(
        weight=grant.weight, tier=grant.tier, fps=grant.fps, h_min=grant.h_min, h_max=grant.h_max,
        max_device_share=grant.max_device_share, rule=grant.rule,
    )  # fmt: skip
