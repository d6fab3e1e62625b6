"""Issue 17's code-health limits hold (tools/code_health.py), and the check can fail: on a small
tree written here with one of each problem it finds every one and nothing else."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[2] / "tools" / "code_health.py"


@pytest.fixture(scope="module")
def health_tool():
    spec = importlib.util.spec_from_file_location("code_health", TOOL)
    module = importlib.util.module_from_spec(spec)
    sys.modules["code_health"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    yield module
    del sys.modules["code_health"]


def test_the_tree_is_within_issue_17s_limits(health_tool):
    health = health_tool.check()
    assert len(health.functions) > 500  # every package was read (about 900 functions)
    shown = health_tool.report(health)
    assert len(health.over(80)) <= 3, shown
    assert health.over(120) == [], shown
    assert health.private_imports == (), shown
    assert health.shadowing == (), shown
    assert health.problems() == [], shown


def _function(name: str, lines: int) -> str:
    """A function of exactly `lines` lines (def line included)."""
    return f"def {name}():\n" + "    x = 1\n" * (lines - 2) + "    return x\n"


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def _tree(root: Path) -> None:
    """A layout like ours with one of each problem (and allowed imports beside them)."""
    _write(
        root,
        {
            "pyproject.toml": (
                '[tool.setuptools]\npackage-dir = { "stairfit" = "app", '
                '"stairfit.model" = "model", "stairfit.fitting" = "fitting" }\n'
            ),
            "model/__init__.py": "from ._rounded import f as f\n",  # own private: fine
            "model/_rounded.py": _function("f", 121) + _function("g", 81) + _function("h", 80),
            "fitting/__init__.py": "",
            "fitting/a.py": (
                "from stairfit.model._rounded import f\n"  # line 1
                "from stairfit.model import _rounded\n"  # line 2
                "import stairfit.model._rounded\n"  # line 3
                "from stairfit.model import f as g\n"  # public: fine
                "from . import _b\n"  # own private: fine
            ),
            "fitting/_b.py": "class K:\n    def method(self):\n" + "        y = 2\n" * 83,
            "app/__init__.py": "",
            "app/inspect.py": "",  # shadows the stdlib
            "app/_ranges.py": "",
            "app/commands/__init__.py": "",
            "app/commands/fit.py": "from .._ranges import x\nfrom ..model._rounded import f\n",
            "app/commands/_io.py": "",  # private: not reported
        },
    )


def test_the_check_finds_each_planted_problem(health_tool, tmp_path):
    _tree(tmp_path)
    health = health_tool.check(tmp_path)
    over_80 = {(f.qualname, f.lines) for f in health.over(80)}
    assert over_80 == {("f", 121), ("g", 81), ("K.method", 84)}  # h has exactly 80
    assert [(f.qualname, f.lines) for f in health.over(120)] == [("f", 121)]
    found = sorted(
        (f.path.relative_to(tmp_path).as_posix(), f.line) for f in health.private_imports
    )
    assert found == [("app/commands/fit.py", 2), ("fitting/a.py", 1), ("fitting/a.py", 2),
                     ("fitting/a.py", 3)]  # fmt: skip
    assert [f.what for f in health.shadowing] == [
        "module stairfit.inspect shadows the standard library's"
    ]
    assert health.problems() == [  # three over 80 are allowed
        "1 functions over 120 lines (none allowed)",
        "4 private imports across packages",
        "1 module names shadow the standard library",
    ]
    assert health_tool.main(["--root", str(tmp_path)]) == 1


def test_the_soft_limit_counts_functions(health_tool, tmp_path):
    files = {
        "pyproject.toml": '[tool.setuptools]\npackage-dir = { "stairfit" = "app" }\n',
        "app/__init__.py": "",
        "app/a.py": "".join(_function(f"f{k}", 81) for k in range(3)),
    }
    _write(tmp_path, files)
    assert health_tool.check(tmp_path).problems() == []  # 3 over 80 are allowed
    assert health_tool.main(["--root", str(tmp_path)]) == 0
    _write(tmp_path, {"app/b.py": _function("one_more", 81)})
    assert health_tool.check(tmp_path).problems() == ["4 functions over 80 lines (at most 3)"]
