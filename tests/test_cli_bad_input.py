"""Bad input at the command line: every broken file of tests/data/corrupt/ handed to the
command that reads it, and bad option values, end with exit code 2, no traceback and (for a
file) one line naming it, before any work starts."""

import json
import shutil
from pathlib import Path

import pytest
from cli_child import run_cli

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate
from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
from dronefl.fl.records import FlSettings, RoundRecord
from dronefl.fl.server_app import initial_state

CORPUS = Path(__file__).parent / "data" / "corrupt"
CASES = ("missing", "empty", "truncated", "wrong_format", "wrong_version", "nan", "wrong_shape")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """20 s of Case 1, as `fl-offline` records it in OUT/data."""
    out = tmp_path_factory.mktemp("recorded") / "data"
    simulate(load_scenario("case1"), duration=20.0, seed=2, out=out, progress=False, plot=False)
    return out


def _place(source: Path, target: Path) -> None:
    """Put corpus file ``source`` at ``target`` (or make ``target`` missing)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    target.unlink(missing_ok=True)
    if source.exists():
        shutil.copyfile(source, target)


def _fl_run(tmp_path: Path, recorded: Path) -> Path:
    """An fl-offline folder whose seed-2 recording is ``recorded``; returns the seed's folder."""
    out = tmp_path / "fl" / "seed_2"
    shutil.copytree(recorded, out / "data")
    return out


FL = ["fl-offline", "--scenario", "case1", "--seeds", "2", "--duration", "20",
      "--methods", "fedavg", "--rounds", "2", "--resume"]  # fmt: skip


def _onboard(tmp_path, recorded, case):
    out = _fl_run(tmp_path, recorded)
    path = out / "data" / "drone_1.npz"
    if case == "missing":  # no drone log at all
        for log in (out / "data").glob("drone_*.npz"):
            log.unlink()
        return [*FL, "--out", str(out.parent)], out / "data"
    _place(CORPUS / "onboard_log" / f"{case}.npz", path)
    return [*FL, "--out", str(out.parent)], path


def _truth(tmp_path, recorded, case):
    out = _fl_run(tmp_path, recorded)
    path = out / "data" / "ground_truth.npz"
    _place(CORPUS / "ground_truth" / f"{case}.npz", path)
    return [*FL, "--out", str(out.parent)], path


def _checkpoint(tmp_path, recorded, case):
    out = _fl_run(tmp_path, recorded)
    path = out / "fedavg" / "checkpoint.npz"
    _place(CORPUS / "checkpoint" / f"{case}.npz", path)
    _place(CORPUS / "checkpoint" / "history.json", out / "fedavg" / "history.json")
    return [*FL, "--out", str(out.parent)], path


def _history(tmp_path, recorded, case):
    out = _fl_run(tmp_path, recorded)
    settings = FlSettings(str(out / "data"), str(out / "fedavg"), method="fedavg", seed=2)
    save_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        Checkpoint("fedavg", 2, initial_state(settings), [RoundRecord(1), RoundRecord(2)]),
    )
    _place(CORPUS / "history" / f"{case}.json", settings.history_path)
    return [*FL, "--out", str(out.parent)], settings.history_path


def _results(tmp_path, recorded, case):
    out = _fl_run(tmp_path, recorded)
    _place(CORPUS / "results" / f"{case}.json", out.parent / "results.json")
    return [*FL, "--out", str(out.parent)], out.parent / "results.json"


def _dataset(tmp_path: Path) -> Path:
    data = tmp_path / "dataset"
    (data / "scenes").mkdir(parents=True)
    (data / "dataset.json").write_text(json.dumps({"config": {"scenario": "case3"}}))
    return data


EVALUATE = ["detector", "evaluate", "--no-ship-noise"]


def _scenes(tmp_path, recorded, case):
    data = _dataset(tmp_path)
    path = data / "scenes" / "test_crop_field.jsonl"
    _place(CORPUS / "scenes" / f"{case}.jsonl", path)
    return [*EVALUATE, "--data", str(data), "--out", str(tmp_path / "eval")], path


def _onnx(tmp_path, recorded, case):
    path = CORPUS / "onnx" / f"{case}.onnx"
    data = _dataset(tmp_path)
    argv = [*EVALUATE, "--weights", str(path), "--data", str(data), "--out", str(tmp_path / "e")]
    return argv, path


def _scenario(tmp_path, recorded, case):
    path = CORPUS / "scenario" / f"{case}.yaml"
    return ["simulate", "--scenario", str(path), "--duration", "1", "--out", str(tmp_path)], path


#: Which command reads each kind of file. Pseudo-labels are read only inside the closed loop
#: (no command takes them), so only their loader is tested (test_corrupt_files.py).
COMMANDS = {
    "onboard_log": _onboard,
    "ground_truth": _truth,
    "checkpoint": _checkpoint,
    "history": _history,
    "results": _results,
    "scenes": _scenes,
    "onnx": _onnx,
    "scenario": _scenario,
}
#: Not errors: `--resume` without recorded data, checkpoint or results starts them afresh.
FRESH = {("ground_truth", "missing"), ("checkpoint", "missing"), ("results", "missing")}
BROKEN = [(kind, case) for kind in COMMANDS for case in CASES if (kind, case) not in FRESH]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("kind", "case"), BROKEN)
def test_a_broken_file_exits_2_with_one_line_naming_it(kind, case, tmp_path, recorded, capsys):
    argv, path = COMMANDS[kind](tmp_path, recorded, case)
    code, err = run_cli(capsys, *argv)
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert str(path) in lines[0]


