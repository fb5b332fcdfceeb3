"""TOML text of a generated scene mapping (the scene fuzzers' writer; not a test module).

Writes what `tomllib` reads back as the same mapping: floats by repr ('nan', 'inf', '1e+300'
are TOML floats too), strings with JSON's escapes (which are TOML's), inline tables for tables
inside a section, and `Deep` values nested thousands of arrays deep without recursion.
"""

import json
import re

BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def toml_key(key: str) -> str:
    return key if BARE_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


class Deep:
    """A value nested ``depth`` arrays deep, written out without recursion."""

    def __init__(self, depth):
        self.depth = depth


def toml_value(value) -> str:
    if isinstance(value, Deep):
        return "[" * value.depth + "1.0" + "]" * value.depth
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        # str() refuses beyond 4,300 digits; such a number is written as one of its size
        return str(value) if value.bit_length() < 14_000 else "9" * (int(value.bit_length() * 0.30103) + 1)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(value)


def to_toml(data: dict) -> str:
    """The file of ``data``; a key whose value is None is left out (TOML has no null)."""
    lines = [f"{toml_key(k)} = {toml_value(v)}" for k, v in data.items() if not isinstance(v, dict) and v is not None]
    for section, table in data.items():
        if isinstance(table, dict):
            lines.append(f"[{toml_key(section)}]")
            lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items() if v is not None]
    return "\n".join(lines) + "\n"
