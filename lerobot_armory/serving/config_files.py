"""Reading the operator's YAML or JSON files (grant rules, policies), every problem one line."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lerobot_armory.errors import ConfigError


def read_config_file(path: str, field: str) -> Any:
    """The parsed content of a YAML (``.yaml``/``.yml``) or JSON file.

    Raises:
        ConfigError: under ``field``, if the file cannot be read or does not parse.
    """
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(field, f"cannot read {path}: {exc}") from None
    try:
        if path.endswith((".yaml", ".yml")):
            import yaml

            return yaml.safe_load(text)
        return json.loads(text)
    except Exception as exc:  # yaml.YAMLError / json.JSONDecodeError: one line either way
        first = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError(field, f"{path} does not parse: {first}") from None
