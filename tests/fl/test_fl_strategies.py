"""Server aggregation: FedAvg's weighted average, screening of bad updates, FedPer, bytes."""

import math

import numpy as np
import pytest
import torch
from flwr.app import Array, ArrayRecord, ConfigRecord, Context, Error, Message, RecordDict
from flwr.serverapp.strategy import FedAvg

from dronefl.fl.client_app import PERSONAL_KEY, _local_model, _windows, handle_train
from dronefl.fl.methods import METHODS
from dronefl.fl.records import ClientReport, FlSettings, to_arrays
from dronefl.fl.server_app import initial_state
from dronefl.fl.strategies import RobustFedAvg, RobustFedProx, make_strategy
from dronefl.fl.traffic import CountingGrid, message_bytes


def _reply(drone: int, n: int, **arrays: np.ndarray) -> Message:
    content = RecordDict(
        {
            "arrays": ArrayRecord({k: Array(v) for k, v in arrays.items()}),
            "metrics": ClientReport(drone, n, 1.0).to_metrics(),
        }
    )
    return Message(content=content, dst_node_id=0, message_type="train")


def _aggregate(strategy, replies, shapes=None):
    strategy._sent = shapes or {"w": (2,)}
    return strategy.aggregate_train(1, replies)


def test_fedavg_is_the_sample_weighted_average():
    # Prepare: drone 1 has 1 window and w = [1, 2]; drone 2 has 3 windows and w = [3, 6].
    replies = [_reply(1, 1, w=np.array([1.0, 2.0])), _reply(2, 3, w=np.array([3.0, 6.0]))]
    # Execute
    arrays, _ = _aggregate(RobustFedAvg(num_drones=2), replies)
    # Assert: (1 * [1, 2] + 3 * [3, 6]) / 4 = [2.5, 5].
    np.testing.assert_allclose(arrays["w"].numpy(), [2.5, 5.0])


def _crashed() -> Message:
    return Message(Error(code=1, reason="drone crashed"), reply_to=_reply(3, 1, w=np.zeros(2)))


@pytest.mark.parametrize(
    ("make_bad", "reason"),
    [
        (lambda: _reply(3, 5, w=np.array([np.nan, 0.0])), "non-finite"),
        (lambda: _reply(3, 5, w=np.array([1e9, 0.0])), "absurd"),
        (lambda: _reply(3, 5, v=np.array([1.0, 1.0])), "unexpected keys"),
        (lambda: _reply(3, 5, w=np.array([1.0, 1.0, 1.0])), "unexpected shapes"),
        (_crashed, "drone crashed"),
    ],
)
def test_a_bad_update_is_left_out_and_logged(make_bad, reason):
    strategy = RobustFedAvg(num_drones=3)
    good = [_reply(1, 1, w=np.array([1.0, 2.0])), _reply(2, 3, w=np.array([3.0, 6.0]))]
    arrays, _ = _aggregate(strategy, [*good, make_bad()])
    np.testing.assert_allclose(arrays["w"].numpy(), [2.5, 5.0])
    assert len(strategy.logs[1].rejected) == 1
    assert reason in strategy.logs[1].rejected[0]
    assert sorted(strategy.logs[1].train_loss) == [1, 2]


def test_without_any_valid_update_the_global_model_is_kept():
    strategy = RobustFedAvg(num_drones=1)
    arrays, metrics = _aggregate(strategy, [_reply(1, 1, w=np.array([np.inf]))], {"w": (1,)})
    assert arrays is None and metrics is None


def test_fedprox_sends_mu_and_rounds_continue_after_resume():
    strategy = make_strategy(METHODS["fedprox"], num_drones=1, proximal_mu=0.3, round_offset=7)
    assert isinstance(strategy, RobustFedProx)

    class OneNode:
        def get_node_ids(self):
            return [11]

    messages = list(
        strategy.configure_train(1, to_arrays({"w": torch.ones(2)}), ConfigRecord(), OneNode())
    )
    config = messages[0].content["config"]
    assert config["proximal-mu"] == 0.3 and config["server-round"] == 8


def context_with(head: dict[str, torch.Tensor]) -> Context:
    """Drone 1's (partition 0's) context holding ``head`` as its personal head."""
    context = Context(
        run_id=1, node_id=1, node_config={"partition-id": 0}, state=RecordDict(), run_config={}
    )
    context.state[PERSONAL_KEY] = to_arrays(head)
    return context


