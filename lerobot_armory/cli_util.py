"""Shared command-line plumbing: draccus parsing and one-line errors instead of tracebacks."""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import draccus

from lerobot_armory.errors import ConfigError

T = TypeVar("T")


def parse_or_exit(config_class: type[T], argv: list[str] | None, prog: str) -> T:
    """Parse ``argv`` (default: ``sys.argv[1:]``) into ``config_class`` with draccus.

    ``--help`` prints draccus' help. Any parse error (unknown option, unknown choice such as
    ``--scheduler.type=nope``, a value of the wrong type) exits 2 with one line naming it.
    """
    args = sys.argv[1:] if argv is None else argv
    # Accept the space-separated form (``--preset libero``) as well as draccus' ``--preset=libero``.
    args = _join_space_separated(args)
    captured = io.StringIO()
    try:
        # argparse prints a usage block before its error; keep only the error line.
        with contextlib.redirect_stderr(captured):
            return draccus.parse(config_class=config_class, args=args, prog=prog)
    except SystemExit as exc:
        if exc.code not in (0, None):
            lines = [ln for ln in captured.getvalue().strip().splitlines() if ln.strip()]
            message = lines[-1] if lines else "invalid arguments"
            prefix = f"{prog}: error: "
            _die(prog, message[len(prefix):] if message.startswith(prefix) else message)
        raise
    except ConfigError as exc:
        _die(prog, str(exc))
    except Exception as exc:  # draccus raises assorted decoding errors; none deserve a traceback
        # A config's own check (__post_init__) raised inside draccus, which wraps it in "Couldn't
        # instantiate class ...": the check's line names the field and what is wrong, so show it.
        cause: BaseException | None = exc
        while cause is not None and not isinstance(cause, ConfigError):
            cause = cause.__cause__ or cause.__context__
        _die(prog, str(cause) if cause is not None else _first_line(exc))
    raise AssertionError("unreachable")


def split_passthrough(argv: list[str] | None, group: str, own: set[str]) -> tuple[list[str], list[str]]:
    """Split ``--<group>.<field>=value`` options whose field is not one of ``own`` off ``argv``.

    LeRobot lets ``--policy.path=DIR`` be followed by any field of that policy's own config
    (``--policy.dtype=bfloat16``); those fields are known only once the policy is found, so they
    pass through draccus untouched and are checked where the policy is loaded. Returns
    ``(remaining args, ["field=value", ...])``.
    """
    args = _join_space_separated(sys.argv[1:] if argv is None else argv)
    keep, passed = [], []
    prefix = f"--{group}."
    for a in args:
        name = a[len(prefix):].partition("=")[0] if a.startswith(prefix) else ""
        if name and name.split(".")[0] not in own:
            passed.append(a[len(prefix):])
        else:
            keep.append(a)
    return keep, passed


def run_or_exit(fn: Callable[[T], Any], cfg: T, prog: str = "lerobot-armory") -> Any:
    """Call ``fn(cfg)``; a :class:`ConfigError` becomes one line on stderr and exit code 2."""
    try:
        return fn(cfg)
    except ConfigError as exc:
        _die(prog, str(exc))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        sys.exit(130)


def _join_space_separated(args: list[str]) -> list[str]:
    out: list[str] = []
    k = 0
    while k < len(args):
        a = args[k]
        if a.startswith("--") and "=" not in a and a not in ("--help", "-h") and k + 1 < len(args) and not args[k + 1].startswith("--"):
            out.append(f"{a}={args[k + 1]}")
            k += 2
        else:
            out.append(a)
            k += 1
    return out


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def _die(prog: str, message: str) -> None:
    print(f"{prog}: error: {message}", file=sys.stderr)
    sys.exit(2)
