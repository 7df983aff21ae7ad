"""The gRPC edge: the serving core's own messages <-> the robot protocol's protobuf, both ways."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_armory.entrypoints.grpc.translate import clock_sync_from_wire, grant_to_wire, report_from_wire, to_wire
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.serving.messages import ChunkOut, Grant, Notice, NoticeKind, SyncRequest
from lerobot_armory.wire import decode


def test_every_notice_kind_is_the_protocols_with_the_same_value():
    assert {k.name: k.value for k in NoticeKind} == dict(pb.Notice.Kind.items())


def test_a_chunk_goes_out_as_raw_float32_and_decodes_to_the_same_actions():
    actions = np.arange(20, dtype=np.float64).reshape(10, 2) / 7.0  # float64 in: the wire carries float32
    msg = to_wire(ChunkOut(chunk_id=5, i_start=40, actions=actions, server_send_time=12.5, obs_capture_time=3.25))
    assert msg.WhichOneof("kind") == "chunk"
    chunk = msg.chunk
    assert (chunk.chunk_id, chunk.i_start, chunk.server_send_time, chunk.obs_capture_time) == (5, 40, 12.5, 3.25)
    out = decode(chunk.actions)
    assert out.dtype == np.float32 and out.shape == (10, 2)
    np.testing.assert_array_equal(out, actions.astype(np.float32))


def test_notices_and_sync_requests_keep_every_field():
    notice = to_wire(Notice(NoticeKind.INFERENCE_FAILED, "batch failed", 17)).notice
    assert (notice.kind, notice.message, notice.index) == (pb.Notice.INFERENCE_FAILED, "batch failed", 17)
    assert to_wire(Notice(NoticeKind.INFO, "hello")).notice.index == -1
    sync = to_wire(SyncRequest(3, 99.5)).sync_request
    assert (sync.sync_id, sync.server_send_time) == (3, 99.5)
    with pytest.raises(TypeError, match="not a server message"):
        to_wire("a string")  # type: ignore[arg-type]


def test_a_report_keeps_at_most_the_receipts_that_can_mean_anything():
    wire = pb.ExecutionReport(
        report_time=4.0, index=30, executed_steps=28, starved_steps=2,
        chunks=[pb.ChunkReceipt(chunk_id=k, arrival_time=0.1 * k, first_executed_index=k % 3 - 1) for k in range(100)],
    )  # fmt: skip
    report = report_from_wire(wire, max_receipts=8)
    assert (report.report_time, report.index, report.executed_steps, report.starved_steps) == (4.0, 30, 28, 2)
    assert [r.chunk_id for r in report.receipts] == list(range(8))
    assert report.receipts[2].arrival_time == pytest.approx(0.2) and report.receipts[0].first_executed_index == -1


def test_a_clock_sync_takes_the_robots_stamps_only_and_a_grant_every_field():
    sync = clock_sync_from_wire(pb.ClockSync(sync_id=4, client_send_time=2.0, client_recv_time=1.5, server_recv_time=9.0))
    assert (sync.sync_id, sync.client_send_time, sync.client_recv_time) == (4, 2.0, 1.5)
    grant = Grant(weight=0.5, tier="fast", fps=30.0, h_min=2, h_max=6, max_device_share=0.25, rule="robot:a")
    wire = grant_to_wire(grant)
    assert Grant(wire.weight, wire.tier, wire.fps, wire.h_min, wire.h_max, wire.max_device_share, wire.rule) == grant
