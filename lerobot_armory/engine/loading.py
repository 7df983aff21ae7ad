"""Loading a policy the way LeRobot loads ``--policy.path``: its config (with ``--policy.<field>``
overrides), its weights on the device, its pre- and post-processors, and the stand-ins a demo
policy directory carries (tokenizers, CLIP, registered Gemma sizes). The engine
(:class:`~lerobot_armory.engine.policy_engine.PolicyEngine`) loads through :func:`load_policy`;
nothing here runs a batch.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lerobot_armory.engine import policy_kinds
from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.errors import ConfigError
from lerobot_armory.policies.layout import CLIP_DIR, FAST_DIR, TOKENIZER_DIR, VLM_DIR

log = logging.getLogger("lerobot_armory.engine.policy_engine")


def load_policy(path: str, device: str, overrides: Sequence[str] = ()):
    """Load config, policy and processors the way LeRobot loads ``--policy.path``."""
    try:
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.utils.import_utils import register_third_party_plugins
    except ImportError as exc:  # pragma: no cover - lerobot is a hard dependency
        raise ConfigError("policy.path", f"cannot import lerobot: {exc}") from None
    import lerobot_armory.policies  # noqa: F401  (registers armory_planner)

    try:
        register_third_party_plugins()  # lerobot_policy_* packages the user installed
    except Exception as exc:  # a broken plugin must not stop the policies that do work
        log.warning("third-party plugin registration failed: %s", exc)
    local = Path(path)
    if (local.exists() or path.startswith((".", "/"))) and not (local / "config.json").is_file():
        raise ConfigError("policy.path", f"{path}: not a LeRobot policy directory (no config.json)")
    saved = read_local_config(local)
    register_variants(saved, path)
    pre_overrides: dict[str, dict[str, Any]] = {"device_processor": {"device": device}}
    if (local / TOKENIZER_DIR).is_dir():
        pre_overrides["tokenizer_processor"] = {"tokenizer_name": str((local / TOKENIZER_DIR).resolve())}
    try:
        config = parse_config(PreTrainedConfig, path, list(overrides))
        config.device = device
        why = policy_kinds.refusal(config)
        if why is not None:  # before building it: a refusal costs no model construction
            raise ConfigError("policy.path", f"{path}: a {config.type} policy cannot be served batched per robot: {why}")
        # A SmolVLA demo directory carries its stand-in VLM in DIR/vlm; its config.json can only
        # name it by absolute path (LeRobot resolves a relative one against the working
        # directory), so point it there wherever the directory now is, unless the user chose one.
        if (
            getattr(config, "vlm_model_name", None) is not None
            and (local / VLM_DIR / "config.json").is_file()
            and not any(o.removeprefix("--").removeprefix("policy.").startswith("vlm_model_name=") for o in overrides)
        ):
            config.vlm_model_name = str((local / VLM_DIR).resolve())
        point_at_own_clip(config, local, overrides)
        point_at_own_fast(config, local, overrides, pre_overrides)
        policy = from_pretrained(get_policy_class(config.type), path, config, device)
        policy.to(device)
        policy.eval()
        pre, post = make_pre_post_processors(
            config,
            pretrained_path=path,
            preprocessor_overrides=pre_overrides,
            postprocessor_overrides={"device_processor": {"device": "cpu"}},
        )
    except ConfigError:
        raise
    except Exception as exc:  # hub errors, missing files, incompatible configs...
        raise ConfigError("policy.path", f"cannot load policy from {path}: {first_line(exc)}") from None
    if not hasattr(policy, "predict_action_chunk"):
        raise ConfigError("policy.path", f"{path}: {config.type} does not predict action chunks")
    if overrides:
        check_weights_fit(policy, path, overrides)
    return config, policy, pre, post


# Policy types whose construction is known to work with a CUDA device as torch's default device
# (checked on the CPU by constructing them on the meta device): their random initialisation then
# runs on the GPU. π0.5's 4.1 B parameters take minutes to initialise on a CPU before the saved
# weights overwrite them.
INIT_ON_DEVICE = frozenset({"pi05"})


def from_pretrained(policy_class: Any, path: str, config: Any, device: str) -> Any:
    """``policy_class.from_pretrained(path, config=config)``, with the parameters created on the
    CUDA device for :data:`INIT_ON_DEVICE` types; if that fails, once more the usual way (logged)."""
    import torch

    if torch.device(device).type == "cuda" and config.type in INIT_ON_DEVICE:
        try:
            with torch.device(device):
                return policy_class.from_pretrained(path, config=config)
        except Exception as exc:  # a slower start, never a failed one
            log.warning("creating %s's parameters on %s failed (%s): creating them on the CPU", config.type, device, first_line(exc))
    return policy_class.from_pretrained(path, config=config)


def check_weights_fit(policy: Any, path: str, overrides: Sequence[str]) -> None:
    """Refuse an override that changed the architecture under the saved weights.

    Some policies (π0.5) only print a warning when the state dict does not fit and go on with
    random weights; an override such as ``max_action_dim`` or ``image_resolution`` would then be
    served silently untrained. Compares every parameter's shape with the weights file's header.
    """
    try:
        from safetensors import safe_open
        from transformers.utils import cached_file

        weights = cached_file(path, "model.safetensors")
    except Exception:  # no single safetensors file (sharded, or not transformers-style): nothing to compare
        return
    if weights is None:
        return
    with safe_open(weights, "pt") as f:
        saved = {k.removeprefix("model."): tuple(f.get_slice(k).get_shape()) for k in f.keys()}  # noqa: SIM118
    wrong = [
        f"{name} {tuple(t.shape)} vs {saved[key]} saved"
        for name, t in policy.state_dict().items()
        if (key := name.removeprefix("model.")) in saved and tuple(t.shape) != saved[key]
    ]
    if wrong:
        given = " ".join(f"--policy.{o}" for o in overrides)
        raise ConfigError(
            "policy", f"{given} changes the model's shape under the weights in {path} ({len(wrong)} tensors, e.g. {wrong[0]})"
        )


def first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (one line for the user, no traceback)."""
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0]}" if lines else type(exc).__name__


