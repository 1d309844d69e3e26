"""The package layout's rules, read from the source (``docs/architecture.md``, Layers): no module
imports another module's private (``_name``) helper, the tests included (a test goes through the
public name, or the helper gets one); a test module never imports another test module (what tests
share lives in ``tests/*_support.py`` or ``tests/conftest.py``); and the modules of ``station`` and of
``drivers`` import each other without a circle (every import counts: top-level, in a function, under
TYPE_CHECKING).  And what the daemon's processes load as they start: the rig process no numpy, the
web process none of the identification, the report, the control charts (scipy), matplotlib or the
emulators (each daemon start costs their import otherwise)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules(package: str) -> dict[str, Path]:
    out = {}
    for p in sorted((ROOT / package.replace(".", "/")).rglob("*.py")):
        name = ".".join(p.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = p
    return out


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, imported names) of every import statement in the file."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
    return out


def private_imports(packages: tuple[str, ...]) -> list[str]:
    """``module: from X import _name`` for each private name of station, drivers or tests that a
    module of ``packages`` imports."""
    found = []
    for package in packages:
        for name, path in _modules(package).items():
            for module, names in _imports(path):
                if module.split(".")[0] not in ("station", "drivers", "tests"):
                    continue
                found += [f"{name}: from {module} import {n}" for n in names
                          if n.startswith("_") and not n.startswith("__")]
    return found


def imports_of_test_modules(package: str = "tests") -> list[str]:
    """``module: imports T`` for each test module T (``test_*``) of ``package`` that another module of
    it imports (``from tests.test_x import ...``, ``import tests.test_x``, ``from tests import test_x``)."""
    found = []
    for name, path in _modules(package).items():
        for module, names in _imports(path):
            hit = set()
            for target in (module, *(f"{module}.{n}" for n in names)):
                parts = target.split(".")
                if parts[0] != package:
                    continue
                for i, part in enumerate(parts[1:], start=2):
                    if part.startswith("test_"):
                        hit.add(".".join(parts[:i]))
                        break
            found += [f"{name}: imports {t}" for t in sorted(hit) if t != name]
    return found


def import_cycles(package: str) -> list[list[str]]:
    """Strongly connected components (more than one module) of the package's import graph."""
    mods = _modules(package)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        for module, names in _imports(path):
            for target in (module, *(f"{module}.{n}" for n in names)):
                if target in mods and target != m:
                    graph[m].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


@pytest.mark.slow
def test_no_private_helper_is_imported_across_modules() -> None:
    assert private_imports(("station", "drivers")) == []


@pytest.mark.slow
def test_tests_use_public_names_and_share_through_support_modules() -> None:
    assert private_imports(("tests",)) == []
    assert imports_of_test_modules("tests") == []


@pytest.mark.parametrize("package", ["station", "drivers"])
@pytest.mark.slow
def test_modules_import_each_other_without_a_circle(package: str) -> None:
    assert import_cycles(package) == []


def test_the_rules_see_what_they_forbid(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A private import and a circle written on purpose are found (the checks can fail)."""
    pkg = tmp_path / "station" / "ident"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from station.ident.b import _helper\n")
    (pkg / "b.py").write_text("def f():\n    from station.ident import a\n")
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_x.py").write_text("def test_x():\n    from station.ident.b import _helper\n")
    (tests / "test_y.py").write_text("from tests.test_x import test_x\nfrom tests import test_x as t\n")
    (tests / "y_support.py").write_text("from tests.conftest import station_dict\n")  # allowed
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert private_imports(("station",)) == ["station.ident.a: from station.ident.b import _helper"]
    assert import_cycles("station.ident") == [["station.ident.a", "station.ident.b"]]
    assert private_imports(("tests",)) == ["tests.test_x: from station.ident.b import _helper"]
    assert imports_of_test_modules("tests") == ["tests.test_y: imports tests.test_x"] * 2


# loaded where they are used (a worker, the request's thread, the emulators' process), never at the
# web process's start
NOT_IN_THE_WEB_PROCESS = ("scipy", "numba", "matplotlib", "openpyxl", "drivers.sim.rig", "drivers.rig.synth",
                          "station.ident.identify", "station.report.data", "station.trend.charts")


@pytest.mark.slow  # a process that imports the daemon's API (2 s of CPU)
def test_the_daemons_processes_load_only_what_they_need_at_start() -> None:
    code = ("import sys\n"
            "import station.rigproc.serve\n"  # the rig process
            "print(sorted(m for m in ('numpy', 'scipy', 'h5py', 'fastapi') if m in sys.modules))\n"
            "import drivers.sim.process\n"  # how the web process starts the emulators' process
            "print('numpy' in sys.modules)\n"
            "import station.api, station.commands.serve, station.commands.server, station.rigproc.client\n"
            f"print(sorted(m for m in {NOT_IN_THE_WEB_PROCESS!r} if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split("\n")[:3] == ["[]", "False", "[]"], r.stdout
