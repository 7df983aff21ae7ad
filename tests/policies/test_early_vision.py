"""The vision tower recorded as a graph of its own and started before the pre-processor
(``--engine.early_vision``, ``BucketedSampler.start``): the same chunks whether a batch's vision
graph ran early, at its call, or was started on another batch's images.

There is no GPU here, so a recording is stood in for by :class:`_CPUGraph`: its replay recomputes
the recorded function from the same input buffers into the same output tensors, as a CUDA graph's
replay does — so the rest of a bucket reads the vision graph's output where it lies, and a stale
one would show in the chunks.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from lerobot_armory.engine.cuda_graphs import BucketedSampler
from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from tests.support.vla import rtc_batch as batch


class _CPUGraph:
    def __init__(self, fn: Any) -> None:
        self.fn, self.replays = fn, 0
        self.output = fn()

    def replay(self) -> None:
        import torch

        self.replays += 1
        new = self.fn()
        pairs = zip(self.output, new, strict=True) if isinstance(new, tuple) else [(self.output, new)]
        for dst, src in pairs:
            assert isinstance(src, torch.Tensor)
            dst.copy_(src)


def _record_on_cpu(self: BucketedSampler, fn: Any, warmup: int, device: Any) -> tuple[Any, Any]:
    graph = _CPUGraph(fn)
    return graph, graph.output


@pytest.fixture
def recorded_on_cpu(monkeypatch):
    import torch

    monkeypatch.setattr(BucketedSampler, "_record", _record_on_cpu)
    monkeypatch.setattr(torch.cuda, "synchronize", lambda *args, **kwargs: None)


def _engine(path: str, **options: Any) -> PolicyEngine:
    engine = PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, graph_buckets="1,2,4", **options))
    engine.sampler.set_buckets((1, 2, 4))
    return engine


@pytest.mark.parametrize("policy", ["pi05_dir", "smolvla_dir"])
def test_a_vision_graph_started_before_the_pre_processor_gives_the_same_chunks(policy, request, recorded_on_cpu):
    """Every bucket records a vision graph and, per prompt length, the rest; a served batch starts
    its vision graph before the pre-processor and the rest skips it; the chunks equal the same
    engine's with one graph per bucket (``early_vision=false``), for every batch size."""
    path = str(request.getfixturevalue(policy))
    early, late = _engine(path), _engine(path, early_vision=False)
    for engine in (early, late):
        for bucket in (4, 2, 1):
            engine.on_device(engine._capture, bucket)
    assert set(early.sampler.vision_graphs) == {1, 2, 4} and not late.sampler.vision_graphs
    assert "vision tower's graph started before the pre-processor" in early.description
    cameras = len(early._sampler_cameras)
    for (bucket, _), rest in early.sampler.graphs.items():  # the rest takes no image: the tower is not in it
        assert len(rest.inputs) == len(late.sampler.graphs[(bucket, _)].inputs) - cameras
    # The tower runs once a batch, in the vision graph's replay (a rest that ran it again would be
    # right on the CPU and twice the tower's time on a GPU).
    static = early.sampler.vision.__self__
    towers = []
    real = static._embed_images
    static._embed_images = lambda images: towers.append(1) or real(images)
    vision = early.sampler.vision_graphs[4].graph
    for b in (1, 3, 4):
        obs, tasks, seeds, _ = batch(b, seed=b)
        before, replays, ran = early.sampler.early_starts, vision.replays, len(towers)
        np.testing.assert_array_equal(early.infer(obs, tasks, seeds), late.infer(obs, tasks, seeds))
        assert early.sampler.early_starts == before + 1  # started early, not replayed again at the call
        assert vision.replays == replays + (b > 2) and len(towers) == ran + 1
    assert early.sampler.unrecorded == 0 and late.sampler.unrecorded == 0
    # Every bucket's vision graph writes into one set of buffers sized for the largest bucket.
    outputs = [g.output for g in early.sampler.vision_graphs.values()]
    assert all(o.untyped_storage().data_ptr() == w.untyped_storage().data_ptr() for out in outputs for o, w in zip(out, outputs[0], strict=True))


def test_a_batch_started_on_other_images_runs_its_vision_graph_again(pi05_dir, recorded_on_cpu):
    """``start`` on one batch's images, then the call with another batch (a pre-processor that
    made new image tensors, or a start left over from a failed batch): the vision graph runs again
    on the batch's own images, and the chunks are its own."""
    import torch

    engine = _engine(str(pi05_dir))
    for bucket in (4, 2, 1):
        engine.on_device(engine._capture, bucket)

    def inputs(seed: int) -> Any:
        obs, tasks, seeds, _ = batch(2, seed=seed)
        with torch.inference_mode():
            processed = engine.preprocessor({**engine.to_batch(obs), "task": tasks})
            return engine._sampler_inputs(processed, {"noise": engine._noise(seeds)})

    a, b = inputs(1), inputs(2)
    with torch.inference_mode():
        want = engine.sampler(b).clone()
        assert engine.sampler.start(list(a.images))
        got = engine.sampler(b)
        assert engine.sampler.early_starts == 0
        torch.testing.assert_close(got, want, atol=0, rtol=0)
        # A start on the batch's own images counts; a start with no vision graph to run does not.
        assert engine.sampler.start(list(b.images))
        torch.testing.assert_close(engine.sampler(b), want, atol=0, rtol=0)
        assert engine.sampler.early_starts == 1
        assert not engine.sampler.start([torch.cat([b.images[0]] * 3)])  # 6 rows: larger than every bucket
        # A start counts for the call right after it only: one that ran eagerly (a prompt length
        # no graph was recorded for) uses it up, and the next call runs its vision graph itself.
        vision = engine.sampler.vision_graphs[2].graph
        assert engine.sampler.start(list(b.images))
        engine.sampler(b.prompt_fitted(b.prompt_length + 1))
        replays = vision.replays
        torch.testing.assert_close(engine.sampler(b), want, atol=0, rtol=0)
        assert engine.sampler.early_starts == 1 and vision.replays == replays + 1