def read_local_config(local: Path) -> dict[str, Any]:
    try:
        data = json.loads((local / "config.json").read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def register_variants(saved: dict[str, Any], path: str) -> None:
    """A π0.5, π0 or π0-FAST directory of ours names a model size LeRobot does not ship: register it first."""
    from lerobot_armory.policies import pi05_variants

    if saved.get("type") in pi05_variants.PATCHED_TYPES and pi05_variants.uses_variant(saved):
        name = {"pi05": "π0.5", "pi0": "π0", "pi0_fast": "π0-FAST"}.get(saved["type"], saved["type"])
        try:
            pi05_variants.register()
        except ImportError as exc:
            raise ConfigError("policy.path", f"{path}: {name} needs LeRobot's pi extra (pip install 'lerobot-armory[pi]'): {exc}") from None


def point_at_own_clip(config: Any, local: Path, overrides: Sequence[str]) -> None:
    """A Multi-Task DiT demo directory carries its stand-in CLIP in DIR/clip, named by absolute
    path in its config.json (as SmolVLA's DIR/vlm): point the image and text encoders there
    wherever the directory now is, unless the user chose them."""
    if not (local / CLIP_DIR / "config.json").is_file():
        return
    chosen = {o.removeprefix("--").removeprefix("policy.").partition("=")[0] for o in overrides}
    for field in ("vision_encoder_name", "text_encoder_name"):
        if isinstance(getattr(config, field, None), str) and field not in chosen:
            setattr(config, field, str((local / CLIP_DIR).resolve()))


def point_at_own_fast(config: Any, local: Path, overrides: Sequence[str], pre_overrides: dict[str, dict[str, Any]]) -> None:
    """A π0-FAST demo directory carries its stand-in FAST tokenizer in DIR/fast and its text
    tokenizer in DIR/tokenizer, both named by absolute path in its config.json: point the config
    and the pre-processor's ``action_tokenizer_processor`` step there wherever the directory now
    is, unless the user chose them. (LeRobot does not save that step's ``paligemma_tokenizer_name``:
    left alone it would load the gated hub tokenizer.)"""
    if not (local / FAST_DIR / "processor_config.json").is_file() or not hasattr(config, "action_tokenizer_name"):
        return
    chosen = {o.removeprefix("--").removeprefix("policy.").partition("=")[0] for o in overrides}
    if "action_tokenizer_name" not in chosen:
        config.action_tokenizer_name = str((local / FAST_DIR).resolve())
    if (local / TOKENIZER_DIR).is_dir() and "text_tokenizer_name" not in chosen:
        config.text_tokenizer_name = str((local / TOKENIZER_DIR).resolve())
    pre_overrides["action_tokenizer_processor"] = {
        "action_tokenizer_name": config.action_tokenizer_name, "paligemma_tokenizer_name": config.text_tokenizer_name,
    }  # fmt: skip


def parse_config(base: Any, path: str, overrides: list[str]) -> Any:
    """``PreTrainedConfig.from_pretrained(path, cli_overrides=...)`` with one clear line for an
    override that names no field of the policy's config or has a bad value."""
    if not overrides:
        return base.from_pretrained(path)
    probe = base.from_pretrained(path)  # the policy type decides which fields exist
    known = {f.name for f in dataclasses.fields(probe)}
    args = []
    for item in overrides:
        name, eq, value = item.removeprefix("--").removeprefix("policy.").partition("=")
        top = name.split(".")[0]
        if not eq or not name:
            raise ConfigError("policy", f"override {item!r} must look like --policy.<field>=<value>")
        if top not in known:
            ours = {f.name for f in dataclasses.fields(PolicyOptions)} - {"overrides"}
            close = difflib.get_close_matches(top, sorted(known | ours), n=3)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ConfigError(f"policy.{name}", f"{probe.type} policies have no field {top!r}{hint}")
        args.append(f"--{name}={value}")
    try:
        return base.from_pretrained(path, cli_overrides=args)
    except SystemExit:  # draccus reports an unparsable value on stderr and exits
        raise ConfigError("policy", f"invalid value in {' '.join(args)} for a {probe.type} policy") from None
    except Exception as exc:  # draccus wraps the config's own check (PI05Config: "Invalid dtype: float16")
        while exc.__cause__ is not None or exc.__context__ is not None:
            exc = exc.__cause__ or exc.__context__
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        where = f"policy.{args[0][2:].partition('=')[0]}" if len(args) == 1 else "policy"
        raise ConfigError(where, f"{' '.join(args)} refused by the {probe.type} config: {first}") from None
