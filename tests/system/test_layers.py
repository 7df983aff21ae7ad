"""The package's layers: what may import what, and no import cycle.

Lowest first: the pure core (mirror, dispatch, schedulers, placement, the delay and latency
models); policies (model code); the engine (a loaded policy, run batched); the serving core (fleet,
sessions, the loop), which speaks its own message types; the entrypoints (gRPC, openpi, cluster),
which translate their wire at their edge. The robot side runs on the robot's computer and drags in
none of the server. The product package never imports the research code, the benchmarks or the
tests, which are not shipped.

:data:`CONTRACTS` is the one table: ``pyproject.toml``'s import-linter contracts must say the same
(checked below), ``lint-imports`` checks them transitively, and a static check over the source
names every offending import by file and line (including imports inside functions); a dynamic
check imports the client in a fresh interpreter and looks at what got loaded.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "lerobot_armory"

# (contract name, source modules, forbidden modules); the same in pyproject.toml.
CONTRACTS: list[tuple[str, tuple[str, ...], tuple[str, ...]]] = [
    (
        "the robot side imports no simulator, scheduler, engine, serving core, entrypoint or bench",
        ("lerobot_armory.robot",),
        ("lerobot_armory.sim", "lerobot_armory.schedulers", "lerobot_armory.engine", "lerobot_armory.serving",
         "lerobot_armory.entrypoints", "lerobot_armory.bench", "ray"),
    ),
    (
        "the core (mirror, dispatch, arbiter, schedulers, placement, delay and latency models) is pure: no engine, serving, wire or I/O layer",
        ("lerobot_armory.mirror", "lerobot_armory.transition", "lerobot_armory.delay", "lerobot_armory.robot_spec", "lerobot_armory.dispatch", "lerobot_armory.arbiter", "lerobot_armory.schedulers", "lerobot_armory.placement",
         "lerobot_armory.network_delay", "lerobot_armory.inference_latency"),
        ("lerobot_armory.engine", "lerobot_armory.serving", "lerobot_armory.entrypoints", "lerobot_armory.sim",
         "lerobot_armory.bench", "lerobot_armory.robot", "lerobot_armory.policies", "lerobot_armory.acceleration",
         "lerobot_armory.demo", "lerobot_armory.proto",
         "lerobot_armory.wire", "torch", "grpc", "google", "websockets"),
    ),
    (
        "policies are model code: no engine, serving core, entrypoint, simulator, scheduler or bench",
        ("lerobot_armory.policies", "lerobot_armory.acceleration", "lerobot_armory.demo"),
        ("lerobot_armory.engine", "lerobot_armory.serving", "lerobot_armory.entrypoints", "lerobot_armory.sim",
         "lerobot_armory.schedulers", "lerobot_armory.bench", "lerobot_armory.robot"),
    ),
    (
        "the engine knows no robots, sessions or wires",
        ("lerobot_armory.engine",),
        ("lerobot_armory.serving", "lerobot_armory.entrypoints", "lerobot_armory.sim", "lerobot_armory.bench",
         "lerobot_armory.robot", "lerobot_armory.schedulers", "lerobot_armory.dispatch", "lerobot_armory.mirror", "lerobot_armory.transition", "lerobot_armory.delay",
         "lerobot_armory.proto", "lerobot_armory.wire", "grpc", "google", "websockets"),
    ),
    (
        "the serving core speaks its own messages: no entrypoint, protobuf, gRPC or websockets",
        ("lerobot_armory.serving",),
        ("lerobot_armory.entrypoints", "lerobot_armory.proto.armory_pb2", "lerobot_armory.proto.armory_pb2_grpc",
         "lerobot_armory.wire", "lerobot_armory.sim", "lerobot_armory.bench", "lerobot_armory.robot", "grpc", "google",
         "websockets"),
    ),
    (
        "the product package imports no research, benchmark or test code",
        ("lerobot_armory",),
        ("research", "armory_research", "benchmarks", "tests"),
    ),
    (
        "the console scripts' mains (lerobot_armory.scripts) are imported by nothing",
        ("lerobot_armory.mirror", "lerobot_armory.transition", "lerobot_armory.delay", "lerobot_armory.robot_spec", "lerobot_armory.dispatch", "lerobot_armory.arbiter", "lerobot_armory.schedulers", "lerobot_armory.placement", "lerobot_armory.policies", "lerobot_armory.acceleration", "lerobot_armory.demo", "lerobot_armory.engine", "lerobot_armory.serving", "lerobot_armory.entrypoints", "lerobot_armory.robot", "lerobot_armory.sim", "lerobot_armory.bench", "lerobot_armory.wire", "lerobot_armory.proto"),
        ("lerobot_armory.scripts",),
    ),
]  # fmt: skip
ROBOT_MAY_NOT = CONTRACTS[0][2]


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


def test_pyproject_holds_the_same_contracts():
    """import-linter's contracts are this table, word for word: neither can drift alone."""
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert [(c["name"], tuple(c["source_modules"]), tuple(c["forbidden_modules"])) for c in declared] == CONTRACTS
    assert all(c["type"] == "forbidden" for c in declared)


@pytest.mark.parametrize("name,sources,forbidden", CONTRACTS, ids=[c[0].split(":")[0][:60] for c in CONTRACTS])
def test_every_file_keeps_its_layer(name, sources, forbidden):
    files = []
    for source in sources:
        path = ROOT / source.replace(".", "/")
        files += _py_files(path) if path.is_dir() else _py_files(path.with_suffix(".py"))
    assert files, f"{sources} match no file"
    found = _violations(files, forbidden)
    assert not found, f"{name}:\n" + "\n".join(found)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in it, functions included)."""
    modules = {_module_name(p, ROOT): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        for _, name in _imports(path):
            while name and name not in modules:  # ``from pkg import name`` names an attribute
                name = name.rpartition(".")[0]
            if name and name != module and not module.startswith(name + "."):  # a package's own __init__ is no cycle
                graph[module].add(name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_of_the_package_imports_itself_back():
    """No import cycle, counting imports inside functions and under TYPE_CHECKING."""
    cycles = _cycles(_import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_static_check_sees_imports_inside_functions_and_relative_ones(tmp_path):
    """The checker itself: a nested import and a relative one are both found, with their line."""
    pkg = tmp_path / "lerobot_armory" / "robot"
    pkg.mkdir(parents=True)
    (pkg / "m.py").write_text("import os\n\ndef f():\n    from lerobot_armory.sim.run import simulate\n\nfrom ..serving import loop\n")
    found = _violations([pkg / "m.py"], ROBOT_MAY_NOT, root=tmp_path)
    assert found == [
        "lerobot_armory/robot/m.py:4: imports lerobot_armory.sim.run",
        "lerobot_armory/robot/m.py:4: imports lerobot_armory.sim.run.simulate",
        "lerobot_armory/robot/m.py:6: imports lerobot_armory.serving",
        "lerobot_armory/robot/m.py:6: imports lerobot_armory.serving.loop",
    ]


@pytest.mark.slow
@pytest.mark.subprocess
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


@pytest.mark.subprocess
@pytest.mark.skipif(shutil.which("lint-imports", path=str(Path(sys.executable).parent)) is None, reason="import-linter not installed")
def test_import_linter_contracts_hold():
    """The same layers as ``[tool.importlinter]`` contracts in pyproject.toml (import-linter also
    follows imports transitively, which the per-file check above does not)."""
    lint = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    done = subprocess.run([lint, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
