"""The Triton kernels of the π0 family's fused layers (``acceleration/triton_kernels.py``), run on the
CPU through Triton's interpreter: the same values as PyTorch's operations they replace, the same
chunks as LeRobot's sampler, fewer launches a sample. Off on a CPU otherwise, with the reason.

The interpreter rounds float32 to bf16 its own way (not to nearest even, as a GPU does), so bf16
accuracy is not judged here: float32 is."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from lerobot_armory.engine import rtc
from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from tests.support.vla import sampler_inputs


@pytest.fixture
def interpreted(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Triton's kernels run through its CPU interpreter while the test runs (jitted afresh, in
    that mode, and forgotten after)."""
    from lerobot_armory.acceleration import triton_kernels

    pytest.importorskip("triton", reason="Triton ships with PyTorch's CUDA builds; a CPU-only torch has none")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    jit = triton_kernels._kernels  # a test may patch the module's name: clear the cache itself after
    jit.cache_clear()
    yield
    jit.cache_clear()


KERNELS = ("gelu_tanh_mul", "add_rms_norm", "rope_qkv", "masked_softmax")
# Two denoising steps, not the policy's ten: each step runs the same layers with the same kernels,
# and the interpreter runs every program of every launch in Python (ten steps took ~1 min a test).
# bf16 keeps the ten: the interpreter's own bf16 rounding puts π0 0.011-0.012 off at two or four
# steps, over the 0.01 bound that holds at ten.
STEPS = "num_inference_steps=2"


