"""One typed, frozen :class:`Setting`: every knob of DroneFL's method, loaded from a TOML file.

A setting is what a study varies; an experiment is what it measures (scenario, method, seeds,
duration). The setting is made of one sub-config per role that reads it:

* :class:`ModelSetting` (``[model]``): the trajectory transformer's options (``dronefl.models``);
* :class:`TrainingSetting` (``[training]``): how a model trains in a round, offline or online
  (``dronefl.fl``);
* :class:`PretrainingSetting` (``[pretraining]``): the crop-field pretraining the closed
  loop's models start from (``dronefl.experiments.pretrain``);
* :class:`LearningSetting` (``[learning]``): the closed loop's online rounds and their
  pseudo-labels (``dronefl.learners``, ``dronefl.tracking.labels``);
* :class:`DroneSetting` (``[drone]``): what each drone sends (``dronefl.roles.drone``);
* :class:`FusionSetting` (``[fusion]``): the cloud's fusion (``dronefl.tracking``);
* :class:`PlannerSetting` (``[planner]``): the cloud's planner (``dronefl.planning``).

The named settings are files in this folder (``recommended.toml``, ``paper.toml``); a user's
own file works the same way and may start from another with ``base = "recommended"``, giving
only the fields it changes. ``--set fusion.temporal_kernel=false`` overrides one field.
:meth:`Setting.load` validates everything once, before any work; no other layer re-checks a
field or holds a default. :meth:`Setting.digest` (a content hash of every field) names the
setting in episode identities and cache keys.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

#: The folder of the named settings.
SETTINGS_DIR = Path(__file__).resolve().parent
#: The setting every command and the Python API use unless told otherwise.
DEFAULT_SETTING = "recommended"

#: Choices of the named fields (the registries that implement them are keyed by the same names;
#: tests check that they agree).
OPTIMIZERS = ("adam", "sgd")
DRIFT_CORRECTIONS = ("none", "scaffold")
AGGREGATIONS = ("mean", "median", "trimmed-mean", "krum")
WEIGHT_DTYPES = ("float32", "float16")
ADAIN_SITES = ("encoder", "head")
STYLE_INITS = ("identity", "altitude")
BOX_SIZES = ("image", "metric", "ground")
LABEL_SOURCES = ("smoothed", "filtered", "ground_truth")
LABEL_DRONES = ("all", "others")
FUSION_METHODS = ("robust", "paper")
DISTANCE_POINTS = ("next", "rest")
#: ``pretraining.detection_gaps`` may name this instead of a probability.
AUTO = "auto"


class SettingError(ValueError):
    """A setting file or override is unreadable, or a field is missing, unknown, of the wrong
    type or out of range; the message names the file and the field."""


def knob(doc: str, **check: Any) -> Any:
    """A setting field with its documentation (shown by ``dronefl setting show``) and its
    checks: ``choices`` (a tuple of names), ``low`` / ``high`` (inclusive bounds),
    ``positive`` (> 0), ``optional`` (``None`` allowed). It has no default: every value comes
    from a setting file (the named ones are in this folder)."""
    return field(metadata={"doc": doc, **check})


class _Section:
    """Shared validation of the sub-configs: every field is checked against its type and its
    :func:`knob` checks when the sub-config is made."""

    section: ClassVar[str]

    def __post_init__(self) -> None:
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            object.__setattr__(self, f.name, _checked(self.section, f, str(f.type), value))


def _checked(section: str, f: Any, text: str, value: Any) -> Any:
    """``value`` of field ``f`` (of the annotated type ``text``) converted (a list to a tuple,
    an int to a float) and checked; :class:`SettingError` naming ``section.field`` otherwise."""
    name, meta = f"{section}.{f.name}", f.metadata
    if value is None:
        if meta.get("optional"):
            return None
        raise SettingError(f"{name}: must be given")
    if "tuple" in text:
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise SettingError(f"{name}: must be a list of names, got {value!r}")
        value = tuple(value)
        unknown = [v for v in value if v not in meta["choices"]]
        if unknown or not value or len(set(value)) != len(value):
            raise SettingError(
                f"{name}: must be distinct names among {', '.join(meta['choices'])}, got {value!r}"
            )
        return value
    if "bool" in text and isinstance(value, bool):
        return value
    if "float" in text and isinstance(value, int | float) and not isinstance(value, bool):
        return _number(name, float(value), meta)
    if "int" in text and isinstance(value, int) and not isinstance(value, bool):
        return _number(name, value, meta)
    if "str" in text and isinstance(value, str):
        if "choices" in meta and value not in meta["choices"]:
            raise SettingError(f"{name}: {value!r} is not one of {', '.join(meta['choices'])}")
        return value
    expected = {"bool": "true or false", "int": "an integer", "float": "a number", "str": "a name"}
    wanted = " or ".join(expected[t] for t in text.replace(" ", "").split("|") if t in expected)
    raise SettingError(f"{name}: must be {wanted}, got {value!r}")


def _number(name: str, value: float, meta: dict) -> float:
    if not math.isfinite(value):
        raise SettingError(f"{name}: must be finite, got {value!r}")
    if meta.get("positive") and not value > 0:
        raise SettingError(f"{name}: must be > 0, got {value!r}")
    low, high = meta.get("low"), meta.get("high")
    if (low is not None and value < low) or (high is not None and value > high):
        raise SettingError(f"{name}: must be in [{low}, {high}], got {value!r}")
    return value


@dataclass(frozen=True)
class ModelSetting(_Section):
    """The trajectory transformer that every drone flies (SPEC §4)."""

    section: ClassVar[str] = "model"
    past_steps: int = knob("L_p: past steps (0.2 s each) the predictor reads", low=2, high=100)
    adain_sites: tuple[str, ...] = knob(
        "where AdaIN conditions on the altitude: encoder (after every encoder layer, "
        "statistics over time) and/or head (before the output head, over channels)",
        choices=ADAIN_SITES,
    )
    head_style_init: str = knob(
        "how the head's AdaIN style starts: identity (plain normalisation) or altitude "
        "(outputs in proportion to the altitude, as a camera footprint is)",
        choices=STYLE_INITS,
    )
    box_size: str = knob(
        "how box sizes are read: image (fractions of the image, the paper's), metric (x the "
        "altitude / 50 m: in proportion to the ground size) or ground (the centre's offset too)",
        choices=BOX_SIZES,
    )


@dataclass(frozen=True)
class TrainingSetting(_Section):
    """How a drone's model trains in one FL round (offline FL, pretraining and the closed
    loop's online rounds) and how the cloud combines the updates."""

    section: ClassVar[str] = "training"
    optimizer: str = knob("local optimiser: adam, or sgd with momentum 0.9", choices=OPTIMIZERS)
    lr: float = knob("learning rate of the local steps", positive=True, high=1.0)
    batch_size: int = knob("windows per local step", low=1, high=65536)
    epochs: int = knob("local epochs E per round (offline FL and pretraining)", low=1, high=1000)
    drift_correction: str = knob(
        "client-drift correction: none (FedAvg's local steps) or scaffold (control variates; "
        "needs sgd)",
        choices=DRIFT_CORRECTIONS,
    )
    lr_step_at: float = knob(
        "fraction of the rounds trained at lr, the rest at lr x 0.1 (1: a constant lr)",
        positive=True,
        high=1.0,
    )
    proximal_mu: float = knob(
        "FedProx's proximal weight mu (the fedprox method only)", low=0.0, high=1e6
    )
    aggregation: str = knob(
        "how the cloud combines the updates: mean (FedAvg, weighted by windows), median, "
        "trimmed-mean or krum",
        choices=AGGREGATIONS,
    )
    weights_dtype: str = knob("number format of the weights on the radio", choices=WEIGHT_DTYPES)


