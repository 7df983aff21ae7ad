"""Errors raised for bad configurations and bad inputs.

Every user-facing command turns a :class:`ConfigError` into one line naming the offending
field (never a traceback), so the field name is part of the exception.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """An impossible or unknown configuration value.

    Args:
        field: dotted name of the offending option as the user typed it (``h_min``,
            ``scheduler.type``, ``latency_profile``...).
        message: what is wrong and, where possible, what would be accepted.
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")
