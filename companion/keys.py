"""Declared configuration keys: each TOML key's kind, range, default and doc, checked once.

The scenario files (companion.sim.scenario) and the service configuration (companion.config)
declare their keys with `Key` and a value `Kind`; `read_table` checks a TOML table against the
declarations and every error names the dotted key (`ConfigError`; all of a table's errors at
once as `AggregateConfigError`). `markdown_rows` writes the reference tables from the same
declarations.
"""

from __future__ import annotations

import difflib
import math
import numbers
import tomllib
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from functools import partial
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, ErrorCollector
from companion.sat.linalg import spd_2x2_faults

FloatArray = NDArray[np.float64]
T = TypeVar("T")

# ---------------------------------------------------------------------------------------------
# Value kinds: how a raw TOML value is type-checked, range-checked, described and written back
# ---------------------------------------------------------------------------------------------

_TOML_TYPE_NAMES = ((bool, "boolean"), (int, "integer"), (float, "float"), (str, "string"))


def describe(raw: object) -> str:
    """'<TOML type> <short value>' for an error message."""
    if raw is None:
        return "nothing (None)"
    name = type(raw).__name__
    for py_type, toml_name in _TOML_TYPE_NAMES:
        if isinstance(raw, py_type):
            name = toml_name
            break
    else:
        if isinstance(raw, list | tuple):
            name = "array"
        elif isinstance(raw, Mapping):
            name = "table"
    text = toml_text(raw) if isinstance(raw, bool | str) else repr(raw)
    if len(text) > 40:
        text = text[:37] + "..."
    return f"{name} {text}"


def toml_text(value: object) -> str:
    """A value in TOML syntax (for defaults in the reference and values in messages)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_text(v) for v in value) + "]"
    return repr(value)


def plural(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def array_items(key: str, raw: object, shape_doc: str) -> Sequence[object]:
    """raw as a sequence (a TOML array), else ConfigError naming key."""
    if not isinstance(raw, list | tuple):
        raise ConfigError(key, f"must be an array {shape_doc}, got {describe(raw)}")
    return raw


class Kind(ABC, Generic[T]):
    """How one key's value is parsed and checked (`parse`), described (`doc`), written (`dump`)."""

    doc: str = ""

    @abstractmethod
    def parse(self, key: str, raw: object) -> T:
        """The checked value, or ConfigError(key, ...)."""

    def dump(self, value: T) -> object:
        """The value as plain TOML data (what `parse` accepts back)."""
        return value


class Int(Kind[int]):
    def __init__(self, ge: int | None = None, le: int | None = None) -> None:
        self.ge, self.le = ge, le
        if ge is not None and le is not None:
            self.doc = f"integer in [{ge}, {le}]"
        else:
            self.doc = "integer" if ge is None else f"integer >= {ge}"

    def parse(self, key: str, raw: object) -> int:
        # bool is an int subclass in Python but not an integer in TOML; a float is never an int.
        if isinstance(raw, bool) or not isinstance(raw, numbers.Integral):
            raise ConfigError(key, f"must be an integer, got {describe(raw)}")
        value = int(raw)
        if (self.ge is not None and value < self.ge) or (self.le is not None and value > self.le):
            raise ConfigError(key, f"must be {self.doc.removeprefix('integer ')}, got {value}")
        return value


class Float(Kind[float]):
    def __init__(
        self, gt: float | None = None, ge: float | None = None, le: float | None = None
    ) -> None:
        self.gt, self.ge, self.le = gt, ge, le
        if ge is not None and le is not None:
            self.range = f"in [{ge}, {le}]"
        elif gt is not None and le is not None:
            self.range = f"in ({gt}, {le}]"
        elif gt is not None:
            self.range = f"> {gt}"
        elif ge is not None:
            self.range = f">= {ge}"
        elif le is not None:
            self.range = f"<= {le}"
        else:
            self.range = ""
        self.doc = f"number {self.range}".rstrip()

    def parse(self, key: str, raw: object) -> float:
        if isinstance(raw, bool) or not isinstance(raw, numbers.Real):
            raise ConfigError(key, f"must be a number, got {describe(raw)}")
        try:
            value = float(raw)
        except OverflowError:  # an integer beyond the float range
            value = math.inf
        if not math.isfinite(value):
            raise ConfigError(key, f"must be finite, got {describe(raw)}")
        if (
            (self.gt is not None and not value > self.gt)
            or (self.ge is not None and not value >= self.ge)
            or (self.le is not None and not value <= self.le)
        ):
            raise ConfigError(key, f"must be {self.range}, got {value!r}")
        return value


class Bool(Kind[bool]):
    doc = "boolean"

    def parse(self, key: str, raw: object) -> bool:
        if not isinstance(raw, bool):
            raise ConfigError(key, f"must be true or false, got {describe(raw)}")
        return raw


class Text(Kind[str]):
    doc = "non-empty string"

    def parse(self, key: str, raw: object) -> str:
        if not isinstance(raw, str) or not raw:
            raise ConfigError(key, f"must be a non-empty string, got {describe(raw)}")
        return raw


