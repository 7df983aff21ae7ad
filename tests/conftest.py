"""Fixtures shared by the server/robot tests: a tiny random ACT and a tiny π0.5, saved as LeRobot policy dirs."""

from __future__ import annotations

import collections
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

# Where console scripts and the venv's Python live: a test that starts one of these is a
# ``subprocess`` test (the fast tier leaves those out).
BIN = Path(sys.executable).parent


def pytest_configure(config: pytest.Config) -> None:
    # Under pytest-xdist (``make test``: two workers on two cores) each worker's torch gets one
    # thread: two workers each spinning two OpenMP threads on two cores slow both.
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tiers from what a test uses, and the slowest modules first.

    A test that takes openpi's client environment is an ``openpi`` (and ``subprocess``) test; a
    ``gpu`` test is skipped without a CUDA device. Modules run in order of their ``slow`` tests,
    most first (each module's tests kept together, so its fixtures are made once): under
    pytest-xdist the long tests start early and the run does not end on one of them.
    """
    import torch

    no_gpu = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "openpi_env" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.openpi)
            item.add_marker(pytest.mark.subprocess)
        if item.get_closest_marker("gpu") and not torch.cuda.is_available():
            item.add_marker(no_gpu)
    weight: collections.Counter[str] = collections.Counter()
    for item in items:
        weight[item.nodeid.split("::")[0]] += item.get_closest_marker("slow") is not None
    order = {item: k for k, item in enumerate(items)}
    items.sort(key=lambda item: (-weight[item.nodeid.split("::")[0]], order[item]))


@pytest.fixture(autouse=True)
def _subprocess_marker_is_honest(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A test not marked ``subprocess`` that starts a Python process or a console script fails:
    the fast tier must stay fast and free of them. (Processes a module or session fixture starts
    are that fixture's, not checked here.)"""
    if request.node.get_closest_marker("subprocess") is not None:
        yield
        return
    started: list[str] = []
    real = subprocess.Popen.__init__

    def init(self: subprocess.Popen, args: object, *rest: object, **kwargs: object) -> None:
        argv = [args] if isinstance(args, (str, bytes, os.PathLike)) else list(args)  # type: ignore[call-overload]
        words = os.fsdecode(argv[0]).split() if argv else []
        path = Path(words[0]) if words else Path()
        # torch.compile's inductor starts its compile workers, and checks each C++ kernel it built
        # loads, in whichever test compiles first: the library's processes, not the test's.
        inductor = any(("torch/_inductor" in os.fsdecode(a) or "torchinductor" in os.fsdecode(a)) for a in argv)
        if (path.parent == BIN or path.name.startswith("python")) and not inductor:
            started.append(" ".join(os.fsdecode(a) for a in argv)[:300])
        real(self, args, *rest, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(subprocess.Popen, "__init__", init)
    yield
    assert not started, f"this test started {started}: mark it @pytest.mark.subprocess (tests/conftest.py)"

TINY = dict(chunk_size=10, state_dim=2, cameras="front", image_size=32, dim_model=32, n_encoder_layers=1, seed=0)


@pytest.fixture(scope="session")
def demo_policy_dir(tmp_path_factory):
    """A small random-weight ACT built offline and saved like any LeRobot policy."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

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
    from lerobot_armory.demo.build import main

    out = tmp_path_factory.mktemp("pi05") / "pi05-tiny"
    main(["--kind=pi05", "--size=tiny", f"--output={out}", "--chunk_size=10"])
    return out


@pytest.fixture(scope="session")
def pi0_dir(tmp_path_factory):
    """``lerobot-armory-make-demo-policy --kind=pi0 --size=tiny`` (chunk 10, armory_sim features)."""
    from lerobot_armory.demo.build import main

    out = tmp_path_factory.mktemp("pi0") / "pi0-tiny"
    main(["--kind=pi0", "--size=tiny", f"--output={out}", "--chunk_size=10"])
    return out


@pytest.fixture(scope="session")
def smolvla_dir(tmp_path_factory):
    """``lerobot-armory-make-demo-policy --kind=smolvla`` (chunk 10, armory_sim features)."""
    from lerobot_armory.demo.build import main

    out = tmp_path_factory.mktemp("smolvla") / "smolvla-tiny"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HUB_OFFLINE", "1")
        main(["--kind=smolvla", f"--output={out}", "--chunk_size=10"])
    return out
