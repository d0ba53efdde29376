"""Scenarios as data: the typed, validated description of one multi-drone tracking setup.

A scenario is a YAML file (the paper's Cases 1-3 ship as ``case1``/``case2``/``case3`` in
``dronefl/scenarios/``). :func:`load_scenario` reads one, rejects anything questionable before
any work starts, and returns a frozen :class:`Scenario`. Every error is a
:class:`ScenarioError` whose message is one line naming the file and the field.

The field is worked in parallel east-west *lanes* ``lane_spacing`` m apart (crop rows in
``crop_field``, alleys between tree rows in ``orchard``); lane ``k`` runs along
``y = (k + 1/2) * lane_spacing`` between the two headlands.

Reading is safe for any file: one larger than :data:`MAX_SCENARIO_BYTES` is refused unread,
and YAML anchors and aliases (which a scenario never needs, and which let a few hundred bytes
expand to gigabytes) are refused while the YAML is composed, before anything is built.

Every number must be finite (YAML ``.inf`` and ``.nan`` are refused) and within these bounds
(``[a, b]`` closed, ``(a, b]`` open at ``a``):

==================================  ===========================================  =====
field                               bound                                        unit
==================================  ===========================================  =====
``name``                            1-64 of ``A-Z a-z 0-9 - _ .``, not ``.`` first
``rate_hz``                         [1, 50]                                      Hz
``field.width``, ``field.height``   (0, 327.67] (:data:`MAX_FIELD_SIZE_M`)       m
``field.lane_spacing``              [1, 327.67], at most ``field.height``        m
``field.headland``                  (0, 327.67], 2 x headland < ``field.width``  m
``camera.width_px``, ``height_px``  [16, 8192]                                   px
``camera.detector_px``              [32, 4096]                                   px
``camera.hfov_deg``                 (10, 170)                                    deg
``vehicle.length/width/height``     (0, 20]                                      m
``odometry_noise.position``         [0, 5]                                       m
``odometry_noise.velocity``         [0, 5]                                       m/s
``odometry_noise.attitude``         [0, 0.5]                                     rad
``odometry_noise.rate``             [0, 1]                                       rad/s
``targets[k].start_x``              between the headlands                        m
``targets[k].speed``                (0, 5]                                       m/s
``targets[k].walk_std``             (0, 5]                                       m/s
``targets[k].walk_period``          (0, 3600]                                    s
``targets[k].path_gain``            (0, 1] (at most 1 / dt: no overshoot)        1/s
``drones[k].altitude``              [5, 150], above ``vehicle.height``           m
``drones[k].max_speed``             [0.1, 30]                                    m/s
``drones[k].max_accel``             [0.1, 20]                                    m/s^2
``drones[k].start``                 inside the field                             m
==================================  ===========================================  =====
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic.dataclasses import dataclass

ENVIRONMENTS = ("crop_field", "orchard", "open")
Environment = Literal["crop_field", "orchard", "open"]
MotionModel = Literal["constant_speed", "random_walk"]

# Infinity and NaN are refused in every float field (allow_inf_nan=False).
_STRICT = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

#: Largest field side, m: positions travel as int16 centimetres (:mod:`dronefl.wire`).
MAX_FIELD_SIZE_M = 327.67
#: Largest target or drone id: ids travel as one unsigned byte (:mod:`dronefl.wire`).
MAX_ID = 255
#: Largest scenario file, bytes (the shipped ones are under 2 KB); a larger one is not read.
MAX_SCENARIO_BYTES = 1_000_000
#: Deepest nesting of YAML collections in a scenario file (a scenario needs 4).
MAX_YAML_DEPTH = 16
#: A scenario name: it becomes a folder name (``<cache>/<name>/``, ``<out>/<name>/``), so
#: only ASCII letters, digits, ``-``, ``_`` and ``.`` (never first: no ``.``, ``..`` or hidden
#: folder), 1-64 characters. The dot is allowed for names like ``case1-altitude-29.9m``.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,63}")


class ScenarioError(ValueError):
    """A scenario (or experiment config) file is invalid; the message names file and field."""


@dataclass(config=_STRICT)
class FieldSpec:
    """The farm: ``width`` x ``height`` m (x east, y north), lanes ``lane_spacing`` m apart,
    and a ``headland`` strip of that many m at the west and east ends where vehicles turn."""

    width: Annotated[float, Field(gt=0)] = 160.0
    height: Annotated[float, Field(gt=0)] = 120.0
    lane_spacing: Annotated[float, Field(ge=1, le=MAX_FIELD_SIZE_M)] = 5.0
    headland: Annotated[float, Field(gt=0, le=MAX_FIELD_SIZE_M)] = 20.0

    @property
    def n_lanes(self) -> int:
        """Number of lanes that fit in the field."""
        return int(math.floor(self.height / self.lane_spacing + 1e-9))

    def lane_y(self, lane: int) -> float:
        """North coordinate of lane ``lane``'s centre line, m."""
        return (lane + 0.5) * self.lane_spacing


