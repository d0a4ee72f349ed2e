"""Every declared configuration key refuses a wrong value with a ConfigError that names it.

The cases are generated from the declarations themselves (`companion.config.SECTIONS` for the
service configuration; `_TOP`, `_SECTIONS` and `_COMPONENT_KEYS` of `companion.sim.scenario` for
scenario files), so a key added later is covered without touching this file. For each key, its
value `Kind` yields wrong-typed values (a string for a number, an array for a string, a table,
a boolean for an integer, NaN and infinities for numbers) and, where the kind has bounds, values
just and far outside them; an array kind also gets a bad element, which must be named by its
index (`search.area[0][1]`). Each is put into a valid configuration (`sitl/service.toml`, or an
explicit-belief scenario) and parsing must raise ConfigError whose key is that key (or one of
its elements) and whose message starts with it. Unknown keys, unknown sections, sections that
are not tables and missing required keys are named too. A hypothesis test then throws random
wrong values at random keys.

tests/test_scenario.py holds the scenario format's hand-written cases with their exact
messages; this file adds the systematic sweep over every declaration.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import SECTIONS, parse_config
from companion.errors import ConfigError
from companion.keys import (
    REQUIRED,
    Bool,
    Choice,
    Float,
    Floats,
    Int,
    Ints,
    Key,
    Kind,
    Matrix2,
    Pair,
    PathText,
    Points,
    Rows,
    Text,
    join_key,
    load_toml,
)
from companion.sim import scenario as sc
from companion.sim import scenario_keys as sk

ROOT = Path(__file__).resolve().parent.parent
SITL_CONFIG = ROOT / "sitl" / "service.toml"

# ---------------------------------------------------------------------------------------------
# Wrong values for each kind of value
# ---------------------------------------------------------------------------------------------

BadValue = tuple[str, object]  # (description for the test id, the raw value)

_TABLE: BadValue = ("table", {"value": 1})
_NOT_NUMBERS: list[BadValue] = [
    ("string", "1"), ("array", [1.0]), _TABLE, ("true", True), ("false", False),
    ("none", None),
]
_NON_FINITE: list[BadValue] = [
    ("nan", math.nan), ("inf", math.inf), ("-inf", -math.inf), ("int 1e400", 10**400),
]


def _below(bound: float) -> list[float]:
    """Numbers just and far below bound."""
    return [math.nextafter(bound, -math.inf), bound - 1.0 - abs(bound)]


def _above(bound: float) -> list[float]:
    """Numbers just and far above bound."""
    return [math.nextafter(bound, math.inf), bound + 1.0 + abs(bound)]


def _float_bad(kind: Float) -> list[BadValue]:
    out = [*_NOT_NUMBERS, *_NON_FINITE]
    if kind.gt is not None:
        out += [("= gt", float(kind.gt))] + [(f"{v!r} <= gt", v) for v in _below(kind.gt)]
    if kind.ge is not None:
        out += [(f"{v!r} < ge", v) for v in _below(kind.ge)]
    if kind.le is not None:
        out += [(f"{v!r} > le", v) for v in _above(kind.le)]
    return out


def _int_bad(kind: Int) -> list[BadValue]:
    out = [("string", "1"), ("array", [1]), _TABLE, ("true", True), ("false", False),
           ("none", None), ("float", 1.0), ("float 2.5", 2.5), ("nan", math.nan),
           ("inf", math.inf)]
    if kind.ge is not None:
        out += [("ge - 1", kind.ge - 1), ("ge - 1000", kind.ge - 1000)]
    if kind.le is not None:
        out += [("le + 1", kind.le + 1), ("le + 1000", kind.le + 1000)]
    return out


def _scalar_bad(kind: Kind[Any]) -> list[BadValue]:
    """Wrong values for a kind whose value is one TOML scalar."""
    if isinstance(kind, Float):
        return _float_bad(kind)
    if isinstance(kind, Int):
        return _int_bad(kind)
    if isinstance(kind, Bool):
        return [("int 1", 1), ("int 0", 0), ("string", "true"), ("array", [True]), _TABLE,
                ("float", 1.0), ("nan", math.nan), ("none", None)]
    if isinstance(kind, Choice):
        first = kind.options[0]
        out: list[BadValue] = [("unknown option", "no-such-option"), ("empty string", ""),
                               ("int", 1), ("true", True), ("array", [first]), _TABLE,
                               ("nan", math.nan), ("none", None)]
        if first.upper() not in kind.options and first.upper() != first:
            out.append(("upper case", first.upper()))
        return out
    if isinstance(kind, Text):
        return [("empty", ""), ("int", 5), ("float", 1.5), ("true", True), ("array", ["x"]),
                _TABLE, ("nan", math.nan), ("none", None)]
    if isinstance(kind, PathText):  # any string names a file (or, empty, none)
        return [("int", 5), ("float", 1.5), ("true", True), ("array", ["x"]), _TABLE,
                ("nan", math.nan), ("none", None)]
    raise AssertionError(f"no wrong values are known for {type(kind).__name__}: teach this file")


def _valid(kind: Kind[Any]) -> object:
    """A value of the kind that parses (the filler around a bad element)."""
    if isinstance(kind, Float):
        if kind.ge is not None:
            return float(kind.ge)
        value = 0.0 if kind.gt is None else float(kind.gt) + 1.0
        return value if kind.le is None else min(value, float(kind.le))
    if isinstance(kind, Int):
        return 0 if kind.ge is None else kind.ge
    if isinstance(kind, Bool):
        return True
    if isinstance(kind, Choice):
        return kind.options[0]
    if isinstance(kind, Text | PathText):
        return "x"
    if isinstance(kind, Pair):
        return [_valid(kind.item)] * 2
    raise AssertionError(f"no valid value is known for {type(kind).__name__}: teach this file")


def _element_bad(items: Sequence[Kind[Any]]) -> Iterator[tuple[str, list[object]]]:
    """Arrays of valid elements with one element replaced by each of its wrong values."""
    filler = [_valid(item) for item in items]
    for i, item in enumerate(items):
        for what, bad in _scalar_bad(item):
            row = list(filler)
            row[i] = bad
            yield f"[{i}] {what}", row


_NOT_AN_ARRAY: list[BadValue] = [("number", 1.0), ("string", "1, 2"), _TABLE, ("true", True),
                                 ("none", None)]


def bad_values(kind: Kind[Any]) -> list[BadValue]:
    """Every wrong value this file knows for a kind; AssertionError for a kind it does not."""
    if isinstance(kind, Pair | Floats):
        items = [kind.item] * 2 if isinstance(kind, Pair) else list(kind.items)
        out = [*_NOT_AN_ARRAY, ("empty", []), ("one too few", [_valid(i) for i in items][:-1]),
               ("one too many", [*(_valid(i) for i in items), _valid(items[0])])]
        out += list(_element_bad(items))
        if isinstance(kind, Pair) and kind.ordered:
            lo, hi = kind.item.ge, kind.item.le
            if lo is not None and hi is not None and lo < hi:
                out.append(("reversed", [hi, lo]))
        return out
    if isinstance(kind, Points):
        return [*_NOT_AN_ARRAY, ("flat", [1.0, 2.0]), ("3 numbers", [[1.0, 2.0, 3.0]]),
                ("one number", [[1.0]]),
                *((f"[0]{what}", [row]) for what, row in _element_bad([Float(), Float()]))]
    if isinstance(kind, Ints):
        return [*_NOT_AN_ARRAY, *((f"[0] {what}", [bad]) for what, bad in _scalar_bad(kind.item))]
    if isinstance(kind, Rows):
        columns = list(kind.columns)
        return [*_NOT_AN_ARRAY, ("flat", [_valid(c) for c in columns]),
                ("short row", [[_valid(c) for c in columns][:-1]]),
                *((f"[0]{what}", [row]) for what, row in _element_bad(columns))]
    if isinstance(kind, Matrix2):
        return [*_NOT_AN_ARRAY, ("1 row", [[1.0, 0.0]]), ("3 rows", [[1.0, 0.0]] * 3),
                ("asymmetric", [[1.0, 0.5], [0.4, 1.0]]), ("indefinite", [[1.0, 2.0], [2.0, 1.0]]),
                ("singular", [[1.0, 1.0], [1.0, 1.0]]), ("negative", [[-1.0, 0.0], [0.0, -1.0]]),
                ("zero", [[0.0, 0.0], [0.0, 0.0]]),
                *((f"[0]{what}", [row, [0.0, 1.0]])
                  for what, row in _element_bad([Float(), Float()]))]
    if isinstance(kind, sk.Components):
        return [*_NOT_AN_ARRAY, ("array of numbers", [1.0]), ("array of strings", ["x"]),
                ("array of arrays", [[1.0, 2.0]])]
    return _scalar_bad(kind)


# ---------------------------------------------------------------------------------------------
# Where the keys live, and valid documents to put the bad values into
# ---------------------------------------------------------------------------------------------

Parse = Callable[[Mapping[str, Any]], object]


def _sitl_config() -> dict[str, Any]:
    return load_toml(SITL_CONFIG, "configuration")


def _parse_config(data: Mapping[str, Any]) -> object:
    return parse_config(data, base=SITL_CONFIG.parent)


# An explicit belief, so that the belief.components[0] keys have a table to live in.
_SCENARIO: dict[str, Any] = {"belief": {"kind": "explicit", "components": [{"mean": [1.0, 1.0]}]}}


def _scenario() -> dict[str, Any]:
    return copy.deepcopy(_SCENARIO)


def _parse_scenario(data: Mapping[str, Any]) -> object:
    return sc.parse_scenario(data, name="fuzz")


def _in_table(data: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The table a dotted prefix names, created when absent ('' is the top level)."""
    table = data
    for part in prefix.split(".") if prefix else []:
        table = table[part[:-3]][0] if part.endswith("[0]") else table.setdefault(part, {})
    return table


