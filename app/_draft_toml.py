"""A commented TOML document for `stairfit init` (app/draft.py).

tomli_w writes no comments, so the drafted scene is written here: tables of `key = value`
lines, each with an optional comment (where the value came from), arrays on one line. A value
init could not know is a `Todo`: written as the string "TODO: what to give" (which every
command refuses, `scene.TODO_PREFIX`), and replaced by a stand-in when init checks that the
rest of the file validates.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .scene import TODO_PREFIX

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


@dataclass(frozen=True)
class Todo:
    """A value init could not know: what the user must give (`text`), and a valid value that
    stands in for it when init checks the rest of the file (`stand_in`)."""

    text: str
    stand_in: object

    def __str__(self) -> str:
        return f"{TODO_PREFIX} {self.text}"


@dataclass(frozen=True)
class Entry:
    """One `key = value` line and its comment ("" for none)."""

    key: str
    value: object
    comment: str = ""


@dataclass(frozen=True)
class Table:
    """A table: its header path ("" for the top level), whether it is one of an array of
    tables (`[[path]]`), its entries, and comment lines written above its header."""

    path: str
    entries: tuple[Entry, ...] = ()
    array: bool = False
    notes: tuple[str, ...] = ()
    children: tuple[Table, ...] = field(default=())


def from_raw(path: str, raw: dict[str, object], array: bool = False) -> Table:
    """A table (and its sub-tables) from a dict as `tomllib` read it: values first, then
    sub-tables (`[path.key]`), then arrays of tables (`[[path.key]]`)."""
    entries, children = [], []
    for key, value in raw.items():
        name = f"{path}.{_key(key)}" if path else _key(key)
        if isinstance(value, dict):
            children.append(from_raw(name, value))
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            children += [from_raw(name, v, array=True) for v in value]
        else:
            entries.append(Entry(key, value))
    return Table(path, tuple(entries), array, (), tuple(children))


def render(tables: Sequence[Table], header: Sequence[str] = ()) -> str:
    """The document: the header comment lines, then every table in order."""
    lines = [f"# {h}".rstrip() for h in header] + ([""] if header else [])
    for t in tables:
        lines += _table_lines(t)
    return "\n".join(lines).rstrip() + "\n"


def _table_lines(t: Table) -> list[str]:
    out = [""] if t.path else []
    out += [line for n in t.notes for line in _comment(n)]
    if t.path:
        out.append(f"[[{t.path}]]" if t.array else f"[{t.path}]")
    for e in t.entries:
        line = f"{_key(e.key)} = {value_text(e.value)}"
        if e.comment and len(line) + len(e.comment) + 4 <= LINE_WIDTH:
            out.append(f"{line}  # {e.comment}")
        else:
            out += [*_comment(f"{e.key}: {e.comment}"), line] if e.comment else [line]
    for child in t.children:
        out += _table_lines(child)
    return out


LINE_WIDTH = 100
"""Comments longer than fit beside their value go above it, wrapped to this width."""


def _comment(text: str) -> list[str]:
    """A comment as lines of at most `LINE_WIDTH` characters."""
    import textwrap

    return [f"# {line}" for line in textwrap.wrap(text, LINE_WIDTH - 2, break_on_hyphens=False)]


def _key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else _string(key)


def _string(s: str) -> str:
    """A TOML basic string (escapes as TOML defines them)."""
    escapes = {
        '"': '\\"',
        "\\": "\\\\",
        "\b": "\\b",
        "\t": "\\t",
        "\n": "\\n",
        "\f": "\\f",
        "\r": "\\r",
    }
    body = "".join(
        escapes.get(c, c if ord(c) >= 0x20 and ord(c) != 0x7F else f"\\u{ord(c):04x}") for c in s
    )
    return f'"{body}"'


def value_text(v: object) -> str:
    """A value as TOML text, on one line."""
    if isinstance(v, Todo):
        return _string(str(v))
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(float(v))
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(value_text(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {value_text(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML form for {type(v).__name__}")


def stand_ins(value: object, todos: dict[str, object]) -> object:
    """`value` (as `tomllib` read the drafted text) with every TODO string replaced by its
    stand-in (`todos`: TODO text -> stand-in)."""
    if isinstance(value, str) and value in todos:
        return todos[value]
    if isinstance(value, dict):
        return {k: stand_ins(v, todos) for k, v in value.items()}
    if isinstance(value, list):
        return [stand_ins(v, todos) for v in value]
    return value


def collect_todos(tables: Sequence[Table]) -> dict[str, object]:
    """Every Todo of the tables (including inside lists): its text -> its stand-in."""
    found: dict[str, object] = {}

    def visit(v: object) -> None:
        if isinstance(v, Todo):
            found[str(v)] = v.stand_in
        elif isinstance(v, list | tuple):
            for x in v:
                visit(x)

    def walk(t: Table) -> None:
        for e in t.entries:
            visit(e.value)
        for c in t.children:
            walk(c)

    for t in tables:
        walk(t)
    return found
