"""Types of the JSON documents stairfit writes and reads back (results.json, renders.json, a
study's ledger and table): a record being built, and a JSON value or object as parsed.

A record is built from Python and NumPy values and made JSON by its writer (`report._jsonable`);
a parsed document is whatever `json.loads` returns, whose shape the reader checks or trusts.
"""

from __future__ import annotations

from typing import TypeAlias

Record: TypeAlias = dict[str, object]
"""A JSON object being built: field name -> value (numbers, strings, lists, records, arrays)."""

JSONValue: TypeAlias = "bool | int | float | str | list[JSONValue] | dict[str, JSONValue] | None"
"""Any value `json.loads` returns."""

JSONObject: TypeAlias = "dict[str, JSONValue]"
"""A JSON object as `json.loads` returns it."""
