"""A 2-drone, 2-round Flower simulation end to end."""

import json
import math

import pytest

from dronefl.fl.records import FlSettings
from dronefl.fl.simulation import WORKERS_ENV, backend_config, run_federated


@pytest.mark.slow
def test_two_drones_two_rounds_of_fedper(case1_run, tmp_path):
    # Resuming on the engine is tested bit for bit in test_fl_kill_resume.py (FedAvg) and
    # test_fl_scaffold.py (state kept on the drones' disks, as FedPer's heads are).
    settings = FlSettings(str(case1_run), str(tmp_path / "fedper"), method="fedper", rounds=2,
                          epochs=2, stride=5)  # fmt: skip
    seen = []
    history = run_federated(settings, on_round=seen.append)

    assert [h.server_round for h in history] == [1, 2] and seen == history
    assert json.loads(settings.history_path.read_text()) == [h.to_json() for h in history]
    for entry in history:
        assert set(entry.test_mse) == {1, 2}
        assert all(math.isfinite(v) for v in entry.test_mse.values())
        assert entry.rejected == ()
        down, up = entry.bytes_down, entry.bytes_up
        assert down["train"] > 2 * 11_000 * 4 and up["train"] > 2 * 11_000 * 4  # ~11k floats
    # FedPer's personal heads live on the drones' own disks, one per drone.
    assert sorted(p.name for p in (tmp_path / "fedper" / "personal").iterdir()) == [
        "drone_1.npz",
        "drone_2.npz",
    ]


@pytest.mark.parametrize("value", ["0", "-1", "two", ""])
def test_a_bad_worker_count_is_named(monkeypatch, value):
    monkeypatch.setenv(WORKERS_ENV, value)
    with pytest.raises(ValueError, match=f"{WORKERS_ENV}: must be a whole number >= 1"):
        backend_config()


def test_the_worker_count_sizes_ray(monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, "3")
    assert backend_config()["init_args"]["num_cpus"] == 3
    assert backend_config(2)["init_args"]["num_cpus"] == 2
    monkeypatch.delenv(WORKERS_ENV)
    assert backend_config()["init_args"]["num_cpus"] == 2