# (document name, make a valid document, parse it, [(table prefix, its declared keys)])
DOCUMENTS: list[tuple[str, Callable[[], dict[str, Any]], Parse, list[tuple[str, tuple[Key, ...]]]]]
DOCUMENTS = [
    ("config", _sitl_config, _parse_config, list(SECTIONS.items())),
    ("scenario", _scenario, _parse_scenario,
     [("", sk.TOP_KEYS), *sk.SECTION_KEYS.items(), ("belief.components[0]", sk.COMPONENT_KEYS)]),
]


def _cases() -> Iterator[Any]:
    for doc, make, parse, tables in DOCUMENTS:
        for prefix, keys in tables:
            for key in keys:
                name = join_key(prefix, key.leaf)
                for what, value in bad_values(key.kind):
                    yield pytest.param(make, parse, prefix, key.leaf, value,
                                       id=f"{doc}:{name}={what}")


def _assert_names(err: ConfigError, name: str) -> None:
    """The error is about `name` itself or one of its elements, and says so first."""
    assert err.key == name or err.key.startswith(f"{name}["), str(err)
    assert str(err).startswith(f"{err.key}: ") and err.problem, str(err)


# ---------------------------------------------------------------------------------------------
# The sweep
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("make", "parse"), [(d[1], d[2]) for d in DOCUMENTS],
                         ids=[d[0] for d in DOCUMENTS])
