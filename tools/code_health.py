"""Code-health check of issue 17: long functions, private imports across packages, module names
that shadow the standard library. Reads the source with `ast` (nothing is imported or run).

The packages and their folders come from pyproject.toml's `[tool.setuptools] package-dir`
(`stairfit` = app/, `stairfit.model` = model/, ...); a module's name follows its path
(app/commands/fit.py is `stairfit.commands.fit`). Checked:

* functions (and methods, and nested functions) longer than `SOFT_LINES` and `HARD_LINES`,
  counted from the `def` line to the last line of the body (decorators excluded), docstring
  and comments included;
* imports of a private module or name (`_x`) of another package: `stairfit.model._rounded`,
  `from stairfit.model import _rounded`, a relative `from .._x import y` that leaves the
  package. The packages are `stairfit.model`, `stairfit.fitting`, `stairfit.imaging` and
  `stairfit` itself (app/, with its subpackage `stairfit.commands`), so app/commands/fit.py may
  import app/_ranges.py;
* public modules and subpackages named like a standard-library module (`inspect`, `types`,
  `io`, ...), which shadow it when their folder is on `sys.path` (a script run from app/) and
  mislead a reader (`from stairfit import inspect`). Private names (`_io`) are left alone: the
  standard library's own `_x` modules are implementation details nobody imports by name.

The limits of issue 17's "Done when" are `MAX_OVER_SOFT` functions over `SOFT_LINES` lines and
none over `HARD_LINES`, no private import across packages and no shadowing name; the exit status
is 1 when any is exceeded (tests/repository/test_code_health.py asserts the same).

    python tools/code_health.py            # the report; exit status 1 on a violation
"""

from __future__ import annotations

import argparse
import ast
import sys
import tomllib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOFT_LINES = 80
"""A function longer than this many lines is counted (issue 17: at most `MAX_OVER_SOFT`)."""
HARD_LINES = 120
"""No function may be longer than this many lines."""
MAX_OVER_SOFT = 3
"""How many functions may exceed `SOFT_LINES` (issue 17's Done when)."""
TOP_PACKAGES = ("stairfit.model", "stairfit.fitting", "stairfit.imaging")
"""Packages whose private modules are theirs alone; everything else of `stairfit` is one."""


@dataclass(frozen=True)
class Module:
    """A source file: its dotted name, whether it is a package's `__init__`, its path."""

    name: str
    path: Path
    is_package: bool

    @property
    def package(self) -> str:
        """The package a relative import starts from."""
        return self.name if self.is_package else self.name.rpartition(".")[0]


@dataclass(frozen=True)
class Finding:
    """One thing found: where (`path:line`) and what."""

    path: Path
    line: int
    what: str

    def show(self, root: Path) -> str:
        """`app/x.py:12: what` relative to `root` when inside it."""
        path = self.path.relative_to(root) if self.path.is_relative_to(root) else self.path
        return f"{path}:{self.line}: {self.what}"


@dataclass(frozen=True)
class FunctionLength:
    """A function's qualified name, where it starts and how many lines it has."""

    path: Path
    line: int
    qualname: str
    lines: int


# --- modules --------------------------------------------------------------------------------


def package_dirs(root: Path) -> dict[str, Path]:
    """`{package: folder}` from pyproject.toml's `[tool.setuptools] package-dir`."""
    with open(root / "pyproject.toml", "rb") as fh:
        config = tomllib.load(fh)
    mapping = config["tool"]["setuptools"]["package-dir"]
    return {name: root / folder for name, folder in mapping.items()}


def iter_modules(dirs: dict[str, Path]) -> Iterator[Module]:
    """Every .py file under the package folders, named by its path; a folder that is another
    package's own (e.g. model/ inside a top-level layout) belongs to that package only."""
    owned = set(dirs.values())
    for package, folder in dirs.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder)
            if any(folder / p in owned for p in rel.parents if p != Path(".")):
                continue
            parts = [package, *rel.with_suffix("").parts]
            is_package = parts[-1] == "__init__"
            yield Module(".".join(parts[:-1] if is_package else parts), path, is_package)


def top_package(name: str) -> str:
    """The package a module belongs to for the private-import rule (`TOP_PACKAGES` or the
    rest of `stairfit`); a name outside stairfit is its own first component."""
    for top in TOP_PACKAGES:
        if name == top or name.startswith(top + "."):
            return top
    return "stairfit" if name.split(".")[0] == "stairfit" else name.split(".")[0]


def _is_private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


# --- long functions -------------------------------------------------------------------------