class PathText(Kind[str]):
    """A file name; the empty string stands for none (the reader makes it None)."""

    doc = "string (empty: none)"

    def parse(self, key: str, raw: object) -> str:
        if not isinstance(raw, str):
            raise ConfigError(key, f"must be a string (a file name, or empty), got "
                                   f"{describe(raw)}")
        return raw


class Choice(Kind[T]):
    """One of a fixed set of options: strings, or members of a str-valued Enum (parsed to them)."""

    def __init__(self, *options: T) -> None:
        self.options = options
        self.texts = [o.value if isinstance(o, Enum) else o for o in options]
        self.doc = "one of " + ", ".join(toml_text(t) for t in self.texts)

    def parse(self, key: str, raw: object) -> T:
        if isinstance(raw, Enum):
            raw = raw.value
        if not isinstance(raw, str) or raw not in self.texts:
            raise ConfigError(key, f"must be {self.doc}, got {describe(raw)}")
        return self.options[self.texts.index(raw)]

    def dump(self, value: T) -> object:
        return value.value if isinstance(value, Enum) else value


class Pair(Kind[tuple[float, float]]):
    def __init__(self, item: Float, ordered: bool = False) -> None:
        self.item, self.ordered = item, ordered
        each = f", each {item.range}" if item.range else ""
        self.doc = f"[number, number]{each}" + (", first <= second" if ordered else "")

    def parse(self, key: str, raw: object) -> tuple[float, float]:
        items = array_items(key, raw, "of 2 numbers")
        if len(items) != 2:
            got = plural(len(items), "item")
            raise ConfigError(key, f"must be an array of 2 numbers, got {got}")
        a = self.item.parse(f"{key}[0]", items[0])
        b = self.item.parse(f"{key}[1]", items[1])
        if self.ordered and a > b:
            raise ConfigError(key, f"must be [lo, hi] with lo <= hi, got {toml_text([a, b])}")
        return (a, b)

    def dump(self, value: tuple[float, float]) -> object:
        return list(value)


class Floats(Kind[tuple[float, ...]]):
    """A fixed-length array of numbers, each position with its own range: [lat, lon, alt]."""

    def __init__(self, shape_doc: str, *items: Float) -> None:
        self.shape_doc, self.items = shape_doc, items
        ranges = [f"{name} {item.range}" for name, item in
                  zip(shape_doc.strip("[]").split(", "), items, strict=True) if item.range]
        self.doc = f"{shape_doc} (numbers" + (f"; {', '.join(ranges)})" if ranges else ")")

    def parse(self, key: str, raw: object) -> tuple[float, ...]:
        n = len(self.items)
        cells = array_items(key, raw, f"of {n} numbers {self.shape_doc}")
        if len(cells) != n:
            got = plural(len(cells), "item")
            raise ConfigError(key, f"must be an array of {n} numbers {self.shape_doc}, got {got}")
        return tuple(item.parse(f"{key}[{i}]", v) for i, (item, v) in
                     enumerate(zip(self.items, cells, strict=True)))

    def dump(self, value: tuple[float, ...]) -> object:
        return list(value)


def frozen_rows(rows: Sequence[Sequence[float]], ncols: int) -> FloatArray:
    """A read-only float array of shape (len(rows), ncols)."""
    out = np.array(rows, dtype=np.float64).reshape(len(rows), ncols)
    out.flags.writeable = False
    return out


class Points(Kind[FloatArray]):
    """An array of [x, y] points, returned as a read-only (n, 2) array."""

    def __init__(self, doc: str = "array of [x, y] (metres)") -> None:
        self.doc = doc

    def parse(self, key: str, raw: object) -> FloatArray:
        pair = Pair(Float())
        items = array_items(key, raw, "of [x, y] points")
        return frozen_rows([pair.parse(f"{key}[{i}]", p) for i, p in enumerate(items)], 2)

    def dump(self, value: FloatArray) -> object:
        return [[float(x), float(y)] for x, y in value]


class Ints(Kind[tuple[int, ...]]):
    """An array of integers, each >= ge."""

    def __init__(self, ge: int = 0) -> None:
        self.item = Int(ge=ge)
        self.doc = f"array of integers >= {ge}"

    def parse(self, key: str, raw: object) -> tuple[int, ...]:
        items = array_items(key, raw, "of integers")
        return tuple(self.item.parse(f"{key}[{i}]", v) for i, v in enumerate(items))

    def dump(self, value: tuple[int, ...]) -> object:
        return list(value)


class Rows(Kind[tuple[tuple[Any, ...], ...]]):
    """An array of fixed-length arrays whose positions have their own kinds ([step, x, y], ...)."""

    def __init__(self, shape_doc: str, *columns: Kind[Any]) -> None:
        self.shape_doc, self.columns = shape_doc, columns
        self.doc = f"array of {shape_doc} (" + "; ".join(c.doc for c in columns) + ")"

    def parse(self, key: str, raw: object) -> tuple[tuple[Any, ...], ...]:
        rows = []
        for i, row in enumerate(array_items(key, raw, f"of {self.shape_doc}")):
            cells = array_items(f"{key}[{i}]", row, self.shape_doc)
            if len(cells) != len(self.columns):
                raise ConfigError(
                    f"{key}[{i}]",
                    f"must be an array {self.shape_doc}, got {plural(len(cells), 'item')}",
                )
            pairs = zip(self.columns, cells, strict=True)
            rows.append(tuple(c.parse(f"{key}[{i}][{j}]", v) for j, (c, v) in enumerate(pairs)))
        return tuple(rows)

    def dump(self, value: tuple[tuple[Any, ...], ...]) -> object:
        return [list(row) for row in value]


