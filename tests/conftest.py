"""Fixtures shared by the server/robot tests: a tiny random ACT and a tiny π0.5, saved as LeRobot policy dirs."""

from __future__ import annotations

import pytest

TINY = dict(chunk_size=10, state_dim=2, cameras="front", image_size=32, dim_model=32, n_encoder_layers=1, seed=0)


@pytest.fixture(scope="session")
def demo_policy_dir(tmp_path_factory):
    """A small random-weight ACT built offline and saved like any LeRobot policy."""
    from lerobot_armory.policies.demo.build import DemoPolicyConfig, make_demo_policy

    out = tmp_path_factory.mktemp("policy") / "tiny-act"
    make_demo_policy(DemoPolicyConfig(output=str(out), **TINY))
    return out


@pytest.fixture(scope="session")
def engine(demo_policy_dir):
    """The tiny ACT loaded through the --policy.path code path, on the CPU."""
    import torch

    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions

    torch.set_num_threads(1)  # tests share 2 cores with the server's threads
    return PolicyEngine(PolicyOptions(str(demo_policy_dir), "cpu"))


@pytest.fixture(scope="session")
def pi05_dir(tmp_path_factory):
    """``lerobot-armory-make-demo-policy --kind=pi05 --size=tiny`` (chunk 10, armory_sim features)."""
    from lerobot_armory.policies.demo.build import main

    out = tmp_path_factory.mktemp("pi05") / "pi05-tiny"
    main(["--kind=pi05", "--size=tiny", f"--output={out}", "--chunk_size=10"])
    return out


@pytest.fixture(scope="session")
def pi0_dir(tmp_path_factory):
    """``lerobot-armory-make-demo-policy --kind=pi0 --size=tiny`` (chunk 10, armory_sim features)."""
    from lerobot_armory.policies.demo.build import main

    out = tmp_path_factory.mktemp("pi0") / "pi0-tiny"
    main(["--kind=pi0", "--size=tiny", f"--output={out}", "--chunk_size=10"])
    return out


@pytest.fixture(scope="session")
def smolvla_dir(tmp_path_factory):
    """``lerobot-armory-make-demo-policy --kind=smolvla`` (chunk 10, armory_sim features)."""
    from lerobot_armory.policies.demo.build import main

    out = tmp_path_factory.mktemp("smolvla") / "smolvla-tiny"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HUB_OFFLINE", "1")
        main(["--kind=smolvla", f"--output={out}", "--chunk_size=10"])
    return out