@dataclass(config=_STRICT)
class CameraSpec:
    """Downward pinhole camera: sensor ``width_px`` x ``height_px`` with ``hfov_deg`` horizontal
    field of view; frames are resized to ``detector_px`` x ``detector_px`` for the detector."""

    width_px: Annotated[int, Field(ge=16, le=8192)] = 1280
    height_px: Annotated[int, Field(ge=16, le=8192)] = 720
    hfov_deg: Annotated[float, Field(gt=10, lt=170)] = 80.0
    detector_px: Annotated[int, Field(ge=32, le=4096)] = 640

    def footprint_half_extent(self, height_above: float) -> tuple[float, float]:
        """Half-width and half-height (m) of the ground footprint seen from ``height_above`` m:
        ``h tan(hfov / 2)`` and that times ``height_px / width_px``."""
        half_width = height_above * math.tan(math.radians(self.hfov_deg) / 2)
        return half_width, half_width * self.height_px / self.width_px


@dataclass(config=_STRICT)
class VehicleSpec:
    """Size of every ground vehicle (a box), m."""

    length: Annotated[float, Field(gt=0, le=20)] = 4.0
    width: Annotated[float, Field(gt=0, le=20)] = 2.0
    height: Annotated[float, Field(gt=0, le=20)] = 1.5


@dataclass(config=_STRICT)
class OdometryNoiseSpec:
    """Standard deviations of the odometry noise: position m, velocity m/s, attitude rad,
    angular rate rad/s."""

    position: Annotated[float, Field(ge=0, le=5)] = 0.05
    velocity: Annotated[float, Field(ge=0, le=5)] = 0.05
    attitude: Annotated[float, Field(ge=0, le=0.5)] = 0.01
    rate: Annotated[float, Field(ge=0, le=1)] = 0.02


@dataclass(config=_STRICT)
class TargetSpec:
    """One ground vehicle.

    It starts on lane ``lane`` at ``start_x`` m heading ``east`` or ``west`` and follows its
    boustrophedon path at ``speed`` m/s: along the lane, a U-turn in the headland onto the lane
    ``lane_shift`` further north, back, and so on, reversing the sweep at the field's edge.
    ``random_walk`` adds a per-axis N(0, ``walk_std``^2) m/s velocity perturbation re-drawn every
    ``walk_period`` s; the driver steers back to the path with gain ``path_gain`` 1/s.
    """

    id: Annotated[int, Field(ge=1)]
    lane: Annotated[int, Field(ge=0)]
    start_x: float
    heading: Literal["east", "west"] = "east"
    motion: MotionModel = "constant_speed"
    speed: Annotated[float, Field(gt=0, le=5)] = 0.5
    lane_shift: Annotated[int, Field(ge=1)] = 6
    walk_std: Annotated[float, Field(gt=0, le=5)] = 1.0
    walk_period: Annotated[float, Field(gt=0, le=3600)] = 1.0
    # At most 1 / dt for the slowest rate (1 Hz): a correction never overshoots the path.
    path_gain: Annotated[float, Field(gt=0, le=1)] = 0.2


@dataclass(config=_STRICT)
class DroneSpec:
    """One drone: flies at fixed ``altitude`` m and watches the target ids in ``targets``.

    Horizontal speed is bounded by ``max_speed`` m/s and acceleration by ``max_accel`` m/s^2.
    ``start`` ``[x, y]`` m defaults to above the centre of the box around its targets' start
    positions.
    """

    id: Annotated[int, Field(ge=1)]
    altitude: Annotated[float, Field(ge=5, le=150)]
    targets: tuple[int, ...]
    max_speed: Annotated[float, Field(ge=0.1, le=30)] = 3.0
    max_accel: Annotated[float, Field(ge=0.1, le=20)] = 2.0
    start: tuple[float, float] | None = None


