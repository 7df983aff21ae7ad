"""``lerobot-armory-make-demo-policy --kind=<type>`` for more of LeRobot's chunking policy types:
diffusion, pi0, pi0_fast, vqbet, multi_task_dit and xvla, each LeRobot's own classes at a tiny
size with random weights, built with no network and loaded back in a fresh process as
``--policy.path`` loads them.

pi0, pi0_fast and xvla load through the engine (``PolicyEngine(PolicyOptions(DIR, "cpu"))``). diffusion,
vqbet and multi_task_dit read an observation history (and vqbet and multi_task_dit read it from
the policy's own queues), which the engine does not feed them yet: they load through LeRobot's own
API (``PreTrainedConfig`` + the policy class's ``from_pretrained`` + ``make_pre_post_processors``),
and the check feeds them a history of ``n_obs_steps`` observations itself.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lerobot_armory.errors import ConfigError

pytest.importorskip("diffusers", reason="diffusion and multi_task_dit need lerobot[diffusion,multi-task-dit]")

# One worker builds and checks every kind (pytest-xdist): the module's fixtures run once.
pytestmark = pytest.mark.xdist_group("demo_kinds")

KINDS = ("diffusion", "pi0", "pi0_fast", "vqbet", "multi_task_dit", "xvla")
CHUNK, STATE, N_OBS = 10, 2, 2
ENGINE_KINDS = ("pi0", "pi0_fast", "xvla")  # served by today's engine (one observation, no queues)

# Run in a fresh interpreter (one for every kind: none was built in it): for each KIND DIR pair of
# its arguments, load DIR as a user would, predict a chunk for a batch of two and print one JSON
# line. Every socket connection is refused (nothing may come from the hub).
_CHECK = r"""
import json, socket, statistics, sys, time
def refuse(*a, **k):
    raise OSError("network access in an offline test")
socket.socket.connect = refuse
socket.create_connection = refuse
import torch
torch.set_num_threads(1)

def check(kind, path):
    out = {}

    def timed(fn, reps=5):
        fn()
        times = []
        for _ in range(reps):
            t = time.perf_counter(); fn(); times.append(time.perf_counter() - t)
        return 1000 * statistics.median(times)

    if kind in ("pi0", "pi0_fast", "xvla"):
        from lerobot_armory.engine.policy_engine import PolicyEngine
        from lerobot_armory.engine.options import PolicyOptions
        engine = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1))
        obs = [engine.example_observation(k) for k in range(2)]
        tasks = ["pick up the red block", "sort the bricks"]
        a = engine.infer(obs, tasks, [1, 2])
        b = engine.infer(obs, tasks, [1, 2])
        c = engine.infer(obs, tasks, [3, 4])
        out.update(type=engine.config.type, policy=type(engine.policy).__name__, shape=list(a.shape),
                   same_noise_equal=bool((a == b).all()), other_noise_differs=bool((a != c).any()),
                   finite=bool(torch.isfinite(torch.as_tensor(a)).all()), rows_nonzero=bool((a != 0).any(axis=(1, 2)).all()),
                   ms_b1=timed(lambda: engine.infer(obs[:1], tasks[:1], [1])))
    else:
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.policies.utils import populate_queues
        config = PreTrainedConfig.from_pretrained(path)
        policy = get_policy_class(config.type).from_pretrained(path, config=config).eval()
        pre, post = make_pre_post_processors(config, pretrained_path=path)
        g = torch.Generator().manual_seed(0)
        def history(b):  # n_obs_steps observations of b robots, oldest first
            steps = []
            for _ in range(config.n_obs_steps):
                o = {k: (torch.rand(b, *f.shape, generator=g) if f.type.name == "VISUAL" else torch.randn(b, *f.shape, generator=g))
                     for k, f in config.input_features.items()}
                o["task"] = ["pick up the red block"] * b
                steps.append(o)
            return steps
        def chunk(steps, **kw):
            with torch.no_grad():
                if kind == "diffusion":  # reads the history from the batch: (B, n_obs_steps, ...)
                    batch = {k: torch.stack([s[k] for s in steps], dim=1) for k in config.input_features}
                    batch["task"] = steps[-1]["task"]
                    return post(policy.predict_action_chunk(pre(batch), **kw))
                policy.reset()  # vqbet, multi_task_dit: read the history from the policy's queues
                for s in steps:
                    p = {k: v for k, v in pre(s).items() if k != "action"}
                    p["observation.images"] = torch.stack([p[k] for k in config.image_features], dim=-4)
                    policy._queues = populate_queues(policy._queues, p)
                return post(policy.predict_action_chunk(dict(p)))
        steps, one = history(2), history(1)
        kw, kw1 = {}, {}
        if kind == "diffusion":
            kw = {"noise": torch.randn(2, config.horizon, config.action_feature.shape[0], generator=g)}
            kw1 = {"noise": kw["noise"][:1]}
        a, b = chunk(steps, **kw), chunk(steps, **kw)
        out.update(type=config.type, policy=type(policy).__name__, shape=list(a.shape),
                   same_noise_equal=bool((a == b).all()), finite=bool(torch.isfinite(a).all()),
                   rows_nonzero=bool((a != 0).any(dim=2).any(dim=1).all()),
                   ms_b1=timed(lambda: chunk(one, **kw1)))
        if kind == "diffusion":
            c = chunk(steps, noise=torch.randn(kw["noise"].shape, generator=g))
            out["other_noise_differs"] = bool((a != c).any())
    return out

