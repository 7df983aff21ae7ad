"""``OpTrace``: kernels counted as a GPU launches them, from a CPU (what ``benchmarks/pi05_ops.py``
and the static sampler's launch test rely on)."""

from __future__ import annotations

import pytest
import torch

from lerobot_armory.acceleration.op_trace import ONE_KERNEL_ON_CUDA, OpTrace


def test_a_copy_hidden_inside_a_composite_op_is_counted_under_no_grad_and_hidden_under_inference_mode():
    """Reshaping a transposed tensor copies it (one kernel on a GPU). Under no_grad the trace sees
    the copy; under inference_mode the composite op arrives whole and hides it — why the counts
    are taken under no_grad."""
    x = torch.randn(2, 5, 3, 4)
    with torch.no_grad(), OpTrace() as seen:
        x.transpose(1, 2).reshape(2, 15, 4)
    with torch.inference_mode(), OpTrace() as hidden:
        x.transpose(1, 2).reshape(2, 15, 4)
    assert seen.launches == 1 and hidden.launches == 0


@pytest.mark.skipif(not ONE_KERNEL_ON_CUDA, reason="this torch build has no fused CUDA rms_norm kernel")
def test_rms_norm_counts_as_the_one_kernel_cuda_runs_and_its_value_is_unchanged():
    x, w = torch.randn(2, 5, 64), torch.randn(64)
    with torch.no_grad(), OpTrace() as trace:
        y = torch.nn.functional.rms_norm(x, (64,), w, 1e-6)
        z = y * 2  # ops after it are counted as usual
    assert dict(trace.launched) == {"aten._fused_rms_norm.default": 1, "aten.mul.Tensor": 1}
    torch.testing.assert_close(z, 2 * x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + 1e-6) * w)


def test_a_tensor_built_from_python_data_is_a_host_sync():
    with torch.no_grad(), OpTrace() as trace:
        torch.tensor([1.0, 2.0]) + 1
    assert dict(trace.host_syncs) == {"aten.lift_fresh.default": 1}