class Matrix2(Kind[FloatArray]):
    """A symmetric positive definite 2x2 matrix [[a, b], [b, d]], returned read-only."""

    doc = "[[number, number], [number, number]], symmetric positive definite"

    def parse(self, key: str, raw: object) -> FloatArray:
        rows = array_items(key, raw, "[[a, b], [b, d]]")
        if len(rows) != 2:
            got = plural(len(rows), "row")
            raise ConfigError(key, f"must be a 2x2 array [[a, b], [b, d]], got {got}")
        row0 = Pair(Float()).parse(f"{key}[0]", rows[0])
        row1 = Pair(Float()).parse(f"{key}[1]", rows[1])
        matrix = np.array([row0, row1], dtype=np.float64)
        # Scaled first (definiteness does not depend on scale): any finite entries can be checked.
        asymmetric, indefinite = spd_2x2_faults(matrix / max(float(np.abs(matrix).max()), 1e-300))
        if asymmetric or indefinite:
            raise ConfigError(key, "must be symmetric positive definite")
        return frozen_rows([row0, row1], 2)

    def dump(self, value: FloatArray) -> object:
        return [[float(v) for v in row] for row in value]


class Derived:
    """Marks a default computed from other keys; `doc` says how."""

    def __init__(self, doc: str) -> None:
        self.doc = doc


REQUIRED = Derived("required")


@dataclass(frozen=True, slots=True)
class Key:
    """One key: TOML name (leaf), kind, default, doc; its dataclass field is the leaf by default."""

    leaf: str
    kind: Kind[Any]
    default: object
    doc: str
    field: str = ""  # the dataclass field it fills, when not named as the key (dt -> dt_s)
    project: bool = False  # the project's addition to scenario-format.md
    stored: bool = True  # False: only shapes other fields (camera.hfov_deg), not written back

    def __post_init__(self) -> None:
        if not self.field:
            object.__setattr__(self, "field", self.leaf)


def join_key(prefix: str, leaf: str) -> str:
    return f"{prefix}.{leaf}" if prefix else leaf


def unknown_key(key: str, leaf: str, known: Sequence[str]) -> ConfigError:
    close = difflib.get_close_matches(leaf, known, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return ConfigError(key, f"unknown key ({hint}known: {', '.join(known)})")


def read_table(table: Mapping[Any, Any], prefix: str, keys: Sequence[Key]) -> dict[str, Any]:
    """Field name -> checked value for each declared key (None for a derived default).

    Every bad key of the table is reported: one ConfigError, or AggregateConfigError for several.
    """
    known = [k.leaf for k in keys]
    errors = ErrorCollector()
    for leaf in table:
        if leaf not in known:
            errors.add(unknown_key(join_key(prefix, str(leaf)), str(leaf), known))
    values: dict[str, Any] = {}
    for k in keys:
        key = join_key(prefix, k.leaf)
        if k.leaf in table:
            values[k.field] = errors.attempt(partial(k.kind.parse, key, table[k.leaf]))
        elif k.default is REQUIRED:
            errors.add(ConfigError(key, "is required"))
        elif isinstance(k.default, Derived):
            values[k.field] = None
        else:
            values[k.field] = k.kind.parse(key, k.default)
    errors.raise_any()
    return values


def section_table(data: Mapping[Any, Any], section: str) -> Mapping[Any, Any]:
    table = data.get(section, {})
    if not isinstance(table, Mapping):
        raise ConfigError(section, f"must be a table, got {describe(table)}")
    return table


def dump_table(spec: object, keys: Sequence[Key]) -> dict[str, Any]:
    """The stored keys' values as plain TOML data; a None (a derived default) is left out."""
    return {k.leaf: k.kind.dump(getattr(spec, k.field)) for k in keys
            if k.stored and getattr(spec, k.field) is not None}


def markdown_rows(prefix: str, keys: Sequence[Key]) -> list[str]:
    lines = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for k in keys:
        default = k.default.doc if isinstance(k.default, Derived) else f"`{toml_text(k.default)}`"
        origin = " *(project key)*" if k.project else ""
        cells = (f"`{join_key(prefix, k.leaf)}`", k.kind.doc, default, k.doc + origin)
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return lines


def load_toml(path: str | Path, what: str) -> dict[str, Any]:
    """The TOML data in a file, or ConfigError naming the file and what is wrong with it."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as exc:
        raise ConfigError(str(p), f"no such {what} file") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), f"invalid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(str(p), f"invalid TOML: not UTF-8 text (byte {exc.start})") from exc
    except OSError as exc:
        raise ConfigError(str(p), f"cannot read the file: {exc.strerror or exc}") from exc