def counted_kernel_calls(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the Triton kernels the fused layers call, in order, while the test runs; each
    runs outside any dispatch mode (one launch each: the interpreter's own tensor work is not an
    operation a GPU would launch)."""
    from torch.utils._python_dispatch import _disable_current_modes

    from lerobot_armory.acceleration import pi05_kernels

    calls: list[str] = []
    for name in KERNELS:

        def run(*args: Any, kernel: Any = getattr(pi05_kernels, name), name: str = name, **kwargs: Any) -> Any:
            calls.append(name)
            with _disable_current_modes():
                return kernel(*args, **kwargs)

        monkeypatch.setattr(pi05_kernels, name, run)
    return calls


def test_the_kernels_compute_what_pytorchs_operations_do(interpreted):
    import torch

    from lerobot_armory.acceleration.triton_kernels import add_rms_norm, gelu_tanh_mul

    gen = torch.Generator().manual_seed(0)
    for shape in ((3, 2 * 40), (2, 5, 2 * 1100)):  # 1100 columns: two programs a row, the second part-masked
        gate_up = 3 * torch.randn(*shape, generator=gen)
        gate, up = gate_up.chunk(2, dim=-1)
        got = gelu_tanh_mul(gate_up)
        assert got.shape == gate.shape and got.dtype == torch.float32
        torch.testing.assert_close(got, torch.nn.functional.gelu(gate, approximate="tanh") * up, atol=1e-5, rtol=1e-5)
    h, y = torch.randn(2, 7, 96, generator=gen), torch.randn(2, 7, 96, generator=gen)
    weight, gate = torch.rand(96, generator=gen), torch.randn(1, 1, 96, generator=gen)
    for g in (gate, None):
        total, normed = add_rms_norm(h, y, g, weight, 1e-6, torch.float32)
        want = h + y if g is None else torch.addcmul(h, y, g)
        torch.testing.assert_close(total, want, atol=1e-6, rtol=0)
        torch.testing.assert_close(normed, torch.nn.functional.rms_norm(want, (96,), weight, 1e-6), atol=2e-6, rtol=1e-6)
    _, normed = add_rms_norm(h, y.to(torch.bfloat16), gate.to(torch.bfloat16), weight, 1e-6, torch.bfloat16)
    assert normed.dtype == torch.bfloat16


def test_the_rotary_and_softmax_kernels_compute_what_pytorchs_operations_do(interpreted):
    """The rotation writes q and, into the cache's slice only, k and v (the tables per batch row or
    one for all); the softmax adds the mask in place over rows longer than one pass (two programs'
    worth of keys), masked keys get 0, and a NaN score spoils its own row only."""
    import torch

    from lerobot_armory.acceleration.triton_kernels import _SOFTMAX_BLOCK, masked_softmax, rope_qkv

    gen = torch.Generator().manual_seed(0)
    b, length, heads, kv, d = 2, 5, 3, 2, 8
    qkv = torch.randn(b, length, heads + kv, d, generator=gen)
    swapped = torch.cat((qkv[..., d // 2 :], qkv[..., : d // 2]), dim=-1)
    for rows in (b, 1):
        cos, sin = (torch.randn(rows, length, heads + kv, d, generator=gen) for _ in range(2))
        cache = torch.full((b, length + 4, kv, d), 7.0)
        q = rope_qkv(qkv, cos, sin, heads, cache[:, 3 : 3 + length])
        want = qkv * cos + swapped * sin
        torch.testing.assert_close(q, want[:, :, :heads], atol=1e-6, rtol=0)
        torch.testing.assert_close(cache[:, 3 : 3 + length], want[:, :, heads:], atol=1e-6, rtol=0)
        assert (cache[:, :3] == 7.0).all() and (cache[:, 3 + length :] == 7.0).all()
    with pytest.raises(ValueError, match="rope_qkv"):
        rope_qkv(qkv, cos, sin, heads, torch.empty(b, length, kv + 1, d))
    # Rows of 7 keys (the unaligned variant), 632 (aligned: the expert's at one prompt length),
    # 2,048 (aligned, two passes) and BLOCK + 300 (unaligned, two passes); 3 heads (a padded head
    # block) and 8 (π0.5's).
    for keys, heads_ in ((7, 3), (632, 8), (2048, 3), (_SOFTMAX_BLOCK + 300, 4)):
        scores = 4 * torch.randn(2, 3, heads_, keys, generator=gen)
        mask = torch.where(torch.rand(2, 3, 1, keys, generator=gen) < 0.3, -2.3819763e38, 0.0)
        mask[..., -1] = 0.0  # every query attends a key
        mask[0, 1, 0, : min(keys - 1, _SOFTMAX_BLOCK)] = float("-inf")  # a first pass with nothing but -inf: no NaN from it
        scores[1, 2, heads_ - 1, keys // 2] = float("nan")
        want = torch.softmax(scores + mask, dim=-1)
        got = masked_softmax(scores.clone(), mask)
        assert got[1, 2, heads_ - 1].isnan().all() and got.isnan().sum() == keys
        finite = ~want.isnan()
        torch.testing.assert_close(got[finite], want[finite], atol=1e-6, rtol=1e-5)
        assert (got[(mask < 0).expand_as(got) & finite] == 0).all()
        if keys <= _SOFTMAX_BLOCK:  # the two passes forced on a row that fits one (micro.py's comparison)
            torch.testing.assert_close(masked_softmax(scores.clone(), mask, one_pass=False), got, equal_nan=True, atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="masked_softmax"):
        masked_softmax(scores, mask[:, :, :, :-1])
    with pytest.raises(ValueError, match="two passes"):
        masked_softmax(scores, mask, one_pass=True)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pi05", "pi0"])
def test_with_the_kernels_the_chunks_stay_lerobots_and_a_sample_launches_fewer_kernels(kind, request, interpreted, monkeypatch):
    """Float32: the fused sampler with the Triton kernels gives LeRobot's chunks (1e-5, with RTC),
    and a sample launches fewer kernels, each Triton kernel standing for at least two of PyTorch's
    (the MLP's activation: GELU and its product; the residual sum, the norm and its cast)."""
    import torch

    from lerobot_armory.acceleration.op_trace import OpTrace
    from lerobot_armory.acceleration.pi0_static import StaticPi0
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    sampler = {"pi05": StaticPi05, "pi0": StaticPi0}[kind]
    horizon = 8
    guided = rtc.RTCOptions(enabled=True, execution_horizon=horizon, delay_margin=0)
    with monkeypatch.context() as off_cpu:
        off_cpu.delenv("TRITON_INTERPRET")  # the engine's own dry run without the interpreted kernels
        engine = PolicyEngine(PolicyOptions(str(request.getfixturevalue(f"{kind}_dir")), "cpu", overrides=[STEPS]), guided, EngineOptions(static_sampler=True))
        plain = sampler(engine.policy, guided=True)
    reference = sampler(engine.policy, guided=True, fused=False)
    assert not plain.ops.hand_kernels and "CUDA only" in plain.ops.hand_kernels_reason
    fused = sampler(engine.policy, guided=True)
    assert fused.ops.hand_kernels, fused.ops.hand_kernels_reason
    calls = counted_kernel_calls(monkeypatch)
    for b in (1, 3):
        inputs = sampler_inputs(engine, b, seed=b, horizon=horizon)
        with torch.no_grad():
            want = reference.sample(inputs)
            plain.sample(inputs), fused.sample(inputs)  # the per-size constants, outside the count
            with OpTrace() as before:
                theirs = plain.sample(inputs)
            calls.clear()
            with OpTrace() as after:
                ours = fused.sample(inputs)
        torch.testing.assert_close(ours, want, atol=1e-5, rtol=0)
        torch.testing.assert_close(theirs, want, atol=1e-5, rtol=0)
        assert set(calls) == set(KERNELS)
        assert after.launches + len(calls) <= before.launches - len(calls), (before.launches, after.launches, len(calls))
        assert not after.host_syncs


@pytest.mark.slow
def test_a_compiled_sampler_runs_the_kernels_only_between_its_compiled_layers(pi05_dir, interpreted, monkeypatch):
    """``--engine.compile_sampler=true``: inside a compiled layer the operations are PyTorch's
    (inductor fuses them; an opaque kernel would stand between its fusions), between layers — a
    layer's pending sum with the next layer's input norm — the Triton kernel runs; the chunks stay
    LeRobot's. Dynamo's ``eager`` backend stands in for inductor (the same tracing)."""
    import torch

    from lerobot_armory.acceleration.pi05_static import StaticPi05

    real_compile = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: real_compile(fn, **{**kw, "backend": "eager"}))
    torch._dynamo.reset()
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=[STEPS]), engine=EngineOptions(static_sampler=True))
    reference, sampler = StaticPi05(engine.policy, fused=False), StaticPi05(engine.policy)
    sampler.compile_layers()
    assert sampler.ops.hand_kernels
    calls = counted_kernel_calls(monkeypatch)
    inputs = sampler_inputs(engine, 2, seed=1, guided=False)
    with torch.no_grad():
        ours, want = sampler.sample_compiled(inputs), reference.sample(inputs)
    between_layers = len(sampler.vlm.layers) - 1 + (len(sampler.expert.layers) - 1) * sampler.num_steps
    # ... and the last VLM layer's keys and values, whose layer is cut short before its attention.
    assert sorted(calls) == ["add_rms_norm"] * between_layers + ["rope_qkv"]
    torch.testing.assert_close(ours, want, atol=1e-5, rtol=0)
    torch._dynamo.reset()


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pi05", "pi0"])
@pytest.mark.parametrize("float32_products", [False, True], ids=["bf16-products", "float32-products"])
def test_in_bf16_every_kernel_launch_was_compiled_at_load_and_the_chunks_stay_near(kind, float32_products, request, interpreted, monkeypatch):
    """bf16, with the output projections in bf16 or (on a GPU) float32: the load-time check
    (``hand_kernels_reason``) launches every variant Triton will compile for a sample — the same
    pointer dtypes, block sizes, gate or none and integer specialisations — so nothing compiles
    inside a CUDA graph's recording; the chunks are finite and within a bf16 rounding of the
    sampler without the kernels (the interpreter's own bf16 rounding included)."""
    import torch

    from lerobot_armory.acceleration import pi05_kernels, triton_kernels
    from lerobot_armory.acceleration.pi0_static import StaticPi0
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    if float32_products:  # the GPU's product, stood in for by its arithmetic (test_pi05_static.py)
        monkeypatch.setattr(pi05_kernels, "float32_products_reason", lambda device, dtype: None)
        monkeypatch.setattr(pi05_kernels, "_float32_mm", lambda a, b: torch.mm(a.float(), b.float()))
    launches: list[tuple[Any, ...]] = []
    jitted = triton_kernels._kernels()

    class Recorded:
        def __init__(self, kernel: Any, name: str) -> None:
            self.kernel, self.name = kernel, name
            names = kernel.arg_names  # the interpreter keeps jit's options in ``kwargs``
            self.unspecialised = {names.index(n) for n in kernel.kwargs.get("do_not_specialize") or ()}

        def __getitem__(self, grid: Any) -> Any:
            def launch(*args: Any, **kwargs: Any) -> Any:
                # What Triton specialises on: tensors' dtypes, integers' divisibility by 16 (and 1)
                # unless the kernel says not to, constexprs
                # and pointers' alignment to 16 bytes.
                key = tuple(
                    (str(a.dtype), a.data_ptr() % 16 == 0) if isinstance(a, torch.Tensor)
                    else "any" if i in self.unspecialised
                    else (a % 16 == 0, a == 1) if isinstance(a, int)
                    else type(a).__name__
                    for i, a in enumerate(args)
                )  # fmt: skip
                launches.append((self.name, key, tuple(sorted(kwargs.items()))))
                return self.kernel[grid](*args, **kwargs)

            return launch

    recorded = tuple(Recorded(kernel, name) for kernel, name in zip(jitted, ("gelu", "norm", "rope", "softmax"), strict=True))
    monkeypatch.setattr(triton_kernels, "_kernels", lambda: recorded)
    sampler = {"pi05": StaticPi05, "pi0": StaticPi0}[kind]
    with monkeypatch.context() as off_cpu:
        off_cpu.delenv("TRITON_INTERPRET")  # the engine's own dry run without the interpreted kernels
        engine = PolicyEngine(PolicyOptions(str(request.getfixturevalue(f"{kind}_dir")), "cpu", overrides=["dtype=bfloat16"]), engine=EngineOptions(static_sampler=True))
        plain = sampler(engine.policy)
    launches.clear()  # the engine's own sampler launched some: only this one's load-time check counts
    fused = sampler(engine.policy)
    assert fused.ops.hand_kernels and fused.ops.float32_products == float32_products
    compiled_at_load = set(launches)
    launches.clear()
    for b in (1, 3):
        inputs = sampler_inputs(engine, b, seed=b, guided=False)
        with torch.no_grad():
            ours, theirs = fused.sample(inputs), plain.sample(inputs)
        assert launches and set(launches) <= compiled_at_load, set(launches) - compiled_at_load
        assert {name for name, _, _ in launches} == {"gelu", "norm", "rope", "softmax"}
        assert torch.isfinite(ours).all()
        torch.testing.assert_close(ours, theirs, atol=1e-2, rtol=0)