def test_fedper_head_stays_on_the_drone_and_survives_aggregation(case1_run, tmp_path):
    settings = FlSettings(str(case1_run), str(tmp_path), method="fedper", rounds=2, epochs=1)
    body = initial_state(settings)
    assert not any(k.startswith("head.") for k in body)
    # A drone whose personal head is all 7s trains one round.
    head = {"head.weight": torch.full((2, 16), 7.0), "head.bias": torch.full((2,), 7.0)}
    context = context_with(head)
    layout = settings.layout
    msg = Message(
        RecordDict({"arrays": layout.pack(body), "config": ConfigRecord({"server-round": 2})}),
        dst_node_id=1,
        message_type="train",
    )
    reply = handle_train(msg, context, settings)
    sent = layout.unpack(reply.content["arrays"])
    assert set(sent) == set(body)  # the head never leaves the drone
    assert layout.size == sum(v.numel() for v in body.values())
    trained_head = context.state[PERSONAL_KEY].to_torch_state_dict()
    # It trained: the all-7s head predicts far too large positions, so every Adam step moves
    # each head weight down by about lr (Adam's step is lr x m / sqrt(v): +-lr while the
    # gradient keeps its sign); one epoch is ceil(windows / batch) steps.
    train_set, _ = _windows(settings.run_dir, 1, settings.windows, settings.labels)
    steps = math.ceil(len(train_set) / settings.batch_size) * settings.epochs
    moved = 7.0 - trained_head["head.bias"].numpy()
    np.testing.assert_allclose(moved, steps * settings.lr, rtol=0.05)
    step_sizes = np.abs(7.0 - trained_head["head.weight"].numpy())
    assert step_sizes.max() <= steps * settings.lr * 1.0001 and step_sizes.mean() > 0
    # The cloud averages bodies only; the drone's model for the next round keeps its own head.
    strategy = RobustFedAvg(num_drones=2)
    strategy._sent = {"weights": (layout.size,)}
    second = _reply(2, 10, weights=np.zeros(layout.size, dtype=np.float32))
    arrays, _ = strategy.aggregate_train(1, [reply, second])
    model = _local_model(settings, layout.unpack(arrays), context, 1, 3)
    for k, v in trained_head.items():
        torch.testing.assert_close(model.state_dict()[k], v)


def test_counting_grid_adds_up_every_message():
    class EchoGrid:
        def send_and_receive(self, messages, *, timeout=None):
            return [_reply(1, 1, w=np.ones(3)) for _ in messages]

    grid = CountingGrid(EchoGrid())
    sent = [
        Message(
            RecordDict(
                {
                    "arrays": ArrayRecord({"w": Array(np.zeros(100))}),
                    "config": ConfigRecord({"server-round": 4}),
                }
            ),
            dst_node_id=n,
            message_type="train",
        )
        for n in (1, 2)
    ]
    replies = grid.send_and_receive(sent, timeout=1)
    traffic = grid.traffic.of_round(4)
    assert traffic["down"]["train"] == sum(message_bytes(m) for m in sent)
    assert traffic["up"]["train"] == sum(message_bytes(m) for m in replies)
    assert traffic["down"]["train"] > 2 * 100 * 8  # at least the float64 payload


def test_aggregation_does_not_depend_on_the_order_replies_arrive_in():
    rng = np.random.default_rng(0)
    replies = [_reply(d, n, w=rng.normal(size=1000).astype(np.float32)) for d, n in
               [(1, 3), (2, 7), (3, 11)]]  # fmt: skip
    shapes = {"w": (1000,)}
    forward, _ = _aggregate(RobustFedAvg(num_drones=3), replies, shapes)
    backward, _ = _aggregate(RobustFedAvg(num_drones=3), replies[::-1], shapes)
    assert np.array_equal(forward["w"].numpy(), backward["w"].numpy())


def test_our_fedavg_equals_flowers_fedavg_on_unequal_sample_counts():
    # Prepare: three drones with random weights (two arrays each) and 5, 17 and 130 windows.
    rng = np.random.default_rng(4)
    counts = {1: 5, 2: 17, 3: 130}
    weights = {d: (rng.normal(size=(4, 3)), rng.normal(size=7)) for d in counts}
    replies = [_reply(d, n, a=weights[d][0], b=weights[d][1]) for d, n in counts.items()]
    shapes = {"a": (4, 3), "b": (7,)}
    # Execute: ours (screened, drone order) and Flower's own FedAvg on the same replies.
    ours, _ = _aggregate(RobustFedAvg(num_drones=3), replies[::-1], shapes)
    flowers, _ = FedAvg(arrayrecord_key="arrays").aggregate_train(1, replies)
    # Assert: the same arrays, and both the sample-weighted mean sum_i n_i w_i / sum_i n_i.
    for key, index in (("a", 0), ("b", 1)):
        expected = sum(n * weights[d][index] for d, n in counts.items()) / sum(counts.values())
        np.testing.assert_allclose(ours[key].numpy(), flowers[key].numpy(), rtol=1e-6)
        np.testing.assert_allclose(ours[key].numpy(), expected, rtol=1e-6)