@dataclass(frozen=True)
class PretrainingSetting(_Section):
    """The crop-field pretraining that the closed loop's models start from (SPEC §8)."""

    section: ClassVar[str] = "pretraining"
    rounds: int = knob(
        "FL rounds (the large centralized model: rounds x E epochs)", low=1, high=10000
    )
    seconds: float = knob("seconds of crop field recorded", low=1.0, high=86400.0)
    stride: int = knob("samples between training windows", low=1, high=1000)
    detection_gaps: float | str = knob(
        "share of the windows with a run of detections hidden, as the orchard's trees hide "
        "targets (0: as recorded), or 'auto': per scenario the better of 0 and 0.3 on an "
        "orchard validation recording",
    )

    def __post_init__(self) -> None:
        gaps = self.detection_gaps
        if gaps != AUTO and (
            isinstance(gaps, str | bool)
            or not isinstance(gaps, int | float)
            or not 0.0 <= gaps <= 1.0
        ):
            raise SettingError(
                f"pretraining.detection_gaps: must be 'auto' or in [0, 1], got {gaps!r}"
            )
        if gaps != AUTO:
            object.__setattr__(self, "detection_gaps", float(gaps))
        super().__post_init__()


@dataclass(frozen=True)
class LearningSetting(_Section):
    """The closed loop's online rounds (paper Sec. IV-D): how often, how long, on which
    pseudo-labels and for which drone."""

    section: ClassVar[str] = "learning"
    period: float = knob("seconds of flight between rounds", low=0.2, high=1e6)
    epochs: int = knob("local epochs per online round", low=1, high=1000)
    stride: int = knob("samples between training windows", low=1, high=1000)
    labels: str = knob(
        "pseudo-labels: smoothed (RTS over the whole past) or filtered fused tracks (the "
        "paper's), or ground_truth (an ablation)",
        choices=LABEL_SOURCES,
    )
    label_drones: str = knob(
        "who learns a label: all (the paper) or others (a drone learns a step's label of a "
        "target it watches only where another drone's prediction of it reached the cloud)",
        choices=LABEL_DRONES,
    )


