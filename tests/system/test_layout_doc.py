"""docs/layout.md names every module of the package: a new module without a line there fails."""

from __future__ import annotations

import collections
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_every_module_is_named_in_the_layout():
    layout = (ROOT / "docs" / "layout.md").read_text()
    named = collections.Counter(re.findall(r"[A-Za-z0-9_]+\.py\b", layout))
    modules = collections.Counter(
        p.name
        for p in (ROOT / "lerobot_armory").rglob("*.py")
        if p.name not in ("__init__.py", "__main__.py") and "_pb2" not in p.name  # generated: make proto
    )
    # A name several directories share (three admin.py) must be named once for each of them.
    missing = sorted(f"{name} ({count} modules, named {named[name]} times)" for name, count in modules.items() if named[name] < count)
    assert not missing, f"docs/layout.md does not name: {', '.join(missing)}"