@pytest.fixture(scope="module")
def a_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("plain") / "a_file"
    path.write_text("not a folder")
    return path


#: Bad option values, by command (FILE: a plain file, where a folder is expected).
BAD_OPTIONS = [
    "simulate --duration -1",
    "simulate --duration nan",
    "simulate --duration abc",
    "simulate --duration inf",
    "simulate --duration 0.001",
    "simulate --seed 4294967296",
    "simulate --env mars",
    "simulate --detector foo",
    "simulate --scenario nope",
    "simulate --seed -1",
    "simulate --out FILE/sub",
    "simulate --out /dev/null/x",
    "fl-offline --rounds 0",
    "fl-offline --methods foo",
    "fl-offline --set training.proximal_mu=-1",
    "fl-offline --set training.weights_dtype=int8",
    "fl-offline --set training.epochs=0",
    "fl-offline --set training.aggregation=mode",
    "fl-offline --faults 1:2",
    "fl-offline --duration nan",
    "fl-offline --duration inf",
    "fl-offline --set training.proximal_mu=nan",
    "fl-offline --set training.lr=inf",
    "fl-offline --seeds 4294967296",
    "fl-offline --stride 0",
    "fl-offline --seeds a",
    "fl-offline --setting nope",
    "fl-offline --out FILE/x",
    "fl-ablation --rounds 0",
    "fl-altitude --methods foo",
    "track --scenario nope",
    "track --method x",
    "track --env x",
    "track --detector x",
    "track --duration nan",
    "track --duration inf",
    "track --duration 0.001",
    "track --seed -2",
    "track --set learning.period=-1",
    "track --set learning.labels=x",
    "track --set fusion.method=x",
    "track --set training.weights_dtype=x",
    "track --pretrained FILE",
    "track --setting nope",
    "track --set training.lr=0",
    "track --set training.lr=nan",
    "track --set nothing",
    "track --method centralized-image",
    "table1 --methods centralized-image",
    "table1 --seeds a",
    "table1 --seeds -2",
    "table1 --scenarios nope",
    "table1 --duration -1",
    "pretrain --scenario nope",
    "pretrain --set pretraining.rounds=0",
    "pretrain --setting nope",
    "table1 --detector nope",
    "table1 --setting nope",
    "track --set fusion.random_walk_planner_psd=0",
    "table1 --set fusion.random_walk_planner_psd=-1",
    "table1 --methods fixed --label-ablation",
    "deploy up --set fusion.random_walk_planner_psd=0",
    "cloud --model FILE --set fusion.random_walk_planner_psd=-1",
    "track --set planner.distance_at=later",
    "track --set fusion.constant_speed_psd=0",
    "track --set pretraining.detection_gaps=often",
    "table1 --set pretraining.detection_gaps=1.5",
    "deploy up --set pretraining.detection_gaps=-0.1",
    "pretrain --set pretraining.detection_gaps=often",
    "deploy up --set fusion.constant_speed_psd=-1",
    "deploy up --set learning.labels=ground_truth",
    "deploy up --method centralized",
    "deploy up --duration inf",
    "deploy up --duration 0.001",
    "deploy up --pretrained FILE",
    "deploy up --deadline-ms nan",
    "deploy certs FILE",
    "world --listen nonsense --insecure",
    "world --listen 127.0.0.1:70000 --insecure",
    "world",
    "world --insecure --tls-dir NOWHERE",
    "drone --id 99 --insecure --model FILE",
    "drone --id 1 --model FILE",
    "cloud --model FILE",
    "replay NOWHERE --out FILE",
    "replay FILE --set fusion.method=kalman",
    "setting show nope",
    "image-baseline --epochs 0",
    "image-baseline --duration 0",
    "image-baseline --scenario nope",
    "demo --duration -1",
    "demo --duration inf",
    "demo --out FILE",
    "detector dataset --train-per-env 0",
    "detector train --epochs 0",
    "detector train --data NOWHERE",
    "detector evaluate --data NOWHERE",
    "detector figures --weights NOWHERE/x.onnx",
    "detector figures --eval NOWHERE/eval.json",
    "scenarios nope",
    "scenarios FILE",
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("options", BAD_OPTIONS)
def test_a_bad_option_exits_2_before_any_work(options, tmp_path, a_file, capsys):
    argv = options.replace("FILE", str(a_file)).replace("NOWHERE", str(tmp_path / "nowhere"))
    argv = argv.split()
    if "--out" not in argv and argv[0] not in ("scenarios", "setting"):
        argv += ["--out", str(tmp_path / "out")]
    code, err = run_cli(capsys, *argv)
    assert code == 2, err
    assert "Traceback" not in err
    assert err.strip(), "no message"
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
