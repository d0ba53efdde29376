"""``dronefl reproduce``: each artefact's runs train exactly as the README's tables were
measured (the training settings they were measured with, written out here), and a bad
artefact is refused before any work."""

import pytest
from cli_child import run_cli

from dronefl.config import load_scenario
from dronefl.experiments.fl_offline import OfflineConfig
from dronefl.reproduce import FIG5_RUNS, FULL, QUICK
from dronefl.settings import Setting

#: What Fig. 5's runs were measured with, per (case, method): optimiser, lr, batch, drift
#: correction, the fraction of rounds at the full lr, box sizes, AdaIN sites.
MEASURED = {
    "metric-sgd": ("sgd", 3e-4, 64, "none", 1.0, "metric", "encoder,head"),
    "metric": ("adam", 1e-3, 64, "none", 1.0, "metric", "encoder,head"),
    "metric-scaffold-step": ("sgd", 3e-4, 64, "scaffold", 0.8, "metric", "encoder,head"),
    "metric-scaffold-step-lr6e-4": ("sgd", 6e-4, 64, "scaffold", 0.8, "metric", "encoder,head"),
    "paper": ("adam", 1e-3, 128, "none", 1.0, "image", "encoder"),
}
README_FIG5 = {
    ("case1", "dronefl"): "metric-sgd",
    ("case1", "local"): "metric-sgd",
    ("case1", "dronefl-no-adain"): "metric-sgd",
    ("case1", "centralized-small"): "metric",
    ("case1", "centralized"): "metric",
    **{(c, "dronefl"): "metric-scaffold-step-lr6e-4" for c in ("case2", "case3")},
    **{(c, "dronefl-no-adain"): "metric-scaffold-step-lr6e-4" for c in ("case2", "case3")},
    **{(c, "local"): "metric-scaffold-step" for c in ("case2", "case3")},
    **{(c, "centralized-small"): "metric-scaffold-step" for c in ("case2", "case3")},
    **{(c, "centralized"): "metric" for c in ("case2", "case3")},
    **{
        (c, m): "paper"
        for c in ("case1", "case2", "case3")
        for m in ("fedavg", "fedprox", "fedper")
    },
}


def test_fig5_trains_every_method_as_the_readme_measured_it(tmp_path):
    seen = set()
    for run in FIG5_RUNS:
        config = OfflineConfig(
            run.case, tmp_path, Setting.load(run.setting, run.overrides), FULL.rounds,
            FULL.seeds, FULL.recording, methods=run.methods,
        )  # fmt: skip
        for method in run.methods:
            settings = config.settings(method, 0, load_scenario(run.case))
            optimizer, lr, batch, drift, step, box, sites = MEASURED[README_FIG5[run.case, method]]
            if method in ("fedprox", "local", "centralized", "centralized-small"):
                drift = "none"  # SCAFFOLD corrects FedAvg-based federated methods only
            got = (settings.optimizer, settings.lr, settings.batch_size, settings.drift_correction,
                   settings.lr_step_at, settings.box_size, settings.adain_sites)  # fmt: skip
            assert got == (optimizer, lr, batch, drift, step, box, sites), (run.case, method)
            assert (settings.epochs, settings.rounds, settings.stride) == (10, 50, 10)
            seen.add((run.case, method))
    assert seen == set(README_FIG5)
    assert FULL.seeds == (0, 1, 2, 3, 4) and QUICK.rounds < FULL.rounds


def test_a_bad_artefact_is_refused_before_any_work(tmp_path, capsys):
    code, err = run_cli(capsys, "reproduce", "fig6", "--out", str(tmp_path / "out"))
    assert code == 2 and "ARTEFACT: 'fig6' is not one of fig4, fig5, table1, table2, all" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("artefact", ["fig4", "fig5", "table1", "table2", "all"])
def test_every_artefact_is_documented(artefact):
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    assert f"dronefl reproduce {artefact}" in readme