@dataclass(frozen=True)
class DroneSetting(_Section):
    """What each drone sends to the cloud beside its predictions' positions."""

    section: ClassVar[str] = "drone"
    detected_only: bool = knob(
        "send a target's prediction only at the steps it detects the target (the cloud coasts "
        "the track meanwhile); false: whenever the last L_p steps hold a detection",
    )
    noise_reports: bool = knob(
        "send, per target, the running covariance of the drone's own forecast residual; the "
        "fusion shares two drones' noise by it (needs fusion.method robust)",
    )
    correct_bias: bool = knob(
        "subtract the running mean of the drone's forecast residual (its prediction against "
        "its next detection, back-projected) from what it sends",
    )


@dataclass(frozen=True)
class FusionSetting(_Section):
    """The cloud's fusion: one adaptive EKF per target fed by the drones' predictions (SPEC §6)."""

    section: ClassVar[str] = "fusion"
    method: str = knob(
        "robust (joint Huber-weighted update with consensus gating) or paper (sequential "
        "adaptive EKF)",
        choices=FUSION_METHODS,
    )
    constant_speed_psd: float = knob(
        "process noise q (m^2/s^3) of the constant-velocity model for constant-speed targets",
        positive=True,
        high=1e6,
    )
    random_walk_planner_psd: float | None = knob(
        "in a scenario with random-walk targets, q (m^2/s^3) of a second filter whose tracks "
        "the planner flies on (the labels keep the fusion's own); unset: one filter",
        positive=True,
        high=1e6,
        optional=True,
    )
    temporal_kernel: bool = knob(
        "in a scenario with random-walk targets, the planner's tracks are a 5-tap kernel over "
        "the drones' last predictions (fitted in the crop field)",
    )


@dataclass(frozen=True)
class PlannerSetting(_Section):
    """The cloud's planner (SPEC §7)."""

    section: ClassVar[str] = "planner"
    distance_at: str = knob(
        "where the distance term measures a drone: next (its next position, the paper) or rest "
        "(where it would stop under full braking, which ends orbiting)",
        choices=DISTANCE_POINTS,
    )


_SECTIONS: dict[str, type[_Section]] = {
    "model": ModelSetting,
    "training": TrainingSetting,
    "pretraining": PretrainingSetting,
    "learning": LearningSetting,
    "drone": DroneSetting,
    "fusion": FusionSetting,
    "planner": PlannerSetting,
}


