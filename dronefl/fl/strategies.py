"""Server-side strategies: Flower's FedAvg / FedProx with robust, logged aggregation.

Flower's strategy owns the round loop (``Strategy.start``); DroneFL only overrides hooks:

* ``configure_train`` / ``configure_evaluate`` number rounds globally, so that a resumed run
  continues at round ``k + 1`` (``round_offset``), and remember the names and shapes of the
  arrays sent; evaluation is sent the weights without SCAFFOLD's control variate;
* ``aggregate_train`` first screens every reply (:func:`screen_reply`): a drone that failed,
  sent no weights, other names or shapes, non-finite or absurd weights is left out of that round and
  logged, and the rest are averaged as usual (in drone order, so that a run is reproducible
  bit for bit), weighted by sample count:
  ``w_g = sum_i n_i w_i / sum_i n_i``;
* ``aggregate_evaluate`` keeps every drone's test MSE and their plain mean (the paper's
  "average test MSE across drones");
* a drone asked in a round that has not replied within the round's timeout is logged as such;
* ``aggregation`` other than ``mean`` hands the screened updates to one of Flower's robust
  rules instead of the weighted mean (:data:`AGGREGATORS`): the coordinate-wise median
  (FedMedian, Yin et al., 2018), the coordinate-wise mean without the largest and smallest
  ``1/n`` of the ``n`` values (FedTrimmedAvg with ``beta = 1/n``: one drone cut at each end
  when ``n >= 3``), or Krum (Blanchard et al., 2017) assuming one faulty drone.

FedPer and DroneFL need nothing else on the server: FedPer's drones simply never send their
personal head, DroneFL is FedAvg of a different model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from logging import WARNING

import numpy as np
from flwr.app import ArrayRecord, ConfigRecord, Message, MetricRecord
from flwr.common.logger import log
from flwr.serverapp import Grid
from flwr.serverapp.strategy import FedAvg, FedMedian, FedProx, FedTrimmedAvg, Krum

from dronefl.fl.methods import Method
from dronefl.fl.records import (
    ARRAYS_KEY,
    CONTROL_KEY,
    RoundRecord,
    SettingsError,
    mean_test_mse_metrics,
    reply_drone_id,
    reply_report,
)

#: Weights larger than this (in absolute value) are "absurd" for this model (its trained
#: weights are O(1)); such an update is rejected like a non-finite one.
MAX_ABS_WEIGHT = 1e4


@dataclass
class RoundLog:
    """What happened in one global round, as the server saw it (collected while the round
    runs; :meth:`record` freezes it)."""

    server_round: int
    train_loss: dict[int, float] = field(default_factory=dict)  # drone -> m^2
    test_mse: dict[int, float] = field(default_factory=dict)  # drone -> m^2
    rejected: list[str] = field(default_factory=list)  # "drone 2: non-finite weights"

    def record(self, traffic: dict[str, dict[str, int]]) -> RoundRecord:
        """The finished round with its bytes ``{"down": {type: B}, "up": {type: B}}``."""
        return RoundRecord(
            self.server_round,
            dict(sorted(self.test_mse.items())),
            dict(sorted(self.train_loss.items())),
            tuple(self.rejected),
            dict(traffic["down"]),
            dict(traffic["up"]),
        )


def screen_reply(reply: Message, expected: dict[str, tuple[int, ...]]) -> str | None:
    """Why a training reply must be left out of aggregation, or None if it is usable;
    ``expected`` maps the names of the arrays sent to their shapes."""
    if reply.has_error():
        return f"error ({_error_summary(reply.error.reason)})"
    content = reply.content
    if len(content.array_records) != 1 or len(content.metric_records) != 1:
        return "reply must hold one ArrayRecord and one MetricRecord"
    arrays = next(iter(content.array_records.values()))
    if set(arrays.keys()) != set(expected):
        return "weights with unexpected keys"
    if any(tuple(arrays[k].shape) != shape for k, shape in expected.items()):
        return "weights with unexpected shapes"
    try:
        report = reply_report(content)
    except (SettingsError, TypeError, ValueError) as exc:
        return f"bad metrics ({exc})"
    if report.num_examples < 1:
        return "no training examples"
    for value in arrays.values():
        w = value.numpy()
        if not np.isfinite(w).all():
            return "non-finite weights"
        if np.abs(w).max(initial=0.0) > MAX_ABS_WEIGHT:
            return f"absurd weights (|w| > {MAX_ABS_WEIGHT:g})"
    return None


def _error_summary(reason: str) -> str:
    """The message of a drone's error, without the traceback and process ids the simulation
    engine wraps it in (so that the history of a rerun is the same)."""
    lines = [line.strip() for line in reason.strip().strip("'<>").splitlines() if line.strip()]
    for line in reversed(lines):
        if "Message: " in line:
            return line.split("Message: ", 1)[1].strip().strip("'<>")
    return lines[-1][:200] if lines else "no reason given"


#: The robust aggregation rules, by ``aggregation`` name, for ``n`` drones.
AGGREGATORS: dict[str, Callable[[int], FedAvg]] = {
    "median": lambda n: FedMedian(arrayrecord_key=ARRAYS_KEY),
    "trimmed-mean": lambda n: FedTrimmedAvg(arrayrecord_key=ARRAYS_KEY, beta=1.0 / n),
    "krum": lambda n: Krum(arrayrecord_key=ARRAYS_KEY, num_malicious_nodes=1),
}


class RobustRounds:
    """Mixin for Flower strategies: global round numbers, screened aggregation, round logs."""

    round_offset: int
    logs: dict[int, RoundLog]
    _sent: dict[str, tuple[int, ...]]
    _asked: set[int]
    _drones: dict[int, int]
    _aggregator: FedAvg | None

    def _init_robust(self, round_offset: int, aggregator: FedAvg | None = None) -> None:
        self.round_offset = round_offset
        self.logs = {}
        self._sent = {}
        self._asked = set()
        self._drones = {}  # node id -> drone id, learnt from the drones' replies
        self._aggregator = aggregator

    def _drone_of(self, reply: Message) -> str:
        node = reply.metadata.src_node_id
        drone = reply_drone_id(reply)
        if drone is not None:
            self._drones[node] = drone
        return f"drone {self._drones[node]}" if node in self._drones else f"node {node}"

    def _ask(self, messages: Iterable[Message]) -> list[Message]:
        messages = list(messages)
        self._asked = {m.metadata.dst_node_id for m in messages}
        return messages

    def _log_silent(self, record: RoundLog, replies: list[Message]) -> None:
        """Log every drone asked this round that did not reply (timed out)."""
        silent = self._asked - {reply.metadata.src_node_id for reply in replies}
        for node in sorted(silent):
            name = f"drone {self._drones[node]}" if node in self._drones else f"node {node}"
            record.rejected.append(f"{name}: no reply within the round timeout")
            log(WARNING, "round %d: %s did not reply in time", record.server_round, name)

    def _log(self, server_round: int) -> RoundLog:
        r = server_round + self.round_offset
        return self.logs.setdefault(r, RoundLog(r))

    def configure_train(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        self._sent = {k: tuple(v.shape) for k, v in arrays.items()}
        return self._ask(
            super().configure_train(server_round + self.round_offset, arrays, config, grid)  # type: ignore[misc]
        )

    def configure_evaluate(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        # Evaluation needs the weights only, not SCAFFOLD's control variate.
        arrays = ArrayRecord({k: v for k, v in arrays.items() if k != CONTROL_KEY})
        return self._ask(
            super().configure_evaluate(server_round + self.round_offset, arrays, config, grid)  # type: ignore[misc]
        )

    def aggregate_train(
        self, server_round: int, replies: Iterable[Message]
    ) -> tuple[ArrayRecord | None, MetricRecord | None]:
        record = self._log(server_round)
        replies = list(replies)
        self._log_silent(record, replies)
        valid = []
        for reply in replies:
            reason = screen_reply(reply, self._sent)
            if reason is None:
                valid.append(reply)
                report = reply_report(reply.content)
                record.train_loss[report.drone_id] = report.value
            else:
                name = self._drone_of(reply)
                record.rejected.append(f"{name}: {reason}")
                log(WARNING, "round %d: left out %s: %s", record.server_round, name, reason)
        if not valid:
            log(WARNING, "round %d: no valid update; the global model is kept", record.server_round)
            return None, None
        # In drone order: replies arrive in any order, and floating-point sums depend on it.
        valid.sort(key=lambda reply: reply_report(reply.content).drone_id)
        for reply in valid:
            self._drone_of(reply)
        if self._aggregator is not None:
            return self._aggregator.aggregate_train(server_round, valid)
        return super().aggregate_train(server_round, valid)  # type: ignore[misc]

    def aggregate_evaluate(
        self, server_round: int, replies: Iterable[Message]
    ) -> MetricRecord | None:
        record = self._log(server_round)
        replies = list(replies)
        self._log_silent(record, replies)
        for reply in replies:
            if reply.has_error() or len(reply.content.metric_records) != 1:
                record.rejected.append(f"{self._drone_of(reply)}: evaluation failed")
                continue
            report = reply_report(reply.content)
            if report.finite:
                record.test_mse[report.drone_id] = report.value
            else:
                record.rejected.append(f"drone {report.drone_id}: non-finite test MSE")
        if not record.test_mse:
            return None
        return mean_test_mse_metrics(float(np.mean(list(record.test_mse.values()))))


class RobustFedAvg(RobustRounds, FedAvg):
    """FedAvg (McMahan et al., 2017) with screened aggregation; used by fedavg, fedper, dronefl.
    Without ``evaluate`` the rounds skip federated evaluation."""

    def __init__(
        self,
        num_drones: int,
        round_offset: int = 0,
        evaluate: bool = True,
        aggregation: str = "mean",
    ) -> None:
        FedAvg.__init__(self, **_all_nodes(num_drones, evaluate), arrayrecord_key=ARRAYS_KEY)
        self._init_robust(round_offset, _aggregator(aggregation, num_drones))


class RobustFedProx(RobustRounds, FedProx):
    """FedProx (Li et al., 2020): FedAvg that also sends ``proximal-mu`` to the drones, whose
    local loss adds ``(mu / 2) ||w - w_g||^2``."""

    def __init__(
        self,
        num_drones: int,
        proximal_mu: float,
        round_offset: int = 0,
        evaluate: bool = True,
        aggregation: str = "mean",
    ) -> None:
        FedProx.__init__(
            self,
            **_all_nodes(num_drones, evaluate),
            arrayrecord_key=ARRAYS_KEY,
            proximal_mu=proximal_mu,
        )
        self._init_robust(round_offset, _aggregator(aggregation, num_drones))


def _aggregator(aggregation: str, num_drones: int) -> FedAvg | None:
    """Flower's strategy whose ``aggregate_train`` combines the screened updates (None: the
    strategy's own weighted mean)."""
    if aggregation == "mean":
        return None
    if aggregation not in AGGREGATORS:
        raise SettingsError(f"aggregation: unknown {aggregation!r}")
    return AGGREGATORS[aggregation](num_drones)


def _all_nodes(num_drones: int, evaluate: bool) -> dict[str, int | float]:
    """Every connected drone trains (and evaluates, if rounds evaluate) in every round (paper
    Sec. IV-A)."""
    return {
        "min_train_nodes": num_drones,
        "min_evaluate_nodes": num_drones if evaluate else 0,
        "min_available_nodes": num_drones,
        "fraction_evaluate": 1.0 if evaluate else 0.0,
    }


def make_strategy(
    method: Method,
    num_drones: int,
    proximal_mu: float,
    round_offset: int = 0,
    evaluate: bool = True,
    aggregation: str = "mean",
) -> RobustFedAvg | RobustFedProx:
    """The server strategy of a federated ``method`` (rounds evaluate unless told not to)."""
    if not method.federated:
        raise ValueError(f"method {method.name!r} is not federated")
    if method.proximal:
        return RobustFedProx(num_drones, proximal_mu, round_offset, evaluate, aggregation)
    return RobustFedAvg(num_drones, round_offset, evaluate, aggregation)
