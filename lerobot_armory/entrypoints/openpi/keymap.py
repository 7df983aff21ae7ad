"""From an openpi observation dict to the policy's features: which key feeds which feature.

openpi's examples name things their own way (LIBERO: ``observation/image``,
``observation/wrist_image``, ``observation/state``; ALOHA: ``images/cam_high`` (CHW), ``state``;
all: ``prompt``). Nested dicts are flattened with ``/``. Each policy feature takes the first of its
candidate keys present:

- an explicit entry of ``--openpi.keymap=FILE`` (JSON or YAML ``{openpi key: policy feature}``;
  ``task`` as the feature names the prompt's key);
- the feature's own name (``observation.state``) or with ``/`` for ``.`` (``observation/state``);
- ``observation/images/CAM``, ``images/CAM`` for ``observation.images.CAM``; ``observation/state``,
  ``state`` for ``observation.state``;
- LIBERO's ``observation/image`` and ``observation/wrist_image`` for the policy's first and second
  camera, in the policy's order.

Images arrive as uint8 HWC or CHW (transposed here); numeric features of the right shape are cast
to the policy's dtype. Anything else is an error naming the feature, what came and what is needed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.errors import ConfigError
from lerobot_armory.feature_spec import FeatureSpec, WireError

TASK = "task"
TASK_KEYS = ("prompt", "task")
LIBERO_CAMERAS = ("observation/image", "observation/wrist_image")
MAX_TASK_CHARS = 4096


def flatten(obs: Mapping[str, Any], prefix: str = "", depth: int = 0) -> dict[str, Any]:
    """``{"images": {"cam_high": a}}`` -> ``{"images/cam_high": a}``."""
    if depth > 4:
        raise WireError("observation nests deeper than 4 levels")
    flat: dict[str, Any] = {}
    for key, value in obs.items():
        if not isinstance(key, str):
            raise WireError("observation keys must be strings")
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "/", depth + 1))
        else:
            flat[name] = value
    return flat


def _candidates(feature: FeatureSpec, camera_rank: int | None) -> list[str]:
    name = feature.name
    keys = [name, name.replace(".", "/")]
    if name.startswith("observation.images."):
        cam = name.removeprefix("observation.images.")
        keys += [f"observation/images/{cam}", f"images/{cam}"]
        if camera_rank is not None and camera_rank < len(LIBERO_CAMERAS):
            keys.append(LIBERO_CAMERAS[camera_rank])
    if name == "observation.state":
        keys += ["observation/state", "state"]
    return list(dict.fromkeys(keys))


@dataclass
class KeyMap:
    """The candidate openpi keys of every policy feature (first present wins)."""

    features: list[FeatureSpec]
    explicit: dict[str, str] = field(default_factory=dict)  # openpi key -> feature name (or "task")

    def __post_init__(self) -> None:
        known = {f.name for f in self.features} | {TASK}
        unknown = sorted(v for v in self.explicit.values() if v not in known)
        if unknown:
            raise ConfigError("openpi.keymap", f"maps to unknown features {unknown}; the policy's are {sorted(known)}")
        cameras = [f for f in self.features if f.dtype == "uint8" and len(f.shape) == 3]
        self.candidates: dict[str, list[str]] = {}
        for f in self.features:
            rank = cameras.index(f) if f in cameras else None
            mine = [k for k, v in self.explicit.items() if v == f.name]
            self.candidates[f.name] = mine + [k for k in _candidates(f, rank) if k not in mine]
        self.task_keys = [k for k, v in self.explicit.items() if v == TASK] + list(TASK_KEYS)

    @classmethod
    def load(cls, features: list[FeatureSpec], path: str | None) -> KeyMap:
        """The default key map, with ``path``'s entries first (ConfigError for a bad file)."""
        if not path:
            return cls(features)
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ConfigError("openpi.keymap", f"cannot read {path}: {exc}") from None
        try:
            if path.endswith((".yaml", ".yml")):
                import yaml

                data = yaml.safe_load(text)
            else:
                data = json.loads(text)
        except Exception as exc:  # noqa: BLE001 - any parse error is the file's problem, said in one line
            raise ConfigError("openpi.keymap", f"{path} does not parse: {exc}") from None
        if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise ConfigError("openpi.keymap", f"{path} must map openpi keys to policy feature names (strings)")
        return cls(features, dict(data))

    def apply(self, obs: Any) -> tuple[dict[str, np.ndarray], str]:
        """The policy's arrays and the task, from one openpi observation (:class:`WireError` if it does not fit)."""
        if not isinstance(obs, Mapping):
            raise WireError(f"the observation must be a map, got {type(obs).__name__}")
        flat = flatten(obs)
        arrays: dict[str, np.ndarray] = {}
        problems = []
        for f in self.features:
            key = next((k for k in self.candidates[f.name] if k in flat), None)
            if key is None:
                problems.append(f"{f.name} ({f.describe()}): none of the keys {self.candidates[f.name]} was sent")
                continue
            try:
                arrays[f.name] = _fit(flat[key], f, key)
            except WireError as exc:
                problems.append(str(exc))
        if problems:
            sent = ", ".join(sorted(flat))[:300]
            raise WireError("; ".join(problems) + f" (keys sent: {sent}; map others with --openpi.keymap=FILE)")
        task_key = next((k for k in self.task_keys if k in flat), None)
        task = flat[task_key] if task_key is not None else ""
        if not isinstance(task, str) or len(task) > MAX_TASK_CHARS:
            raise WireError(f"{task_key}: the prompt must be a string of at most {MAX_TASK_CHARS} characters")
        return arrays, task


def _fit(value: Any, feature: FeatureSpec, key: str) -> np.ndarray:
    """``value`` as ``feature`` needs it: CHW images transposed, numbers cast; else WireError."""
    if not isinstance(value, np.ndarray):
        raise WireError(f"{key}: expected an array for {feature.name} {feature.describe()}, got {type(value).__name__}")
    shape = tuple(feature.shape)
    if feature.dtype == "uint8" and len(shape) == 3:
        if value.dtype != np.uint8:
            raise WireError(f"{key}: image must be uint8, got {value.dtype}")
        h, w, c = shape
        if value.shape == (c, h, w) and value.shape != shape:
            value = np.ascontiguousarray(value.transpose(1, 2, 0))
        if value.shape != shape:
            raise WireError(f"{key}: image of shape {list(value.shape)}, {feature.name} needs {list(shape)} (HWC) or {[c, h, w]} (CHW)")
        return value
    if value.shape != shape:
        raise WireError(f"{key}: shape {list(value.shape)}, {feature.name} needs {list(shape)}")
    if value.dtype.kind not in "fiub":
        raise WireError(f"{key}: dtype {value.dtype} cannot become {feature.dtype}")
    out = value.astype(feature.dtype, copy=False)
    if out.dtype.kind == "f" and not np.isfinite(out).all():
        raise WireError(f"{key}: contains NaN or inf")
    return out