def test_the_valid_documents_parse(make: Callable[[], dict[str, Any]], parse: Parse) -> None:
    parse(make())


def test_every_declared_key_has_wrong_values() -> None:
    """bad_values knows every kind in use (AssertionError here if a new kind appears); every
    key gets wrong types, and a bounded number gets values past each of its bounds."""
    for _, _, _, tables in DOCUMENTS:
        for prefix, keys in tables:
            for key in keys:
                values = [v for _, v in bad_values(key.kind)]
                assert len(values) >= 4, join_key(prefix, key.leaf)
                kind = key.kind
                if isinstance(kind, Float | Int):
                    numbers = [float(v) for v in values if (isinstance(v, float) and
                               math.isfinite(v)) or (isinstance(v, int) and
                                                     not isinstance(v, bool) and abs(v) < 1e300)]
                    for low in (kind.ge, getattr(kind, "gt", None)):
                        assert low is None or min(numbers) < low, join_key(prefix, key.leaf)
                    assert kind.le is None or max(numbers) > kind.le, join_key(prefix, key.leaf)


@pytest.mark.parametrize(("make", "parse", "prefix", "leaf", "value"), list(_cases()))
def test_a_wrong_value_is_refused_naming_its_key(
    make: Callable[[], dict[str, Any]], parse: Parse, prefix: str, leaf: str, value: object
) -> None:
    data = make()
    _in_table(data, prefix)[leaf] = copy.deepcopy(value)
    with pytest.raises(ConfigError) as info:
        parse(data)
    _assert_names(info.value, join_key(prefix, leaf))


def _tables() -> Iterator[Any]:
    for doc, make, parse, tables in DOCUMENTS:
        for prefix, _ in tables:
            yield pytest.param(make, parse, prefix, id=f"{doc}:{prefix or 'top'}")


@pytest.mark.parametrize(("make", "parse", "prefix"), list(_tables()))
def test_an_unknown_key_is_named(
    make: Callable[[], dict[str, Any]], parse: Parse, prefix: str
) -> None:
    data = make()
    _in_table(data, prefix)["no_such_key"] = 1.0
    with pytest.raises(ConfigError) as info:
        parse(data)
    _assert_names(info.value, join_key(prefix, "no_such_key"))
    assert "unknown key" in info.value.problem


def _refused_at(make: Callable[[], dict[str, Any]], parse: Parse, section: str, value: object,
                problem: str) -> None:
    """A document whose `section` is `value` is refused, naming the section and the problem."""
    data = make()
    data[section] = value
    with pytest.raises(ConfigError) as info:
        parse(data)
    assert info.value.key == section and problem in info.value.problem


@pytest.mark.parametrize(("make", "parse"), [(d[1], d[2]) for d in DOCUMENTS],
                         ids=[d[0] for d in DOCUMENTS])
@pytest.mark.parametrize("section", ["no_such_section", "Camera", "filters", "1"])
def test_an_unknown_section_is_named(
    make: Callable[[], dict[str, Any]], parse: Parse, section: str
) -> None:
    _refused_at(make, parse, section, {"x": 1}, "unknown key")