def function_lengths(module: Module, tree: ast.Module) -> list[FunctionLength]:
    """Every function of a module with its length (def line to last line)."""
    out: list[FunctionLength] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                n = (child.end_lineno or child.lineno) - child.lineno + 1
                out.append(FunctionLength(module.path, child.lineno, name, n))
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(tree, "")
    return out


# --- imports --------------------------------------------------------------------------------


def _absolute(module: Module, node: ast.ImportFrom) -> str:
    """The absolute module of `from ... import` (relative levels resolved)."""
    if node.level == 0:
        return node.module or ""
    base = module.package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def imported_names(module: Module, tree: ast.Module) -> Iterator[tuple[int, str]]:
    """`(line, dotted name)` of everything a module imports; `from a import b` gives `a.b`."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(module, node)
            for alias in node.names:
                yield node.lineno, source if alias.name == "*" else f"{source}.{alias.name}"


def private_imports(module: Module, tree: ast.Module) -> list[Finding]:
    """Imports of another package's private module or name."""
    own = top_package(module.name)
    found = []
    for line, name in imported_names(module, tree):
        top = top_package(name)
        if top == own or top.split(".")[0] != "stairfit":
            continue
        rest = name[len(top) :].lstrip(".").split(".") if name != top else []
        private = [p for p in rest if _is_private(p)]
        if private:
            found.append(Finding(module.path, line, f"imports {name} ({private[0]} is private)"))
    return found


# --- names ----------------------------------------------------------------------------------


def shadowing_names(modules: Sequence[Module]) -> list[Finding]:
    """Public modules and subpackages whose own name is a standard-library module's."""
    stdlib = sys.stdlib_module_names
    found = []
    for m in modules:
        leaf = m.name.rpartition(".")[2]
        if leaf in stdlib and "." in m.name and not _is_private(leaf):
            kind = "package" if m.is_package else "module"
            found.append(Finding(m.path, 1, f"{kind} {m.name} shadows the standard library's"))
    return found


# --- the check ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Health:
    """Everything found in one tree."""

    functions: tuple[FunctionLength, ...]
    private_imports: tuple[Finding, ...]
    shadowing: tuple[Finding, ...]

    def over(self, lines: int) -> list[FunctionLength]:
        """Functions longer than `lines`, longest first."""
        return sorted((f for f in self.functions if f.lines > lines), key=lambda f: -f.lines)

    def problems(self) -> list[str]:
        """What exceeds issue 17's limits (empty when healthy)."""
        out = []
        soft, hard = self.over(SOFT_LINES), self.over(HARD_LINES)
        if len(soft) > MAX_OVER_SOFT:
            out.append(f"{len(soft)} functions over {SOFT_LINES} lines (at most {MAX_OVER_SOFT})")
        if hard:
            out.append(f"{len(hard)} functions over {HARD_LINES} lines (none allowed)")
        if self.private_imports:
            out.append(f"{len(self.private_imports)} private imports across packages")
        if self.shadowing:
            out.append(f"{len(self.shadowing)} module names shadow the standard library")
        return out


def check(root: Path = ROOT, dirs: dict[str, Path] | None = None) -> Health:
    """Parse every module of the packages under `root` (pyproject's layout, or `dirs`)."""
    modules = list(iter_modules(package_dirs(root) if dirs is None else dirs))
    functions: list[FunctionLength] = []
    imports: list[Finding] = []
    for m in modules:
        tree = ast.parse(m.path.read_text(encoding="utf-8"), filename=str(m.path))
        functions += function_lengths(m, tree)
        imports += private_imports(m, tree)
    return Health(tuple(functions), tuple(imports), tuple(shadowing_names(modules)))


def report(health: Health, root: Path = ROOT) -> str:
    """The findings as text, one line each."""
    limits = f"at most {MAX_OVER_SOFT}, none over {HARD_LINES}"
    lines = [f"functions over {SOFT_LINES} lines ({limits}):"]
    for f in health.over(SOFT_LINES):
        where = Finding(f.path, f.line, "").show(root)
        lines.append(f"  {where} {f.qualname}: {f.lines} lines")
    lines.append("private imports across packages:")
    lines += [f"  {f.show(root)}" for f in health.private_imports] or ["  none"]
    lines.append("module names that shadow the standard library:")
    lines += [f"  {f.show(root)}" for f in health.shadowing] or ["  none"]
    problems = health.problems()
    lines.append("FAILED: " + "; ".join(problems) if problems else "OK: within issue 17's limits")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Print the report; exit status 1 when a limit is exceeded."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="repository root")
    args = parser.parse_args(argv)
    health = check(args.root)
    print(report(health, args.root))
    return 1 if health.problems() else 0


if __name__ == "__main__":
    sys.exit(main())
