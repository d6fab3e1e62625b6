"""The layering of the `stairfit` package's own code (app/, issue 43): nothing but the CLI's entry
imports a command module (the pipeline, simulation, explore and the report are libraries that
commands call; the benchmarks and the tests call them too), no command imports another command,
and the app's modules import each other without a cycle; the tests sit in folders that mirror
the packages (issue 43). Read from the source with `ast` (imports inside functions count; those
under `if TYPE_CHECKING:` do not, as they never run); the checks are tried on small planted
trees too, so that they can fail."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
APP = ROOT / "app"
PACKAGE = "stairfit"
COMMANDS = ("predict", "simulate", "init", "fit", "measure", "demo", "study", "render")
"""`stairfit.cli.COMMANDS`, restated so that this test reads the source only."""


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join([PACKAGE, *parts])


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _runtime_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement that can run (not those under `if TYPE_CHECKING:`)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """{module: the package's modules it imports} for every module under `root` (app/), its
    own packages left out."""
    paths = sorted(root.rglob("*.py"))
    modules = {_module_name(root, p): p for p in paths}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in _runtime_imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                bases = [alias.name for alias in node.names]
                targets.update(bases)
                continue
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            targets.add(base)
            targets.update(f"{base}.{alias.name}" for alias in node.names)
        # a module's own packages are imported before it anyway (`from . import x`)
        graph[name] = {t for t in targets if t in modules and not f"{name}.".startswith(f"{t}.")}
    return graph


def command_importers(graph: dict[str, set[str]]) -> list[str]:
    """The modules outside `stairfit.commands` that import one of its modules, but the CLI."""
    inside = f"{PACKAGE}.commands"
    return sorted(
        name
        for name, targets in graph.items()
        if name != f"{PACKAGE}.cli"
        and name != inside
        and not name.startswith(f"{inside}.")
        and any(t == inside or t.startswith(f"{inside}.") for t in targets)
    )


def command_to_command(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(command, command) pairs where one command module imports another (their shared
    helpers sit in private modules beside them)."""
    names = {f"{PACKAGE}.commands.{c}" for c in COMMANDS}
    return sorted((a, b) for a in names & graph.keys() for b in graph[a] & names)


def script_command_imports(folder: Path) -> list[str]:
    """Files under `folder` (the benchmarks) that import `stairfit.commands` or a module of
    it: they call the libraries, never a command."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        for node in _runtime_imports(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            if any(n == f"{PACKAGE}.commands" or n.startswith(f"{PACKAGE}.commands.")
                   for n in names):  # fmt: skip
                found.append(path.relative_to(folder).as_posix())
                break
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return sorted(found)


def test_only_the_cli_imports_a_command_module() -> None:
    assert command_importers(import_graph(APP)) == []


def test_no_command_imports_another() -> None:
    from stairfit import cli

    assert cli.COMMANDS == COMMANDS
    assert command_to_command(import_graph(APP)) == []


def test_the_benchmarks_call_libraries_not_commands() -> None:
    assert script_command_imports(ROOT / "benchmarks") == []


def test_the_tests_call_libraries_not_commands() -> None:
    """A test calls the libraries, or runs the command line as a user does (`stairfit.cli`,
    the console script in a subprocess); it never imports a command module."""
    assert script_command_imports(ROOT / "tests") == []


TEST_FOLDERS = ("model", "fitting", "imaging", "app", "validation", "repository")
"""tests/: one folder per package (`app`: the `stairfit` package), `validation` for data made
another way and `repository` for the repository as a whole (docs/testing.md)."""
NAMED_TESTS = {
    "fitting/_identify.py": "fitting/test_identify.py",
    "fitting/_chain.py": "fitting/test_chain.py",
    "imaging/_hdr.py": "imaging/test_hdr.py",
    "imaging/_blockvar.py": "imaging/test_blockvar.py",
    "imaging/_markers.py": "imaging/test_markers.py",
    "app/outputs.py": "app/test_outputs.py",
}
"""Modules issue 43 found without a test named for them, and the test file now named for each."""


def test_the_tests_sit_in_folders_that_mirror_the_packages() -> None:
    tests = ROOT / "tests"
    files = sorted(tests.rglob("test_*.py"))
    assert sorted(p.name for p in tests.glob("test_*.py")) == []  # none left at the top
    assert {p.parent.relative_to(tests).as_posix() for p in files} <= set(TEST_FOLDERS)
    names = [p.name for p in files]  # no __init__.py: pytest needs the names unique
    assert sorted(n for n in set(names) if names.count(n) > 1) == []


def test_each_module_has_a_test_named_for_it() -> None:
    for module, test in NAMED_TESTS.items():
        assert (ROOT / module).is_file(), module
        assert (ROOT / "tests" / test).is_file(), f"{module}: no {test}"


def test_the_app_modules_import_each_other_without_a_cycle() -> None:
    assert cycles(import_graph(APP)) == []


def test_the_checks_find_planted_problems(tmp_path: Path) -> None:
    files = {
        "__init__.py": "",
        "cli.py": "from .commands import fit\n",  # the entry: allowed
        "pipeline.py": "from . import report\n",
        "report.py": "def f():\n    from .pipeline import g\n",  # a cycle through a function
        "outcome.py": (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .report import R\n"
        ),
        "explore.py": "import stairfit.commands.fit\n",  # upward: reported
        "commands/__init__.py": "",
        "commands/fit.py": "from .. import pipeline\nfrom . import _helper\n",
        "commands/_helper.py": "from ..outcome import x\n",
        "commands/demo.py": "from .fit import run\n",  # a command importing a command
        "bench/a.py": "from stairfit.commands import fit\n",
        "bench/b.py": "import stairfit.commands.demo as d\n",
        "bench/c.py": "from stairfit import pipeline\n",
    }
    for rel, text in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    graph = import_graph(tmp_path)
    assert graph["stairfit.outcome"] == set()  # the TYPE_CHECKING import does not run
    assert command_importers(graph) == ["stairfit.bench.a", "stairfit.bench.b", "stairfit.explore"]
    assert command_to_command(graph) == [("stairfit.commands.demo", "stairfit.commands.fit")]
    assert script_command_imports(tmp_path / "bench") == ["a.py", "b.py"]
    assert cycles(graph) == [["stairfit.pipeline", "stairfit.report"]]