@pytest.mark.subprocess
def test_every_kernel_compiles_for_hopper_with_vector_loads_and_no_spills(tmp_path):
    """No GPU here: each kernel compiled for sm_90a (an H100's / H200's) at the full π0.5's shapes,
    in bf16 and float32, through Triton's own code generator and ``ptxas`` — the check that the
    kernels build for the device at all, that their global loads and stores are vectorised (the
    strides and lengths Triton does not specialise on come as multiples it can see) and that no
    register spills. Integers Triton specialises are given the divisibility a full π0.5 has."""
    import re
    import subprocess

    triton = pytest.importorskip("triton")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from lerobot_armory.acceleration import triton_kernels

    triton_kernels._kernels.cache_clear()  # jitted for the GPU (no interpreter)
    gelu, norm, rope, softmax = triton_kernels._kernels()
    ptxas = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "ptxas"
    if not ptxas.exists():
        pytest.skip("this Triton carries no ptxas")
    unspecialised = {"qkv_stride", "table_stride", "q_stride", "dest_stride", "dest_row", "length"}
    for dt in ("bf16", "fp32"):
        ints = {"width": "i32", "eps": "fp32", **{name: "i32" for name in unspecialised}}  # as Triton types Python ints
        cases = [
            (gelu, {"BLOCK": 1024}, 4),
            (norm, {"HAS_GATE": True, "BLOCK": 2048}, 4),
            (rope, {"HEADS": 8, "ALL": 10, "D": 256, "HEAD_BLOCK": 16, "BLOCK": 128}, 4),
            *((softmax, {"LENGTH_DIV": 8, "HEADS": 8, "HEAD_BLOCK": 8, "BLOCK": triton_kernels._SOFTMAX_BLOCK, "ONE_PASS": one}, 8) for one in (True, False)),
        ]
        for kernel, constexprs, warps in cases:
            float32_args = {"h_ptr", "weight_ptr", "total_ptr"}  # the norm's float32 stream and weight
            signature = {
                name: "constexpr" if name in constexprs else ints[name] if name in ints else f"*{'fp32' if name in float32_args else dt}"
                for name in kernel.arg_names
            }
            attrs = {(i,): [["tt.divisibility", 16]] for i, (name, kind) in enumerate(signature.items()) if kind.startswith("*") or name == "width"}
            compiled = triton.compile(ASTSource(kernel, signature, constexprs, attrs), target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})
            ptx = compiled.asm["ptx"]
            name = kernel.fn.__name__
            source = tmp_path / f"{name}_{dt}.ptx"
            source.write_text(ptx)
            report = subprocess.run([str(ptxas), "-arch=sm_90a", "-v", str(source), "-o", str(tmp_path / "out.cubin")], capture_output=True, text=True)
            assert report.returncode == 0 and name in report.stderr, (name, report.stderr[-500:])
            assert "0 bytes spill stores" in report.stderr, (name, dt, report.stderr)
            accesses = set(re.findall(r"(?:ld|st)\.global(?:\.[a-z0-9]+)*", ptx))
            assert accesses and all(".v4." in a for a in accesses), (name, dt, accesses)
            if kernel is softmax:  # the mask read in the scores' layout: no conversion through shared memory
                assert compiled.metadata.shared <= 256, (dt, compiled.metadata.shared)
    triton_kernels._kernels.cache_clear()


