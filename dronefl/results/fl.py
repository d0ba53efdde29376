"""Offline FL results (paper Fig. 5): per method and seed the test MSE per round and the final
one per drone, mean ± std over seeds (``results.json`` of ``dronefl fl-offline``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dronefl.fl.checkpoint import CheckpointError
from dronefl.fl.records import RoundRecord
from dronefl.io import atomic_write_json


@dataclass(frozen=True)
class Curve:
    """A test MSE per round (m^2): the ``mean`` over seeds and its ``std``."""

    mean: tuple[float, ...]
    std: tuple[float, ...]


@dataclass(frozen=True)
class SeedResult:
    """One method trained on one seed's recording: the mean over drones of the test MSE
    (m^2) after each round, the final one per drone (m^2), bytes down/up per round (all drones
    together; 0 for training in the cloud), rejected updates by round, and wall seconds."""

    seed: int
    mean_test_mse: tuple[float, ...]
    final_test_mse_per_drone: dict[int, float]
    bytes_down_per_round: tuple[int, ...]
    bytes_up_per_round: tuple[int, ...]
    rejected: dict[int, tuple[str, ...]]
    wall_seconds: float

    @property
    def final_test_mse(self) -> float:
        """Mean over drones of the final test MSE, m^2."""
        return self.mean_test_mse[-1]

    @classmethod
    def of(cls, seed: int, history: list[RoundRecord], seconds: float) -> SeedResult:
        rounds = sorted(history, key=lambda r: r.server_round)
        if any(r.mean_test_mse is None for r in rounds):
            raise ValueError(f"seed {seed}: a round without test MSE (was evaluation off?)")
        return cls(
            seed=seed,
            mean_test_mse=tuple(float(r.mean_test_mse) for r in rounds),  # type: ignore[arg-type]
            final_test_mse_per_drone=dict(rounds[-1].test_mse),
            bytes_down_per_round=tuple(sum(r.bytes_down.values()) for r in rounds),
            bytes_up_per_round=tuple(sum(r.bytes_up.values()) for r in rounds),
            rejected={r.server_round: r.rejected for r in rounds if r.rejected},
            wall_seconds=seconds,
        )

    def to_json(self) -> dict:
        return {
            "seed": self.seed,
            "final_test_mse": self.final_test_mse,
            "final_test_mse_per_drone": {
                str(k): v for k, v in self.final_test_mse_per_drone.items()
            },
            "mean_test_mse": list(self.mean_test_mse),
            "bytes_down_per_round": list(self.bytes_down_per_round),
            "bytes_up_per_round": list(self.bytes_up_per_round),
            "rejected": {str(k): list(v) for k, v in self.rejected.items()},
            "wall_seconds": self.wall_seconds,
        }

    @classmethod
    def from_json(cls, raw: dict) -> SeedResult:
        return cls(
            seed=int(raw["seed"]),
            mean_test_mse=tuple(float(v) for v in raw["mean_test_mse"]),
            final_test_mse_per_drone={
                int(k): float(v) for k, v in raw["final_test_mse_per_drone"].items()
            },
            bytes_down_per_round=tuple(int(v) for v in raw["bytes_down_per_round"]),
            bytes_up_per_round=tuple(int(v) for v in raw["bytes_up_per_round"]),
            rejected={int(k): tuple(v) for k, v in raw["rejected"].items()},
            wall_seconds=float(raw["wall_seconds"]),
        )


@dataclass(frozen=True)
class MethodResult:
    """One method over every seed: its architecture (``model`` in words, ``parameters``), how
    it trained, and one :class:`SeedResult` per seed. ``final_test_mse`` (m^2) and
    ``final_test_mse_per_drone`` (m^2) are means over seeds, with the population std."""

    method: str
    model: str
    parameters: int
    training: str
    seeds: tuple[SeedResult, ...] = ()

    def with_seed(self, result: SeedResult) -> MethodResult:
        kept = tuple(r for r in self.seeds if r.seed != result.seed)
        return replace(self, seeds=tuple(sorted((*kept, result), key=lambda r: r.seed)))

    def seed_result(self, seed: int) -> SeedResult | None:
        return next((r for r in self.seeds if r.seed == seed), None)

    @property
    def final_test_mse(self) -> float:
        return float(np.mean([r.final_test_mse for r in self.seeds]))

    @property
    def final_test_mse_std(self) -> float:
        return float(np.std([r.final_test_mse for r in self.seeds]))

    @property
    def drones(self) -> tuple[int, ...]:
        return tuple(sorted(self.seeds[0].final_test_mse_per_drone))

    @property
    def final_test_mse_per_drone(self) -> dict[int, float]:
        return {
            d: float(np.mean([r.final_test_mse_per_drone[d] for r in self.seeds]))
            for d in self.drones
        }

    @property
    def final_test_mse_per_drone_std(self) -> dict[int, float]:
        return {
            d: float(np.std([r.final_test_mse_per_drone[d] for r in self.seeds]))
            for d in self.drones
        }

    @property
    def curve(self) -> Curve:
        """Mean and std over seeds of the average test MSE per round, m^2."""
        values = np.array([r.mean_test_mse for r in self.seeds])  # (S, R)
        return Curve(tuple(values.mean(axis=0)), tuple(values.std(axis=0)))

    def to_json(self) -> dict:
        return {
            "model": self.model,
            "parameters": self.parameters,
            "training": self.training,
            "seeds_run": [r.seed for r in self.seeds],
            "final_test_mse": self.final_test_mse,
            "final_test_mse_std": self.final_test_mse_std,
            "final_test_mse_per_drone": {
                str(k): v for k, v in self.final_test_mse_per_drone.items()
            },
            "final_test_mse_per_drone_std": {
                str(k): v for k, v in self.final_test_mse_per_drone_std.items()
            },
            "mean_test_mse": list(self.curve.mean),
            "wall_seconds": sum(r.wall_seconds for r in self.seeds),
            "per_seed": [r.to_json() for r in self.seeds],
        }

    @classmethod
    def from_json(cls, method: str, raw: dict) -> MethodResult:
        return cls(
            method=method,
            model=str(raw["model"]),
            parameters=int(raw["parameters"]),
            training=str(raw["training"]),
            seeds=tuple(SeedResult.from_json(r) for r in raw["per_seed"]),
        )


@dataclass(frozen=True)
class OfflineResults:
    """Everything ``results.json`` holds: the scenario, the setting, and one
    :class:`MethodResult` per method. MSE: m^2, mean over a drone's test windows, the L_f
    future steps and both axes, then averaged over drones."""

    scenario: str
    setting: str
    setting_digest: str
    rounds: int
    duration_s: float
    stride: int
    methods: dict[str, MethodResult] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "scenario": self.scenario,
            "setting": self.setting,
            "setting_digest": self.setting_digest,
            "rounds": self.rounds,
            "duration_s": self.duration_s,
            "stride": self.stride,
            "mse": "m^2, mean over windows, future steps and both axes; averaged over drones",
            "methods": {name: block.to_json() for name, block in self.methods.items()},
        }

    @classmethod
    def from_json(cls, raw: dict) -> OfflineResults:
        return cls(
            scenario=str(raw["scenario"]),
            setting=str(raw["setting"]),
            setting_digest=str(raw["setting_digest"]),
            rounds=int(raw["rounds"]),
            duration_s=float(raw["duration_s"]),
            stride=int(raw["stride"]),
            methods={m: MethodResult.from_json(m, b) for m, b in raw["methods"].items()},
        )

    def save(self, path: Path) -> None:
        atomic_write_json(path, self.to_json())

    @classmethod
    def load(cls, path: Path) -> OfflineResults:
        try:
            return cls.from_json(json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            raise CheckpointError(
                f"{path}: corrupt results file; remove it or drop --resume"
            ) from None