def _sections() -> Iterator[Any]:
    for doc, make, parse, tables in DOCUMENTS:
        for prefix, _ in tables:
            if prefix and "." not in prefix:
                yield pytest.param(make, parse, prefix, id=f"{doc}:{prefix}")


@pytest.mark.parametrize(("make", "parse", "section"), list(_sections()))
@pytest.mark.parametrize("value", [1, "x", [1, 2], True])
def test_a_section_that_is_not_a_table_is_named(
    make: Callable[[], dict[str, Any]], parse: Parse, section: str, value: object
) -> None:
    _refused_at(make, parse, section, value, "must be a table")


def _required() -> Iterator[Any]:
    for doc, make, parse, tables in DOCUMENTS:
        for prefix, keys in tables:
            for key in keys:
                if key.default is REQUIRED:
                    name = join_key(prefix, key.leaf)
                    yield pytest.param(make, parse, prefix, key.leaf, id=f"{doc}:{name}")


@pytest.mark.parametrize(("make", "parse", "prefix", "leaf"), list(_required()))
def test_a_missing_required_key_is_named(
    make: Callable[[], dict[str, Any]], parse: Parse, prefix: str, leaf: str
) -> None:
    data = make()
    _in_table(data, prefix).pop(leaf, None)
    with pytest.raises(ConfigError) as info:
        parse(data)
    assert info.value.key == join_key(prefix, leaf) and info.value.problem == "is required"


def test_documents_that_are_not_tables_are_refused() -> None:
    for _, _, parse, _ in DOCUMENTS:
        for value in ([1, 2], "x", 3, None):
            with pytest.raises(ConfigError):
                parse(value)  # type: ignore[arg-type]


@pytest.mark.parametrize("epsg", [4326, 32600, 32661, 32700, 32761, 0])
def test_a_utm_code_that_is_no_utm_zone_names_search_utm_epsg(epsg: int) -> None:
    """In range for its Int kind but no WGS84 / UTM zone: the service configuration's key is
    search.utm_epsg (the scenario's is geo.utm_epsg)."""
    data = _sitl_config()
    data["search"]["utm_epsg"] = epsg
    with pytest.raises(ConfigError) as info:
        parse_config(data, base=SITL_CONFIG.parent)
    _assert_names(info.value, "search.utm_epsg")
    scenario = _scenario()
    scenario["geo"] = {"utm_epsg": epsg}
    with pytest.raises(ConfigError) as info:
        sc.parse_scenario(scenario)
    _assert_names(info.value, "geo.utm_epsg")


# ---------------------------------------------------------------------------------------------
# Random wrong values at random keys
# ---------------------------------------------------------------------------------------------

_ALL_KEYS = [(doc, prefix, key) for doc, _, _, tables in DOCUMENTS for prefix, keys in tables
             for key in keys]
_BY_DOC = {d[0]: d for d in DOCUMENTS}

_junk = st.recursive(
    st.none() | st.booleans() | st.text(max_size=6) | st.floats(allow_nan=True)
    | st.integers(-(10**30), 10**30),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner,
                                                                 max_size=2),
    max_leaves=6,
)


def _wrong_type(kind: Kind[Any]) -> st.SearchStrategy[object]:
    """Random values no parse of this kind can accept (by their TOML type)."""
    tables = st.dictionaries(st.text(max_size=3), _junk, max_size=2)
    if isinstance(kind, Float):
        return st.text() | st.booleans() | st.none() | tables | st.lists(_junk, max_size=3) \
            | st.sampled_from([math.nan, math.inf, -math.inf])
    if isinstance(kind, Int):
        return st.text() | st.booleans() | st.none() | tables | st.lists(_junk, max_size=3) \
            | st.floats()
    if isinstance(kind, Bool):
        return st.text() | st.none() | tables | st.lists(_junk, max_size=3) | st.floats() \
            | st.integers()
    if isinstance(kind, Choice | Text | PathText):
        return st.booleans() | st.none() | tables | st.lists(_junk, max_size=3) | st.floats() \
            | st.integers()
    # Array kinds: anything that is not an array.
    return st.text() | st.booleans() | st.none() | tables | st.floats() | st.integers()


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.data())
def test_random_wrong_values_are_refused_naming_their_key(data: st.DataObject) -> None:
    doc, prefix, key = data.draw(st.sampled_from(_ALL_KEYS), label="key")
    _, make, parse, _ = _BY_DOC[doc]
    value = data.draw(_wrong_type(key.kind), label="value")
    document = make()
    _in_table(document, prefix)[key.leaf] = value
    with pytest.raises(ConfigError) as info:
        parse(document)
    _assert_names(info.value, join_key(prefix, key.leaf))