@pytest.mark.slow
def test_attention_kernels_that_fail_their_check_turn_off_alone_and_are_told(pi05_dir, interpreted, monkeypatch, caplog):
    """The rotary and softmax kernels are checked apart from the first two: where their check fails
    PyTorch's operations serve them, the activation and norm kernels stay, the engine logs why and
    its description says so; the chunks stay LeRobot's (float32)."""
    import logging

    import torch

    from lerobot_armory.acceleration import pi05_kernels
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    monkeypatch.setattr(pi05_kernels, "attention_kernels_reason", lambda *args: "a stand-in failure")
    with caplog.at_level(logging.INFO):
        engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=[STEPS]), engine=EngineOptions(static_sampler=True))
    assert engine.hand_kernels and not engine.attention_kernels
    assert "Triton kernels (not attention's)" in engine.description
    assert any("attention's softmax: a stand-in failure" in r.getMessage() for r in caplog.records)
    reference, sampler = StaticPi05(engine.policy, fused=False), StaticPi05(engine.policy)
    assert sampler.ops.hand_kernels and not sampler.ops.attention_kernels
    calls = counted_kernel_calls(monkeypatch)
    inputs = sampler_inputs(engine, 2, seed=3, guided=False)
    with torch.no_grad():
        ours, want = sampler.sample(inputs), reference.sample(inputs)
    assert set(calls) == {"gelu_tanh_mul", "add_rms_norm"}
    torch.testing.assert_close(ours, want, atol=1e-5, rtol=0)
