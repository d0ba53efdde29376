"""A run folder is data: a crafted file that would run code when unpickled (an ``.npz`` holding
an object array, a pickle under the checkpoint's old name) runs nothing under any command that
reads run folders; it is refused with one line naming the file, or ignored."""

import io
import json
import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cli_child import run_cli

from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME

PACKAGE = Path(__file__).parents[1] / "dronefl"


class _Payload:
    """Unpickling it creates the file ``marker``: the proof that code ran."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _crafted_npz(path: Path, marker: Path, name: str = "prediction") -> None:
    """An ``.npz`` whose array ``name`` is a pickle of :class:`_Payload`."""
    payload = np.empty(1, dtype=object)
    payload[0] = _Payload(marker)
    buffer = io.BytesIO()
    np.save(buffer, payload, allow_pickle=True)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(f"{name}.npy", buffer.getvalue())


def _episode_folder(folder: Path, marker: Path) -> None:
    """An episode folder whose every file that holds arrays is a crafted one."""
    folder.mkdir(parents=True)
    _crafted_npz(folder / "episode.npz", marker)
    _crafted_npz(folder / CHECKPOINT_NAME, marker, "__tree__")
    (folder / "checkpoint.pkl").write_bytes(pickle.dumps(_Payload(marker)))
    config = {"scenario": "case2", "seed": 0}
    (folder / "metrics.json").write_text(json.dumps({"config": config}))


def test_the_package_never_unpickles():
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        assert not re.search(r"pickle\.loads?\(|allow_pickle=True|torch\.load\(", text), path


def test_the_payload_runs_when_unpickled(tmp_path):
    # The check's own check: the crafted file does run code when unpickled.
    marker = tmp_path / "ran"
    _crafted_npz(tmp_path / "x.npz", marker)
    with np.load(tmp_path / "x.npz", allow_pickle=True) as data:
        data["prediction"]
    assert marker.exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["replay", "EP"],
        ["replay", "EP", "--as-flown"],
        ["replay", "EP", "--set", "drone.detected_only=true"],
        ["track", "--scenario", "case2", "--resume", "--out", "EP", "--pretrained", "CACHE"],
    ],
)
def test_a_crafted_run_folder_runs_nothing(argv, tmp_path, capsys):
    marker = tmp_path / "ran"
    folder = tmp_path / "episode"
    _episode_folder(folder, marker)
    places = {"EP": str(folder), "CACHE": str(tmp_path / "cache")}
    argv = [places.get(a, a) for a in argv]
    if argv[0] == "track":  # a checkpoint of its own episode is all --resume reads
        (folder / "metrics.json").unlink()
    code, err = run_cli(capsys, *argv)
    assert code == 2, err
    assert not marker.exists()
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert str(folder) in err