@dataclass(frozen=True)
class Setting:
    """Every knob of the method, one sub-config per role (module docstring). ``name`` says
    where it came from (a named setting, a file, with ``+`` when fields were overridden); it is
    not part of :meth:`digest`."""

    model: ModelSetting
    training: TrainingSetting
    pretraining: PretrainingSetting
    learning: LearningSetting
    drone: DroneSetting
    fusion: FusionSetting
    planner: PlannerSetting
    name: str = field(default="custom", compare=False)

    def __post_init__(self) -> None:
        if self.training.drift_correction == "scaffold" and self.training.optimizer != "sgd":
            raise SettingError(
                "training.drift_correction: 'scaffold' needs training.optimizer 'sgd', got "
                f"{self.training.optimizer!r}"
            )
        if self.drone.noise_reports and self.fusion.method != "robust":
            raise SettingError(
                "drone.noise_reports: the paper fusion cannot use them; set fusion.method to "
                "robust or drone.noise_reports to false"
            )

    @classmethod
    def load(
        cls, name_or_path: str | Path = DEFAULT_SETTING, overrides: Sequence[str] = ()
    ) -> Setting:
        """The setting named ``name_or_path`` (a file of this package: ``recommended``,
        ``paper``) or in the TOML file at that path, with ``overrides`` (``section.field=value``,
        the value in TOML syntax or a bare name) applied; :class:`SettingError` naming the file
        and the field when anything is wrong."""
        data, name = _read(name_or_path, ())
        for override in overrides:
            _apply(data, override)
        if overrides:
            name += " + " + " ".join(overrides)
        return cls.from_dict(data, name)

    @classmethod
    def from_dict(cls, data: dict[str, Any], name: str = "custom") -> Setting:
        """The setting of ``data`` (``{section: {field: value}}``, every field given but the
        optional ones, which are unset when left out)."""
        unknown = sorted(set(data) - set(_SECTIONS))
        if unknown:
            raise SettingError(
                f"setting {name}: unknown section {unknown[0]!r} ({', '.join(_SECTIONS)})"
            )
        parts = {}
        for section, kind in _SECTIONS.items():
            values = data.get(section, {})
            if not isinstance(values, dict):
                raise SettingError(f"setting {name}: [{section}] must be a table")
            known = {f.name for f in fields(kind)}
            extra = sorted(set(values) - known)
            if extra:
                names = ", ".join(sorted(known))
                raise SettingError(f"setting {name}: {section}.{extra[0]}: unknown field ({names})")
            optional = {f.name for f in fields(kind) if f.metadata.get("optional")}
            values = {**dict.fromkeys(optional), **values}  # TOML has no null: left out
            missing = sorted(known - set(values))
            if missing:
                raise SettingError(f"setting {name}: {section}.{missing[0]}: missing")
            try:
                parts[section] = kind(**values)
            except SettingError as exc:
                raise SettingError(f"setting {name}: {exc}") from None
        try:
            return cls(**parts, name=name)
        except SettingError as exc:
            raise SettingError(f"setting {name}: {exc}") from None

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Every field as plain TOML/JSON values (tuples as lists), by section."""
        return {
            section: {
                k: list(v) if isinstance(v, tuple) else v
                for k, v in asdict(getattr(self, section)).items()
            }
            for section in _SECTIONS
        }

    def digest(self) -> str:
        """SHA-256 (12 hex digits) of every field: equal for equal settings, whatever their
        name or the file they came from."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    def to_toml(self) -> str:
        """The setting as a TOML file that :meth:`load` reads back (an unset field, which TOML
        cannot hold, left out)."""
        import tomli_w

        data = {
            s: {k: v for k, v in values.items() if v is not None}
            for s, values in self.to_dict().items()
        }
        return tomli_w.dumps(data)

    @classmethod
    def from_toml(cls, text: str, name: str = "custom") -> Setting:
        """A setting written by :meth:`to_toml`."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SettingError(f"setting {name}: not TOML ({exc})") from None
        return cls.from_dict(data, name)

    def override(self, overrides: Sequence[str]) -> Setting:
        """A copy with ``overrides`` (``section.field=value``, as :meth:`load` takes them)
        applied and validated."""
        if not overrides:
            return self
        data = self.to_dict()
        for override in overrides:
            _apply(data, override)
        return Setting.from_dict(data, f"{self.name} + {' '.join(overrides)}")

    def with_values(self, **sections: dict[str, Any]) -> Setting:
        """A copy with the given fields changed, e.g. ``with_values(learning={"labels":
        "filtered"})`` (validated like a loaded setting)."""
        data = self.to_dict()
        for section, values in sections.items():
            if section not in data:
                raise SettingError(f"setting {self.name}: unknown section {section!r}")
            data[section].update(values)
        changed = " ".join(
            f"{s}.{k}={v}" for s, values in sections.items() for k, v in values.items()
        )
        return Setting.from_dict(data, f"{self.name} + {changed}")

    def describe(self) -> str:
        """Every field with its value and its documentation, by section (``dronefl setting
        show``)."""
        lines = [f"# setting: {self.name} (digest {self.digest()})"]
        for section, kind in _SECTIONS.items():
            doc = " ".join((kind.__doc__ or "").split())
            lines += ["", f"[{section}]  # {doc}"]
            part = getattr(self, section)
            for f in fields(kind):
                value = getattr(part, f.name)
                shown = (
                    "(unset)"
                    if value is None
                    else json.dumps(list(value) if isinstance(value, tuple) else value)
                )
                lines.append(f"{f.name} = {shown}")
                lines.append(f"    # {f.metadata['doc']}")
        return "\n".join(lines)


def named_settings() -> tuple[str, ...]:
    """The names of the settings shipped in this package."""
    return tuple(sorted(p.stem for p in SETTINGS_DIR.glob("*.toml")))


def _read(name_or_path: str | Path, seen: tuple[str, ...]) -> tuple[dict[str, Any], str]:
    """The fields of a named setting or a TOML file, with those of its ``base`` underneath;
    and its name."""
    text = str(name_or_path)
    path = SETTINGS_DIR / f"{text}.toml"
    if "/" in text or text.endswith(".toml") or not path.is_file():
        path = Path(text)
        if not path.is_file():
            raise SettingError(
                f"setting {text}: no such file, nor a named setting ({', '.join(named_settings())})"
            )
        name = str(path)
    else:
        name = text
    if name in seen:
        raise SettingError(f"setting {name}: its bases form a loop ({' -> '.join(seen)})")
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SettingError(f"setting {name}: not a readable TOML file ({exc})") from None
    base = data.pop("base", None)
    if base is None:
        return data, name
    if not isinstance(base, str):
        raise SettingError(f"setting {name}: base must be a setting name or a file, got {base!r}")
    if not Path(base).is_absolute() and (path.parent / base).is_file():
        base = str(path.parent / base)
    merged, _ = _read(base, (*seen, name))
    for section, values in data.items():
        if not isinstance(values, dict):
            raise SettingError(f"setting {name}: [{section}] must be a table")
        merged.setdefault(section, {}).update(values)
    return merged, name


def _apply(data: dict[str, Any], override: str) -> None:
    """Apply one ``section.field=value`` to ``data``; the value is read as TOML (``false``,
    ``0.3``, ``["encoder"]``), else taken as a bare name."""
    key, sep, raw = override.partition("=")
    section, dot, name = key.strip().partition(".")
    if not sep or not dot or not name:
        raise SettingError(f"--set {override!r}: expected section.field=value")
    if section not in _SECTIONS:
        raise SettingError(
            f"--set {override!r}: unknown section {section!r} ({', '.join(_SECTIONS)})"
        )
    known = {f.name: f for f in fields(_SECTIONS[section])}
    if name not in known:
        raise SettingError(
            f"--set {override!r}: {section}.{name}: unknown field ({', '.join(sorted(known))})"
        )
    raw = raw.strip()
    if raw in ("none", "null", "") and known[name].metadata.get("optional"):
        value: Any = None
    else:
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
    data.setdefault(section, {})[name] = value


def setting_fields() -> dict[str, tuple[str, ...]]:
    """Every field name, by section (for tests and docs)."""
    return {s: tuple(f.name for f in fields(k)) for s, k in _SECTIONS.items()}


__all__ = [
    "AUTO",
    "DEFAULT_SETTING",
    "DroneSetting",
    "FusionSetting",
    "LearningSetting",
    "ModelSetting",
    "PlannerSetting",
    "PretrainingSetting",
    "Setting",
    "SettingError",
    "TrainingSetting",
    "named_settings",
]
