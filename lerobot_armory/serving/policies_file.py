"""``--policies=FILE``: several policies served from one device, by name.

A YAML or JSON mapping, name → where to load it from::

    kitchen:                          # robots register with --policy_name=kitchen
      path: /models/pi05_kitchen      # a directory or a hub id, as --policy.path
      overrides: {dtype: bfloat16}    # --policy.<field>=value (a mapping, or a list of "field=value")
      max_batch_size: 4               # its batch cap (default: --max_batch_size)
    sorting:
      path: /models/act_sorting

Every policy is loaded on the server's ``--policy.device`` with the server's ``--engine.*`` and
``--rtc.*``; the schedulers are one type (``--scheduler.*``), each built on its own policy's
``d_infer(b)`` and cap. Every problem with the file is one :class:`ConfigError` line naming it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.serving.config_files import read_config_file

FIELD = "policies"
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
KEYS = ("path", "overrides", "max_batch_size")


@dataclass(frozen=True)
class PolicyEntry:
    """One policy of the file.

    Attributes:
        name: what robots name at registration.
        path: ``--policy.path`` of it.
        overrides: ``--policy.<field>=value`` of it, as ``field=value`` strings.
        max_batch_size: its batch cap (None: the server's ``--max_batch_size``).
    """

    name: str
    path: str
    overrides: tuple[str, ...] = ()
    max_batch_size: int | None = None


def load_policies(path: str) -> list[PolicyEntry]:
    """The policies of a ``--policies`` file, in the file's order (the first is the default
    policy of entrypoints that cannot name one, such as openpi clients)."""
    return policies_from_dict(read_config_file(path, FIELD), path)


def policies_from_dict(data: Any, source: str = "<dict>") -> list[PolicyEntry]:
    """The policies of an already parsed ``--policies`` mapping (see the module docstring)."""
    if not isinstance(data, dict) or not data:
        raise ConfigError(FIELD, f"{source}: expected a mapping of policy name -> {{path, overrides, max_batch_size}}")
    out = []
    for name, entry in data.items():
        where = f"{source}: policy {name!r}"
        if not isinstance(name, str) or not NAME.match(name):
            raise ConfigError(FIELD, f"{where}: a name is 1-64 letters, digits, '_', '.' or '-'")
        if not isinstance(entry, dict):
            raise ConfigError(FIELD, f"{where}: expected a mapping with path (and overrides, max_batch_size)")
        unknown = sorted(map(str, set(entry) - set(KEYS)))
        if unknown:
            raise ConfigError(FIELD, f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(KEYS)})")
        policy_path = entry.get("path")
        if not isinstance(policy_path, str) or not policy_path.strip():
            raise ConfigError(FIELD, f"{where}: path must be a directory or hub id")
        cap = entry.get("max_batch_size")
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, int) or cap < 1):
            raise ConfigError(FIELD, f"{where}: max_batch_size must be an integer >= 1, got {cap!r}")
        out.append(PolicyEntry(name, policy_path, _overrides(entry.get("overrides"), where), cap))
    return out


def _overrides(raw: Any, where: str) -> tuple[str, ...]:
    if raw is None:
        return ()
    if isinstance(raw, dict):
        return tuple(f"{k}={_text(v)}" for k, v in raw.items())
    if isinstance(raw, list) and all(isinstance(o, str) and "=" in o for o in raw):
        return tuple(raw)
    raise ConfigError(FIELD, f"{where}: overrides must be a mapping (dtype: bfloat16) or a list of 'field=value'")


def _text(value: Any) -> str:
    """A YAML value as LeRobot's command line would spell it (true/false, not True/False)."""
    return str(value).lower() if isinstance(value, bool) else str(value)
