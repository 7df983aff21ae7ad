"""Fixtures shared by the server/robot tests: a tiny random ACT saved as a LeRobot policy dir."""

from __future__ import annotations

import pytest

TINY = dict(chunk_size=10, state_dim=2, cameras="front", image_size=32, dim_model=32, n_encoder_layers=1, seed=0)


@pytest.fixture(scope="session")
def demo_policy_dir(tmp_path_factory):
    """A small random-weight ACT built offline and saved like any LeRobot policy."""
    from lerobot_armory.server.demo_policy import DemoPolicyConfig, make_demo_policy

    out = tmp_path_factory.mktemp("policy") / "tiny-act"
    make_demo_policy(DemoPolicyConfig(output=str(out), **TINY))
    return out


@pytest.fixture(scope="session")
def engine(demo_policy_dir):
    """The tiny ACT loaded through the --policy.path code path, on the CPU."""
    import torch

    from lerobot_armory.server.engine import PolicyEngine, PolicyOptions

    torch.set_num_threads(1)  # tests share 2 cores with the server's threads
    return PolicyEngine(PolicyOptions(str(demo_policy_dir), "cpu"))
