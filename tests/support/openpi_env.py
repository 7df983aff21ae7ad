"""openpi-client's own environment (it pins numpy < 2; lerobot needs numpy >= 2), built once.

Like a robot computer running openpi's client: a separate venv under ``.cache/`` with
``openpi-client==0.1.2`` (plus ``typing_extensions``, which its wheel uses but does not declare,
and ``websockets>=13``: its pin allows versions without the sync client it imports), made from
a Python 3.10-3.12 found on PATH or in pyenv (numpy 1.26 has no wheels for 3.13).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENV = ROOT / ".cache" / "openpi-client-env"
PACKAGES = ["openpi-client==0.1.2", "numpy<2", "websockets>=13", "typing_extensions"]


def _candidates() -> list[str]:
    found = [p for p in (shutil.which(n) for n in ("python3.12", "python3.11", "python3.10")) if p]
    pyenv = shutil.which("pyenv")
    if pyenv:
        root = subprocess.run([pyenv, "root"], capture_output=True, text=True).stdout.strip()
        found += [str(v / "bin" / "python") for v in sorted(Path(root, "versions").glob("3.1[0-2]*"), reverse=True)]
    return found


def _base_python() -> str | None:
    """The first candidate that runs and is 3.10-3.12 (a pyenv shim of a version not selected does not run)."""
    check = "import sys; sys.exit(not (3, 10) <= sys.version_info[:2] <= (3, 12))"
    for candidate in _candidates():
        try:
            if subprocess.run([candidate, "-c", check], capture_output=True, timeout=30).returncode == 0:
                return candidate
        except OSError:
            continue
    return None


def openpi_python() -> str | None:
    """The env's python (built on first use), or None when no Python 3.10-3.12 exists here.
    One builder at a time: pytest-xdist workers that both need it wait on a file lock."""
    import fcntl

    ENV.parent.mkdir(parents=True, exist_ok=True)
    with open(ENV.parent / "openpi-client-env.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return _build()


def _build() -> str | None:
    python = ENV / "bin" / "python"
    if python.exists() and subprocess.run([python, "-c", "import openpi_client, websockets.sync.client"]).returncode == 0:
        return str(python)
    base = _base_python()
    if base is None:
        return None
    shutil.rmtree(ENV, ignore_errors=True)
    subprocess.run([base, "-m", "venv", str(ENV)], check=True)
    subprocess.run([python, "-m", "pip", "install", "--quiet", *PACKAGES], check=True, timeout=600)
    return str(python)
