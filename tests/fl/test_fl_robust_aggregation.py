"""Robust aggregation rules from Flower (``aggregation``) and the naming of silent drones,
checked against values computed by hand."""

import numpy as np
import pytest
import torch
from flwr.app import Array, ArrayRecord, ConfigRecord, Message, RecordDict

from dronefl.fl.fault_list import parse_faults
from dronefl.fl.methods import METHODS
from dronefl.fl.records import ClientReport, FlSettings, SettingsError, to_arrays
from dronefl.fl.strategies import make_strategy


def _reply(drone: int, n: int, w: list[float]) -> Message:
    content = RecordDict(
        {
            "arrays": ArrayRecord({"w": Array(np.array(w))}),
            "metrics": ClientReport(drone, n, 1.0).to_metrics(),
        }
    )
    return Message(content=content, dst_node_id=0, message_type="train")


def _aggregate(aggregation: str, weights: list[list[float]], counts: list[int]) -> np.ndarray:
    strategy = make_strategy(METHODS["fedavg"], len(weights), 0.0, aggregation=aggregation)
    strategy._sent = {"w": (len(weights[0]),)}
    replies = [_reply(d + 1, n, w) for d, (w, n) in enumerate(zip(weights, counts, strict=True))]
    arrays, _ = strategy.aggregate_train(1, replies)
    return arrays["w"].numpy()


# Drone 4 sends garbage (finite, below the absurd threshold, so screening keeps it).
HONEST = [[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]]
GARBAGE = [[90.0, -90.0]]


def test_mean_follows_the_garbage_drone():
    # (0 + 1 + 0 + 90) / 4 = 22.75; (0 + 0 + 2 - 90) / 4 = -22.
    np.testing.assert_allclose(_aggregate("mean", HONEST + GARBAGE, [1, 1, 1, 1]), [22.75, -22])


def test_median_is_coordinatewise():
    # x: median of 0, 1, 0, 90 = (0 + 1) / 2; y: median of 0, 0, 2, -90 = (0 + 0) / 2.
    np.testing.assert_allclose(_aggregate("median", HONEST + GARBAGE, [1, 5, 1, 1]), [0.5, 0.0])


def test_trimmed_mean_cuts_one_drone_at_each_end():
    # beta = 1/4: x sorted 0, 0, 1, 90 -> mean(0, 1) = 0.5; y sorted -90, 0, 0, 2 -> 0.
    got = _aggregate("trimmed-mean", HONEST + GARBAGE, [1, 1, 1, 1])
    np.testing.assert_allclose(got, [0.5, 0.0])


def test_krum_picks_the_update_closest_to_its_neighbours():
    # n = 5, f = 1: score = sum of the n - f - 2 = 2 smallest squared distances to the others.
    # [0,0]: 1 + 4 = 5; [1,0]: 1 + 5 = 6; [0,2]: 4 + 5 = 9; [4,0]: 9 + 16 = 25; garbage: huge.
    weights = [[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [4.0, 0.0], *GARBAGE]
    np.testing.assert_array_equal(_aggregate("krum", weights, [1] * 5), [0.0, 0.0])


class TwoNodes:
    def get_node_ids(self):
        return [11, 12]


def test_a_drone_that_never_replies_is_named_in_the_round_log():
    strategy = make_strategy(METHODS["fedavg"], 2, 0.0)
    arrays = to_arrays({"w": torch.zeros(2)})
    # Round 1: both reply, so the cloud learns which node is which drone.
    first = list(strategy.configure_train(1, arrays, ConfigRecord(), TwoNodes()))
    replies = [
        Message(_reply(d, 1, [d, d]).content, reply_to=m)
        for d, m in zip((1, 2), first, strict=True)
    ]
    for reply, node in zip(replies, (11, 12), strict=True):
        reply.metadata.__dict__["_src_node_id"] = node
    strategy.aggregate_train(1, replies)
    # Round 2: drone 2 (node 12) is silent; drone 1 alone makes the model.
    strategy.configure_train(2, arrays, ConfigRecord(), TwoNodes())
    out, _ = strategy.aggregate_train(2, replies[:1])
    np.testing.assert_array_equal(out["w"].numpy(), [1.0, 1.0])
    assert strategy.logs[2].rejected == ["drone 2: no reply within the round timeout"]


@pytest.mark.parametrize(
    ("text", "problem"),
    [("2:1", "ROUND:DRONE:KIND"), ("x:1:nan", "ROUND:DRONE:KIND"), ("0:1:nan", "round >= 1"),
     ("2:1:explode", "kind of"), ("2:1:nan:4", "kind of")],
)  # fmt: skip
def test_a_bad_fault_list_fails_naming_the_item(text, problem):
    with pytest.raises(SettingsError, match=problem):
        FlSettings("run", "out", faults=text)


def test_faults_parse():
    faults = parse_faults("2:1:raise, 3:2:hang")
    assert [(f.server_round, f.drone_id, f.kind) for f in faults] == [
        (2, 1, "raise"),
        (3, 2, "hang"),
    ]


def test_an_unknown_aggregation_fails_naming_the_key():
    with pytest.raises(SettingsError, match="aggregation: 'mode'"):
        FlSettings("run", "out", aggregation="mode")