for kind, path in zip(sys.argv[1::2], sys.argv[2::2]):
    print(json.dumps({"kind": kind, **check(kind, path)}), flush=True)
"""


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """``build(kind)``: the directory ``lerobot-armory-make-demo-policy --kind=<kind>`` writes
    (chunk 10, 2-D state and action, one camera ``front``: armory_sim's features), built once
    per kind with the hub offline; ``build.seconds[kind]`` is its build time."""
    from lerobot_armory.demo.build import main

    root = tmp_path_factory.mktemp("demo-kinds")
    dirs: dict[str, Path] = {}

    def get(kind: str) -> Path:
        if kind not in dirs:
            out = root / f"{kind}-tiny"
            start = time.perf_counter()
            with pytest.MonkeyPatch.context() as mp:
                mp.setenv("HF_HUB_OFFLINE", "1")
                main([f"--kind={kind}", f"--output={out}", f"--chunk_size={CHUNK}", f"--state_dim={STATE}"])
            get.seconds[kind] = time.perf_counter() - start
            dirs[kind] = out
        return dirs[kind]

    get.seconds = {}
    return get


@pytest.fixture(scope="module")
def fresh(build) -> dict[str, dict]:
    """Every kind built, then loaded back in one fresh process: kind -> what the check printed.
    One process for all kinds (importing torch and LeRobot is most of a check's time)."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    args = [str(a) for kind in KINDS for a in (kind, build(kind))]
    proc = subprocess.run([sys.executable, "-c", _CHECK, *args], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith('{"kind"')]
    return {r["kind"]: r for r in results}


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("kind", KINDS)
def test_kind_builds_offline_and_loads_in_a_fresh_process(kind, build, fresh):
    path = build(kind)
    saved = json.loads((path / "config.json").read_text())
    assert saved["type"] == kind
    assert json.loads((path / "armory.json").read_text())["kind"] == kind
    assert set(saved["input_features"]) == {"observation.state", "observation.images.front"}
    assert saved["output_features"]["action"]["shape"] == [STATE]
    res = fresh[kind]
    print(f"{kind}: built in {build.seconds[kind]:.2f} s, {res['ms_b1']:.1f} ms per chunk at b=1 (fresh process)")
    assert res["type"] == kind
    assert res["shape"] == [2, CHUNK, STATE] and res["finite"] and res["rows_nonzero"]
    if kind in ("diffusion", "pi0"):  # the initial noise fixes the chunk
        assert res["same_noise_equal"] and res["other_noise_differs"]
    if kind == "pi0_fast":  # greedy decoding: no noise, the same chunk every time
        assert res["same_noise_equal"] and not res["other_noise_differs"]


def test_diffusion_is_deterministic_given_the_noise_with_a_horizon_the_unet_takes(build):
    saved = json.loads((build("diffusion") / "config.json").read_text())
    assert saved["noise_scheduler_type"] == "DDIM" and saved["pretrained_backbone_weights"] is None
    assert saved["n_obs_steps"] == N_OBS and saved["n_action_steps"] == CHUNK
    assert saved["horizon"] % 2 ** len(saved["down_dims"]) == 0 and saved["horizon"] >= N_OBS - 1 + CHUNK


def test_pi0_uses_the_registered_tiny_variant_and_the_stand_in_tokenizer(build):
    path = build("pi0")
    saved = json.loads((path / "config.json").read_text())
    assert saved["paligemma_variant"] == saved["action_expert_variant"] == "armory_tiny"
    assert (path / "tokenizer" / "tokenizer.json").is_file()


@pytest.mark.parametrize("kind", ["multi_task_dit", "pi0_fast"])
def test_a_moved_directory_loads_its_own_stand_ins(kind, tmp_path, monkeypatch):
    """Built in one place and moved (the old place gone): the engine's loader points the saved
    absolute names at the directory's own ``clip`` (multi_task_dit's CLIP encoders) or ``fast``
    and ``tokenizer`` (pi0_fast's config and pre-processor steps), as it does SmolVLA's ``vlm``."""
    from lerobot_armory.engine.loading import load_policy
    from lerobot_armory.demo.build import main

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    built, moved = tmp_path / "built", tmp_path / "elsewhere" / "moved"
    main([f"--kind={kind}", f"--output={built}", f"--chunk_size={CHUNK}", f"--state_dim={STATE}"])
    moved.parent.mkdir()
    shutil.move(built, moved)
    config, policy, pre, post = load_policy(str(moved), "cpu")
    assert type(policy).__name__ == {"multi_task_dit": "MultiTaskDiTPolicy", "pi0_fast": "PI0FastPolicy"}[kind]
    if kind == "multi_task_dit":
        assert config.vision_encoder_name == config.text_encoder_name == str((moved / "clip").resolve())
    else:
        assert config.action_tokenizer_name == str((moved / "fast").resolve())
        assert config.text_tokenizer_name == str((moved / "tokenizer").resolve())


def test_multi_task_dit_stand_in_clip_pools_the_prompt(build):
    """The stand-in tokenizer ends each prompt with the id CLIP pools at, so the prompt reaches
    the text features (CLIP's attention is causal: pooling the first token would ignore it)."""
    import torch
    from transformers import AutoTokenizer, CLIPTextModel

    clip = build("multi_task_dit") / "clip"
    tokenizer = AutoTokenizer.from_pretrained(clip)
    model = CLIPTextModel.from_pretrained(clip).eval()
    ids = tokenizer(["pick up the red block", "sort the bricks"], padding="max_length", max_length=16, return_tensors="pt")
    assert (ids["input_ids"] == model.config.eos_token_id).any(dim=1).all()
    with torch.no_grad():
        pooled = model(**ids).pooler_output
    assert not torch.allclose(pooled[0], pooled[1])


def test_options_that_do_not_apply_are_refused(tmp_path):
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    with pytest.raises(ConfigError, match="n_obs_steps"):
        make_demo_policy(DemoPolicyConfig(output=str(tmp_path / "a"), kind="act", n_obs_steps=3))
    with pytest.raises(ConfigError, match="one camera"):
        make_demo_policy(DemoPolicyConfig(output=str(tmp_path / "v"), kind="vqbet", cameras="front,wrist"))
    with pytest.raises(ConfigError, match="size"):
        make_demo_policy(DemoPolicyConfig(output=str(tmp_path / "d"), kind="diffusion", size="full"))