@dataclass(config=_STRICT)
class Scenario:
    """A complete multi-drone tracking setup (SPEC §2). Drones are listed highest first."""

    name: str
    targets: tuple[TargetSpec, ...]
    drones: tuple[DroneSpec, ...]
    description: str = ""
    environment: Environment = "crop_field"
    rate_hz: Annotated[float, Field(ge=1, le=50)] = 5.0
    field: FieldSpec = FieldSpec()
    camera: CameraSpec = CameraSpec()
    vehicle: VehicleSpec = VehicleSpec()
    odometry_noise: OdometryNoiseSpec = OdometryNoiseSpec()

    @property
    def dt(self) -> float:
        """Simulation step, s."""
        return 1.0 / self.rate_hz

    @property
    def target_ids(self) -> tuple[int, ...]:
        return tuple(t.id for t in self.targets)

    @property
    def drone_ids(self) -> tuple[int, ...]:
        return tuple(d.id for d in self.drones)

    @property
    def content_hash(self) -> str:
        """A fingerprint of everything the scenario says (12 hex digits of a SHA-256 over its
        canonical JSON): equal for equal scenarios, different after any edit, name included."""
        canonical = json.dumps(dataclasses.asdict(self), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()[:12]

    def assignment(self) -> np.ndarray:
        """``(M, N)`` bool: drone ``drone_ids[i]`` watches target ``target_ids[j]``."""
        return np.array([[t in d.targets for t in self.target_ids] for d in self.drones])

    def drone(self, drone_id: int) -> DroneSpec:
        """The drone with id ``drone_id``."""
        for d in self.drones:
            if d.id == drone_id:
                return d
        raise KeyError(f"no drone {drone_id} in scenario {self.name!r}")

    @field_validator("name")
    @classmethod
    def _check_name(cls, name: str) -> str:
        if not NAME_PATTERN.fullmatch(name):
            raise ValueError(
                f"name: {_shown(name)} is not a name of 1-64 ASCII letters, digits, '-', '_' "
                "and '.' (not first)"
            )
        return name

    @model_validator(mode="after")
    def _check_consistency(self) -> Scenario:
        _check_scenario(self)
        return self


def _check_scenario(s: Scenario) -> None:
    """Cross-field checks; each raises ``ValueError('field.path: message')``."""
    if not s.targets:
        raise ValueError("targets: at least one target is required")
    if not s.drones:
        raise ValueError("drones: at least one drone is required")
    _check_unique([t.id for t in s.targets], "targets", "id")
    _check_unique([d.id for d in s.drones], "drones", "id")
    f = s.field
    if 2 * f.headland >= f.width:
        raise ValueError(
            f"field.headland: two headlands of {f.headland} m do not fit a {f.width} m field"
        )
    if f.n_lanes < 1:
        raise ValueError(f"field.lane_spacing: {f.lane_spacing} m leaves no lane in the field")
    for name, size in (("width", f.width), ("height", f.height)):
        if size > MAX_FIELD_SIZE_M:
            raise ValueError(
                f"field.{name}: {size} m is beyond the {MAX_FIELD_SIZE_M} m that a prediction "
                "message carries (positions travel as int16 centimetres)"
            )
    for key, items in (("targets", s.targets), ("drones", s.drones)):
        for k, item in enumerate(items):
            if item.id > MAX_ID:
                raise ValueError(
                    f"{key}[{k}].id: {item.id} does not fit the one-byte id of the wire formats "
                    f"(at most {MAX_ID})"
                )
    target_ids = set(s.target_ids)
    for k, t in enumerate(s.targets):
        if t.lane >= f.n_lanes:
            raise ValueError(
                f"targets[{k}].lane: lane {t.lane} is outside the field (it has {f.n_lanes} lanes)"
            )
        n_worked = len(range(t.lane % t.lane_shift, f.n_lanes, t.lane_shift))
        if n_worked < 2:
            raise ValueError(
                f"targets[{k}].lane_shift: with a shift of {t.lane_shift} lanes the vehicle has "
                "no second lane to turn onto"
            )
        if t.lane_shift * f.lane_spacing / 2 > f.headland - 1.0:
            raise ValueError(
                f"targets[{k}].lane_shift: a U-turn of radius {t.lane_shift * f.lane_spacing / 2}"
                f" m does not fit the {f.headland} m headland"
            )
        if not f.headland <= t.start_x <= f.width - f.headland:
            raise ValueError(
                f"targets[{k}].start_x: {t.start_x} m is not between the headlands "
                f"[{f.headland}, {f.width - f.headland}] m"
            )
    altitudes: dict[float, int] = {}
    for k, d in enumerate(s.drones):
        if d.altitude in altitudes:
            raise ValueError(
                f"drones[{k}].altitude: {d.altitude} m is also drone {altitudes[d.altitude]}'s "
                "altitude; every drone needs its own"
            )
        altitudes[d.altitude] = d.id
        if d.altitude <= s.vehicle.height:
            raise ValueError(f"drones[{k}].altitude: {d.altitude} m is not above the vehicles")
        if not d.targets:
            raise ValueError(f"drones[{k}].targets: a drone must watch at least one target")
        _check_unique(list(d.targets), f"drones[{k}]", "targets", what="target")
        for tid in d.targets:
            if tid not in target_ids:
                raise ValueError(f"drones[{k}].targets: target {tid} is not in targets")
        if d.start is not None and not (0 <= d.start[0] <= f.width and 0 <= d.start[1] <= f.height):
            raise ValueError(f"drones[{k}].start: {list(d.start)} is outside the field")
    _check_footprints(s)
    for k in range(1, len(s.drones)):
        if s.drones[k].altitude > s.drones[k - 1].altitude:
            raise ValueError(
                f"drones[{k}].altitude: drones must be listed highest first "
                f"({s.drones[k].altitude} m after {s.drones[k - 1].altitude} m)"
            )
    watched = {tid for d in s.drones for tid in d.targets}
    for k, t in enumerate(s.targets):
        if t.id not in watched:
            raise ValueError(f"targets[{k}]: target {t.id} is watched by no drone")


def _check_footprints(s: Scenario) -> None:
    """Every drone must be able to hold all its targets in view at once: their start positions
    (vehicle extent included) must fit inside its camera footprint."""
    start = {t.id: (t.start_x, s.field.lane_y(t.lane)) for t in s.targets}
    for k, d in enumerate(s.drones):
        xs = [start[i][0] for i in d.targets]
        ys = [start[i][1] for i in d.targets]
        half_w, half_h = s.camera.footprint_half_extent(d.altitude - s.vehicle.height)
        need_w = max(xs) - min(xs) + s.vehicle.length
        need_h = max(ys) - min(ys) + s.vehicle.length
        if need_w > 2 * half_w or need_h > 2 * half_h:
            raise ValueError(
                f"drones[{k}].targets: its targets start spread over {need_w:.1f} x {need_h:.1f} m"
                f" but its footprint at {d.altitude} m is {2 * half_w:.1f} x {2 * half_h:.1f} m; "
                "no position holds them all in view (fly higher or watch fewer targets)"
            )


def _check_unique(values: list[int], where: str, key: str, what: str = "id") -> None:
    seen: set[int] = set()
    for k, v in enumerate(values):
        if v in seen:
            path = f"{where}[{k}].{key}" if key == "id" else f"{where}.{key}"
            raise ValueError(f"{path}: duplicate {what} {v}")
        seen.add(v)


def builtin_scenarios() -> tuple[str, ...]:
    """Names of the scenarios shipped with the package (``case1``, ``case2``, ``case3``)."""
    folder = resources.files("dronefl") / "scenarios"
    return tuple(sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml")))


def scenario_path(name_or_path: str | Path) -> Path:
    """Resolve a built-in scenario name (``case1``) or a path to a YAML file."""
    text = str(name_or_path)
    if text in builtin_scenarios():
        return Path(str(resources.files("dronefl") / "scenarios" / f"{text}.yaml"))
    path = Path(text)
    if not path.is_file():
        known = ", ".join(builtin_scenarios())
        raise ScenarioError(f"{text}: no such scenario file (built-in scenarios: {known})")
    return path


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario; raises :class:`ScenarioError` naming file and field."""
    path = scenario_path(name_or_path)
    try:
        raw = yaml.load(_read_scenario_text(path), Loader=_ScenarioLoader)
    except _RefusedYaml as exc:
        raise ScenarioError(f"{path}: {exc.problem} (line {exc.problem_mark.line + 1})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ScenarioError(f"{path}: not valid YAML{where}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot read ({exc})") from None
    if not isinstance(raw, dict):
        raise ScenarioError(f"{path}: a scenario must be a mapping of keys to values")
    return parse_scenario(raw, source=str(path))


def _read_scenario_text(path: Path) -> str:
    """The UTF-8 text of ``path``, read only if it has at most :data:`MAX_SCENARIO_BYTES`."""
    with path.open("rb") as file:
        data = file.read(MAX_SCENARIO_BYTES + 1)
    if len(data) > MAX_SCENARIO_BYTES:
        raise ScenarioError(
            f"{path}: larger than the {MAX_SCENARIO_BYTES} bytes a scenario file may have"
        )
    return data.decode("utf-8")


class _RefusedYaml(yaml.MarkedYAMLError):
    """Valid YAML that a scenario file may not use (``problem`` says what, at ``problem_mark``)."""


class _ScenarioLoader(yaml.SafeLoader):
    """``yaml.safe_load``'s loader that refuses anchors, aliases and collections nested deeper
    than :data:`MAX_YAML_DEPTH` while composing, before any Python object is built: an alias
    bomb ("billion laughs") is refused at its first anchor instead of expanding."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node | None:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or event.anchor is not None:
            raise _RefusedYaml(
                problem="YAML anchors and aliases (&, *) are not allowed in a scenario",
                problem_mark=event.start_mark,
            )
        if self._depth >= MAX_YAML_DEPTH:
            raise _RefusedYaml(
                problem=f"YAML nested deeper than {MAX_YAML_DEPTH} levels",
                problem_mark=event.start_mark,
            )
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def parse_scenario(raw: dict, source: str = "<scenario>") -> Scenario:
    """Validate a scenario given as a mapping (the parsed YAML)."""
    try:
        # Round-trip through JSON so that strict validation sees YAML lists as JSON arrays
        # (accepted for tuple fields) while still refusing '5' for a number.
        text = json.dumps(raw)
    except (TypeError, ValueError, RecursionError):
        where = _field_path(_not_plain(raw) or ())
        raise ScenarioError(
            f"{source}: {where}: not a plain number, string, list or mapping"
        ) from None
    try:
        return Scenario.__pydantic_validator__.validate_json(text, strict=True)
    except ValidationError as exc:
        raise ScenarioError(f"{source}: {_first_error(exc)}") from None


_PLAIN = (str, int, float, bool, type(None))


def _not_plain(value: object, loc: tuple[str | int, ...] = ()) -> tuple[str | int, ...] | None:
    """Where in ``value`` (found at ``loc``) the first thing JSON cannot carry is (a value of
    another type, such as a YAML date, a key that is not a plain scalar, or nesting deeper than
    :data:`MAX_YAML_DEPTH`, such as a cycle); ``None`` where there is nothing of the kind."""
    if len(loc) > MAX_YAML_DEPTH:
        return loc
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, _PLAIN):
                return loc
            found = _not_plain(item, (*loc, key if isinstance(key, str) else json.dumps(key)))
            if found is not None:
                return found
        return None
    if isinstance(value, list | tuple):
        for k, item in enumerate(value):
            found = _not_plain(item, (*loc, k))
            if found is not None:
                return found
        return None
    return None if isinstance(value, _PLAIN) else loc


#: A key shown as is in a field path; any other is shown quoted (``drones[0]['a b']``).
_PLAIN_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _field_path(loc: tuple[str | int, ...]) -> str:
    """``('drones', 0, 'altitude')`` -> ``drones[0].altitude`` (``scenario`` for ``()``); keys
    that are not plain words are quoted, so the path stays on one line."""
    parts = [
        f"[{p}]" if isinstance(p, int) else f".{p}" if _PLAIN_KEY.fullmatch(p) else f"[{p!r}]"
        for p in loc
    ]
    return "".join(parts).lstrip(".") or "scenario"


def _shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` (escapes keep it on one line), cut to about ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = _field_path(tuple(err["loc"]))
    msg = err["msg"]
    if err["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
        return f"{loc}: unknown key"
    if err["type"] == "value_error":
        # Our own checks already start with the field path.
        return msg.removeprefix("Value error, ")
    got = err.get("input")
    shown = "" if isinstance(got, dict | list) else f" (got {_shown(got)})"
    return f"{loc}: {msg}{shown}"
