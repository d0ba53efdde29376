"""The offline experiment end to end on a tiny Case 1: a federated method through Flower's
simulation engine beside the pooled and local references, results.json, mean +- std."""

import json
from dataclasses import replace

import numpy as np
import pytest

from dronefl.experiments.fl_offline import OfflineConfig, run_fl_offline
from dronefl.fl.checkpoint import CheckpointError
from dronefl.results.fl import OfflineResults
from dronefl.settings import Setting


@pytest.mark.slow
def test_new_methods_run_and_results_hold_final_mse_per_drone(tmp_path):
    # Prepare: 60 s of Case 1 (2 drones), one round; a federated ablation method on Flower,
    # DroneFL's model on pooled data, and each drone alone.
    methods = ("dronefl-no-adain", "centralized-small", "local")
    config = OfflineConfig("case1", tmp_path, rounds=1, seeds=(1,), duration=60.0, stride=5,
                           methods=methods, progress=False)  # fmt: skip
    # Execute
    results = run_fl_offline(config)
    # Assert: every method has a finite final MSE per drone; the mean is over the drones.
    raw = json.loads((tmp_path / "results.json").read_text())
    for method in methods:
        block = raw["methods"][method]
        per_drone = block["final_test_mse_per_drone"]
        assert set(per_drone) == {"1", "2"} and all(np.isfinite(list(per_drone.values())))
        assert block["final_test_mse"] == pytest.approx(np.mean(list(per_drone.values())))
    assert raw["methods"]["dronefl-no-adain"]["per_seed"][0]["bytes_up_per_round"][0] > 0
    assert OfflineResults.load(tmp_path / "results.json") == results
    assert (tmp_path / "fig5_case1.png").stat().st_size > 0


def test_several_seeds_give_mean_and_std(tmp_path):
    config = OfflineConfig("case1", tmp_path, rounds=1, seeds=(1, 2), duration=60.0, stride=5,
                           methods=("local",), progress=False)  # fmt: skip
    block = run_fl_offline(config).methods["local"]
    finals = [r.final_test_mse for r in block.seeds]
    assert [r.seed for r in block.seeds] == [1, 2] and finals[0] != finals[1]
    assert block.final_test_mse == pytest.approx(np.mean(finals))
    assert block.final_test_mse_std == pytest.approx(np.std(finals))
    with pytest.raises(ValueError, match="--seeds"):
        OfflineConfig("case1", tmp_path, seeds=(3, 3))


def test_resuming_reuses_a_finished_local_run(tmp_path):
    # A finished `local` run (its checkpoint holds one model per drone) is found finished
    # and reused by --resume, within the seed loop and when the results are gathered.
    config = OfflineConfig("case1", tmp_path, rounds=2, seeds=(1,), duration=60.0, stride=5,
                           methods=("local",), progress=False)  # fmt: skip
    first = run_fl_offline(config).methods["local"]
    checkpoint = next(tmp_path.rglob("local/checkpoint.npz"))
    written = checkpoint.stat().st_mtime_ns

    again = run_fl_offline(replace(config, resume=True)).methods["local"]

    assert checkpoint.stat().st_mtime_ns == written  # nothing was trained again
    assert again.seeds[0].final_test_mse == first.seeds[0].final_test_mse


def test_resuming_refuses_a_folder_trained_with_other_settings(tmp_path):
    # A finished `local` run with 1 local epoch per round; resuming the same --out with
    # 2 epochs must neither report the old result as the new setting nor continue it.
    one, two = (Setting.load("recommended", [f"training.epochs={e}"]) for e in (1, 2))
    config = OfflineConfig("case1", tmp_path, one, rounds=1, seeds=(1,), duration=60.0,
                           stride=5, methods=("local",), progress=False)  # fmt: skip
    first = run_fl_offline(config).methods["local"]
    folder = next(tmp_path.rglob("local/checkpoint.npz")).parent
    kept = {p.name: p.read_bytes() for p in folder.iterdir()}
    results = (tmp_path / "results.json").read_bytes()

    with pytest.raises(CheckpointError, match=r"results.json: results of another experiment"):
        run_fl_offline(replace(config, resume=True, setting=two))
    (tmp_path / "results.json").unlink()  # without them, the method's folder refuses
    with pytest.raises(CheckpointError, match=r"settings.json: .*epochs 1 there, 2 now"):
        run_fl_offline(replace(config, resume=True, setting=two))

    assert {p.name: p.read_bytes() for p in folder.iterdir()} == kept  # nothing lost
    (tmp_path / "results.json").write_bytes(results)
    again = run_fl_offline(replace(config, resume=True)).methods["local"]  # same: reused
    assert again.seeds[0].final_test_mse == first.seeds[0].final_test_mse
    raw = json.loads((folder / "result.json").read_text())
    assert raw["settings"]["epochs"] == 1 and raw["settings"]["method"] == "local"
    # Another recording length: the results, and without them the kept recording, refuse.
    longer = replace(config, resume=True, duration=30.0)
    with pytest.raises(CheckpointError, match=r"results.json: results of another .* 60 s"):
        run_fl_offline(longer)
    (tmp_path / "results.json").unlink()
    with pytest.raises(CheckpointError, match=r"summary.json: a recording of case1 seed 1, 60 s"):
        run_fl_offline(longer)