@pytest.mark.parametrize("failures", [1, 2])
def test_a_failed_split_recording_records_one_graph_a_bucket_instead(pi05_dir, recorded_on_cpu, monkeypatch, failures):
    """A recording that fails halfway (after bucket 4's vision graph and some of its rest) leaves no
    vision graph behind: the buckets are recorded again as one graph each (the split is an extra),
    and if that fails too, none is left and the batches run unrecorded. The chunks are the same
    either way and no batch starts a vision graph whose rest is gone."""
    engine = _engine(str(pi05_dir))
    calls = []

    def fail(self: BucketedSampler, fn: Any, warmup: int, device: Any) -> tuple[Any, Any]:
        calls.append(1)
        # the 4th: bucket 4's recordings are its vision graph, then its rest at each prompt length;
        # the 5th: the first one-graph recording after the split was given up
        if len(calls) == 4 or (failures == 2 and len(calls) == 5):
            raise RuntimeError("CUDA error: out of memory (simulated)")
        return _record_on_cpu(self, fn, warmup, device)

    monkeypatch.setattr(BucketedSampler, "_record", fail)
    engine._record_graphs(log_progress=False)
    assert not engine.sampler.vision_graphs and engine.sampler.vision is None
    if failures == 1:
        assert set(engine.sampler.graphs) == {(b, n) for b in (1, 2, 4) for n in (*engine.prompt_buckets,)}
    else:
        assert not engine.sampler.graphs and "failed" in engine.sampler_note
    obs, tasks, seeds, _ = batch(3)
    want = _engine(str(pi05_dir), early_vision=False).infer(obs, tasks, seeds)
    np.testing.assert_allclose(engine.infer(obs, tasks, seeds), want, atol=1e-6, rtol=0)
    assert engine.sampler.early_starts == 0 and engine.sampler.unrecorded == 0


def test_early_vision_needs_every_pre_processor_step_to_be_one_of_lerobots_that_leave_images_alone(pi05_dir, smolvla_dir):
    """The identity check of ``start`` is sound only if no step can change an image tensor in
    place: a step of a checkpoint's own (after the device step too), or a subclass of one of
    LeRobot's defined elsewhere, turns the split off; LeRobot's π0.5 and SmolVLA pipelines keep it."""
    from lerobot_armory.engine.policy_engine import _known_steps_only

    engines = [_engine(str(pi05_dir)), _engine(str(smolvla_dir))]
    assert all(_known_steps_only(e.preprocessor) and e.sampler.vision is not None for e in engines)
    steps = list(engines[0].preprocessor.steps)

    class ClampImages:  # a checkpoint's own step
        _registry_name = "clamp_images"

    class OwnDevice(type(steps[-1])):  # inherits LeRobot's registry name, not its code
        pass

    for extra in (ClampImages(), object.__new__(OwnDevice)):
        assert not _known_steps_only(type("Pipeline", (), {"steps": [*steps, extra]})())
    assert not _known_steps_only(type("Pipeline", (), {"steps": []})())


def test_the_prompt_bucket_comes_from_the_batchs_own_mask_read_on_the_host(pi05_dir):
    """Choosing a batch's prompt bucket reads no mask back from the device (the read-back would
    wait for the vision graph started early): the tokenizer's mask is read on the host before the
    device step and bound to the tensor the step makes. Another batch's mask is never used for it:
    a mask the pipeline did not return last is read back, as before. The chunks are the same."""
    import torch
    from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK as MASK

    engine = _engine(str(pi05_dir))
    columns = engine._prompt_columns
    assert columns is not None and columns.attached
    short, long = ["pick"] * 2, ["pick up the red block and put it in the green bowl " * 3] * 2
    obs = [engine.example_observation(seed=k) for k in range(2)]
    with torch.inference_mode():
        a = engine.preprocessor({**engine.to_batch(obs), "task": short})[MASK]
        b = engine.preprocessor({**engine.to_batch(obs), "task": long})[MASK]
    assert columns.used(a) is None and torch.equal(columns.used(b), b.any(dim=0))  # only the last batch's
    from lerobot_armory.engine.cuda_graphs import bucket_for

    own = [bucket_for(int(m.any(dim=0).sum()), engine.prompt_buckets) for m in (a, b)]
    assert [engine._prompt_bucket(a), engine._prompt_bucket(b)] == own and own[0] < own[1]
    read_back = _engine(str(pi05_dir))
    read_back._prompt_columns = None
    served, real = [], columns.used
    columns.used = lambda masks: served.append(real(masks)) or served[-1]
    for tasks in (short, long):
        np.testing.assert_array_equal(engine.infer(obs, tasks, [0, 1]), read_back.infer(obs, tasks, [0, 1]))
    assert len(served) == 2 and all(u is not None for u in served)
