"""Errors raised for bad configurations and bad inputs.

Every user-facing command turns a :class:`ConfigError` into one line naming the offending
field (never a traceback), so the field name is part of the exception.
"""

from __future__ import annotations

from collections.abc import Sequence


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

    @classmethod
    def listing(cls, problems: Sequence[str]) -> ConfigError:
        """One error naming several problems, each a ``field: why`` string (at least one).

        A user fixes a command line or a registration in one go when every problem is named at
        once. ``field`` is the first problem's field; the text reads
        ``field: why; other_field: why; ...``.
        """
        if not problems:
            raise ValueError("ConfigError.listing needs at least one problem")
        field, _, why = problems[0].partition(": ")
        return cls(field, "; ".join([why, *problems[1:]]))
