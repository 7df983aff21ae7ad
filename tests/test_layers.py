"""The package's layers: what may import what.

The robot side (``lerobot_armory.robot``) runs on the robot's computer: it must not drag in the
simulator, the schedulers or the server (their dependencies, their import time, their memory).
The mirror and the schedulers are the pure core that the server and the simulator share: they
import neither of them, nor the robot side. And the product package never imports the research
code or the benchmarks, which are not shipped.

Two checks: a static one over the source (every ``import``, including those inside functions,
named by file and line), and a dynamic one that imports the client in a fresh interpreter and
looks at what got loaded (catching what the static check cannot see, e.g. ``importlib`` calls or
an ``__init__`` that pulls in a sibling).
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "lerobot_armory"

ROBOT_MAY_NOT = ("lerobot_armory.sim", "lerobot_armory.schedulers", "lerobot_armory.server", "lerobot_armory.bench", "lerobot_armory.entrypoints.cluster", "ray")
PURE_MAY_NOT = ("lerobot_armory.server", "lerobot_armory.sim", "lerobot_armory.bench", "lerobot_armory.robot", "lerobot_armory.entrypoints.cluster")
# research/ holds the ``armory_research`` package (offline optimum, bounds); benchmarks/ the scripts.
NOBODY_MAY = ("research", "armory_research", "benchmarks")


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """Every module ``path`` imports, anywhere in it, as ``(line, absolute dotted name)``.

    ``from X import Y`` yields ``X.Y`` too: ``from lerobot_armory import sim`` imports the
    subpackage ``lerobot_armory.sim`` without naming it as a module.
    """
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_name(path, root)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module's package
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join([*base, node.module] if node.module else base)
            else:
                module = node.module or ""
            found.append((node.lineno, module))
            found += [(node.lineno, f"{module}.{alias.name}") for alias in node.names if alias.name != "*"]
    return found


def _is_under(module: str, packages: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def _violations(files: list[Path], forbidden: tuple[str, ...], root: Path = ROOT) -> list[str]:
    """``file:line: imports module`` for every import of a module under ``forbidden``."""
    out = []
    for path in files:
        for line, module in _imports(path, root):
            if _is_under(module, forbidden):
                out.append(f"{path.relative_to(root)}:{line}: imports {module}")
    return sorted(set(out))


def _py_files(*paths: Path) -> list[Path]:
    files = []
    for p in paths:
        files += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    return files


def test_the_static_check_sees_imports_inside_functions_and_relative_ones(tmp_path):
    """The checker itself: a nested import and a relative one are both found, with their line."""
    pkg = tmp_path / "lerobot_armory" / "robot"
    pkg.mkdir(parents=True)
    (pkg / "m.py").write_text("import os\n\ndef f():\n    from lerobot_armory.sim.run import simulate\n\nfrom ..server import app\n")
    found = _violations([pkg / "m.py"], ROBOT_MAY_NOT, root=tmp_path)
    assert found == [
        "lerobot_armory/robot/m.py:4: imports lerobot_armory.sim.run",
        "lerobot_armory/robot/m.py:4: imports lerobot_armory.sim.run.simulate",
        "lerobot_armory/robot/m.py:6: imports lerobot_armory.server",
        "lerobot_armory/robot/m.py:6: imports lerobot_armory.entrypoints.server",
    ]


def test_the_robot_side_imports_no_simulator_scheduler_server_or_bench():
    found = _violations(_py_files(PACKAGE / "robot"), ROBOT_MAY_NOT)
    assert not found, "the robot side must stay importable alone:\n" + "\n".join(found)


def test_the_mirror_and_the_schedulers_are_a_pure_layer():
    found = _violations(_py_files(PACKAGE / "mirror.py", PACKAGE / "schedulers", PACKAGE / "placement.py"), PURE_MAY_NOT)
    assert not found, "mirror.py, schedulers/ and placement.py must not depend on server, sim, bench or robot:\n" + "\n".join(found)


def test_policies_are_model_code_below_the_server():
    may_not = ("lerobot_armory.server", "lerobot_armory.sim", "lerobot_armory.schedulers", "lerobot_armory.bench",
               "lerobot_armory.entrypoints.cluster", "lerobot_armory.robot")  # fmt: skip
    found = _violations(_py_files(PACKAGE / "policies"), may_not)
    assert not found, "policies/ (model code: the static sampler, LeRobot variants) must not depend on the server:\n" + "\n".join(found)


def test_the_product_package_imports_no_research_or_benchmark_code():
    found = _violations(_py_files(PACKAGE), NOBODY_MAY)
    assert not found, "lerobot_armory must not import research/ or benchmarks/:\n" + "\n".join(found)


def test_importing_the_client_loads_no_simulator_scheduler_or_server():
    code = (
        "import sys\n"
        "import lerobot_armory.robot.client, lerobot_armory.robot.cli\n"
        f"bad = {ROBOT_MAY_NOT!r}\n"
        "print('\\n'.join(sorted(m for m in sys.modules if any(m == b or m.startswith(b + '.') for b in bad))))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    loaded = done.stdout.split()
    assert not loaded, f"importing the client loaded {loaded}"


@pytest.mark.skipif(shutil.which("lint-imports", path=str(Path(sys.executable).parent)) is None, reason="import-linter not installed")
def test_import_linter_contracts_hold():
    """The same layers as ``[tool.importlinter]`` contracts in pyproject.toml (import-linter also
    follows imports transitively, which the per-file check above does not)."""
    lint = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    done = subprocess.run([lint, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
