"""Schedulers from other installed packages, found through the entry-point group ``lerobot_armory.schedulers``.

A package declares, in its ``pyproject.toml``::

    [project.entry-points."lerobot_armory.schedulers"]
    lrs = "my_package.lrs"

and loading the entry point imports ``my_package.lrs``, whose ``@SchedulerConfig.register_subclass``
registers the scheduler (see ``examples/custom_scheduler.py``). :class:`SchedulerConfig` loads
the plugins the first time its registry is read (a ``--scheduler.type`` being parsed,
``scheduler_names()``, ``make_scheduler_config()``), so importing the package costs nothing.
"""

from __future__ import annotations

import logging
import threading
from importlib.metadata import entry_points

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "lerobot_armory.schedulers"

_lock = threading.RLock()  # re-entrant: a plugin's module may itself read the registry while it loads
_seen: set[tuple[str, str]] = set()  # (name, value) of every entry point tried, loaded or not
_discovered = False


def load_scheduler_plugins() -> list[str]:
    """Import the module of every ``lerobot_armory.schedulers`` entry point not tried before.

    A plugin that fails to import (or to register) is skipped with one warning naming the entry
    point, its package and the error; the others and the built-in schedulers stay available.

    Returns:
        The entry points this call loaded, as ``name = value``.
    """
    global _discovered
    loaded = []
    with _lock:
        _discovered = True
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            if (ep.name, ep.value) in _seen:
                continue
            _seen.add((ep.name, ep.value))
            try:
                ep.load()
            except Exception as exc:  # noqa: BLE001 - a broken plugin must not take the server or the CLI down
                dist = f" of {ep.dist.name} {ep.dist.version}" if ep.dist is not None else ""
                log.warning(
                    "scheduler plugin %r (entry point '%s = %s'%s in group %s) not loaded: %s: %s",
                    ep.name, ep.name, ep.value, dist, ENTRY_POINT_GROUP, type(exc).__name__, exc,
                )  # fmt: skip
                continue
            loaded.append(f"{ep.name} = {ep.value}")
    return loaded


def discover_once() -> None:
    """:func:`load_scheduler_plugins` the first time it is called in this process, nothing after."""
    if _discovered:
        return
    with _lock:  # a second thread waits for the first one's loading
        if not _discovered:
            load_scheduler_plugins()
