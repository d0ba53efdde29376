"""Property: any mapping given to ``parse_scenario`` either becomes a Scenario whose every number
is finite and within the bounds documented in :mod:`dronefl.config`, or is refused with one
ScenarioError line that names a field; never any other exception."""

import copy
import dataclasses
import math
import re

import annotated_types
from hypothesis import given, settings
from hypothesis import strategies as st

from dronefl.config import (
    MAX_FIELD_SIZE_M,
    Scenario,
    ScenarioError,
    load_scenario,
    parse_scenario,
)
from dronefl.experiments.simulate import scenario_dict

#: Case 2 with every key spelled out, and one drone with an explicit start.
BASE = scenario_dict(load_scenario("case2"))
BASE["drones"][0]["start"] = [80.0, 60.0]

#: Floats a bound is not checked against statically (they are bounded by other fields).
CROSS_FIELD = {("FieldSpec", "width"), ("FieldSpec", "height"), ("TargetSpec", "start_x")}

Path = tuple[str | int, ...]


def _paths(value: object, path: Path = ()) -> list[Path]:
    """Every key and list item of ``value``, containers included, as a path of keys/indices."""
    inner: list[Path] = []
    if isinstance(value, dict):
        for key, item in value.items():
            inner += _paths(item, (*path, key))
    elif isinstance(value, list):
        for k, item in enumerate(value):
            inner += _paths(item, (*path, k))
    return [path, *inner] if path else inner


PATHS = _paths(BASE)

NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, -1.0, 1e30, 1e308, math.inf, -math.inf, math.nan]),
    st.integers(min_value=-(10**30), max_value=10**30),
)
OTHERS = st.one_of(
    st.text(max_size=70),
    st.none(),
    st.booleans(),
    st.lists(NUMBERS, max_size=4),
    st.dictionaries(st.text(max_size=8), NUMBERS, max_size=3),
)


def _near(value: object) -> st.SearchStrategy:
    """Values close to a valid ``value``: a number scaled by 1/100 to 100, or an edited text."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        return st.nothing()
    if isinstance(value, str):
        return st.builds(lambda a, b: a + value + b, st.text(max_size=3), st.text(max_size=3))
    scaled = st.floats(min_value=0.01, max_value=100).map(lambda f: f * value)
    return scaled.map(round) if isinstance(value, int) else scaled


def _at(raw: dict, path: Path) -> tuple[object, object] | None:
    """``(container, key)`` of ``path`` in ``raw``, or None where an earlier edit removed it."""
    container: object = raw
    for key in path[:-1]:
        try:
            container = container[key]  # type: ignore[index]
        except (KeyError, IndexError, TypeError):
            return None
    last = path[-1]
    if isinstance(container, dict) and last in container:
        return container, last
    if isinstance(container, list) and isinstance(last, int) and last < len(container):
        return container, last
    return None


@st.composite
def scenario_mappings(draw: st.DrawFn) -> dict:
    """Case 2 with up to four edits: a value replaced (near-valid, non-finite, huge, tiny,
    negative, unicode, wrong type), a key removed, or an unknown key added."""
    raw = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(min_value=0, max_value=4))):
        found = _at(raw, draw(st.sampled_from(PATHS)))
        if found is None:
            continue
        container, key = found
        action = draw(st.sampled_from(["replace", "replace", "remove", "add"]))
        if action == "replace":
            original = container[key]  # type: ignore[index]
            container[key] = draw(st.one_of(_near(original), NUMBERS, OTHERS))  # type: ignore[index]
        elif action == "remove" and isinstance(container, dict):
            del container[key]
        elif action == "add" and isinstance(container, dict):
            container[draw(st.text(max_size=8))] = draw(st.one_of(NUMBERS, OTHERS))
    return raw


def _bounds_hold(value: float, metadata: list) -> bool:
    checks = {
        annotated_types.Gt: lambda b: value > b.gt,
        annotated_types.Ge: lambda b: value >= b.ge,
        annotated_types.Lt: lambda b: value < b.lt,
        annotated_types.Le: lambda b: value <= b.le,
    }
    return all(checks[type(b)](b) for b in metadata if type(b) in checks)


def _check_every_number(node: object) -> None:
    """Every float in the tree of dataclasses under ``node`` is finite and within the field's
    declared bounds; every float field declares a lower and an upper bound (or is bounded by
    other fields, :data:`CROSS_FIELD`)."""
    if isinstance(node, tuple):
        for item in node:
            _check_every_number(item)
        return
    if not dataclasses.is_dataclass(node):
        assert not isinstance(node, float) or math.isfinite(node), node
        return
    fields = type(node).__pydantic_fields__
    for name, info in fields.items():
        value = getattr(node, name)
        _check_every_number(value)
        if isinstance(value, float | int) and not isinstance(value, bool):
            assert _bounds_hold(value, info.metadata), (type(node).__name__, name, value)
        if info.annotation is float and (type(node).__name__, name) not in CROSS_FIELD:
            kinds = {type(b) for b in info.metadata}
            assert kinds & {annotated_types.Gt, annotated_types.Ge}, name
            assert kinds & {annotated_types.Lt, annotated_types.Le}, name


def _check_cross_field_bounds(scenario: Scenario) -> None:
    f = scenario.field
    assert 0 < f.width <= MAX_FIELD_SIZE_M and 0 < f.height <= MAX_FIELD_SIZE_M
    assert f.lane_spacing <= f.height and 2 * f.headland < f.width
    for t in scenario.targets:
        assert f.headland <= t.start_x <= f.width - f.headland
    for d in scenario.drones:
        assert d.altitude > scenario.vehicle.height
        if d.start is not None:
            assert 0 <= d.start[0] <= f.width and 0 <= d.start[1] <= f.height


def _names_a_field(message: str, raw: dict) -> bool:
    """``message`` is ``hypothesis: <field path>: ...`` with a path starting at a scenario
    field or at one of ``raw``'s keys (an unknown key), plain or quoted."""
    roots = {f.name for f in dataclasses.fields(Scenario)}
    roots |= {key for key in raw if re.fullmatch(r"[A-Za-z0-9_-]+", key)}
    starts = [*sorted(roots), *(f"[{key!r}]" for key in raw)]
    pattern = "|".join(re.escape(s) for s in starts)
    return re.match(rf"hypothesis: ({pattern})[.\[:]", message) is not None


def test_the_base_mapping_is_a_valid_scenario():
    _check_every_number(parse_scenario(copy.deepcopy(BASE), source="hypothesis"))


@settings(max_examples=200, deadline=None, derandomize=True)
@given(scenario_mappings())
def test_a_mapping_becomes_a_bounded_scenario_or_one_line_naming_a_field(raw):
    # Execute
    try:
        scenario = parse_scenario(copy.deepcopy(raw), source="hypothesis")
    except ScenarioError as exc:
        # Assert: refused in one line that names a field.
        message = str(exc)
        assert "\n" not in message and len(message.splitlines()) == 1, message
        assert _names_a_field(message, raw), message
        return
    # Assert: accepted, so every number is finite and within its bounds.
    _check_every_number(scenario)
    _check_cross_field_bounds(scenario)
