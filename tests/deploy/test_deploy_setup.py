"""A bad setup fails fast with one clear line and a non-zero exit, never a hang."""

import signal
import socket
import subprocess
import time

import numpy as np
import pytest
import torch
from deploy_helpers import MARK, cli, free_port_block, survivors

from dronefl.config import load_scenario
from dronefl.deploy.certs import make_certificates
from dronefl.deploy.clientapp import save_model
from dronefl.deploy.drone import _refusal
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.models.model import build_model, predictor_config
from dronefl.settings import Setting


def _run(command, env, timeout=120):
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    return done.returncode, lines


@pytest.fixture
def model_file(tmp_path):
    """The recommended setting's model, untrained."""
    path = tmp_path / "model.npz"
    config = PretrainSpec(load_scenario("case1"), Setting.load()).model
    save_model(path, build_model(config).state_dict(), 0, config)
    return path


@pytest.fixture
def certs(tmp_path):
    """A deployment's certificates for Case 1 (drones 1 and 2)."""
    return make_certificates(tmp_path / "certs", [1, 2])


def test_model_file_of_another_model_is_named(tmp_path, run_env, certs):
    path = tmp_path / "other.npz"
    weights = {"w": torch.from_numpy(np.zeros(3, dtype=np.float32))}
    save_model(path, weights, 0, predictor_config("dronefl", 10, 1))
    command = cli("drone", "--id", "1", "--model", str(path), "--tls-dir", str(certs.folder))
    code, lines = _run(command, run_env)
    assert code != 0
    assert lines == [f"error: --model: {path} does not hold the DroneFL predictor's weights"]


def test_cloud_refuses_a_model_file_of_another_setting(model_file, tmp_path, run_env):
    # model_file holds the recommended setting's model (box sizes in proportion to the
    # ground); the paper's reads them as the image gives them: the same weight shapes,
    # another model. Refused before the SuperLink starts.
    out = tmp_path / "cloud"
    code, lines = _run(
        cli("cloud", "--model", str(model_file), "--setting", "paper", "--out", str(out),
            "--insecure"),
        run_env,
    )  # fmt: skip
    assert code == 2
    assert (
        len(lines) == 1 and "--model" in lines[0] and "another model than the setting" in lines[0]
    )
    assert not (out / "logs").exists()
    assert survivors(run_env[MARK]) == []


def test_port_in_use_is_named(tmp_path, run_env):
    base = free_port_block()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", base + 2))
        busy.listen()
        code, lines = _run(
            cli("deploy", "up", "--base-port", str(base), "--out", str(tmp_path / "d")), run_env
        )
    assert code != 0
    assert lines == [
        f"error: port {base + 2} (SuperLink) is already in use; pick another --base-port"
    ]
    assert survivors(run_env[MARK]) == []


def test_missing_certificate_folder_is_named(tmp_path, run_env):
    command = cli(
        "deploy", "up", "--certs", str(tmp_path / "nowhere"),
        "--base-port", str(free_port_block()), "--out", str(tmp_path / "d"),
    )  # fmt: skip
    code, lines = _run(command, run_env)
    assert code == 2
    assert lines == [f"error: {tmp_path / 'nowhere' / 'ca.crt'}: certificate or key file missing"]


def test_drone_id_not_in_the_scenario(run_env, model_file):
    code, lines = _run(cli("drone", "--id", "9", "--model", str(model_file), "--insecure"), run_env)
    assert code == 2
    assert lines == ["error: --id: drone 9 is not in scenario case1 (drones 1, 2)"]


def test_unreachable_superlink(tmp_path, run_env, model_file, certs):
    port = free_port_block(4)
    command = cli(
        "drone", "--id", "1", "--model", str(model_file), "--superlink", f"127.0.0.1:{port}",
        "--connect", f"127.0.0.1:{port + 1},127.0.0.1:{port + 2}", "--start-timeout", "3",
        "--data-dir", str(tmp_path / "disk"), "--tls-dir", str(certs.folder),
    )  # fmt: skip
    code, lines = _run(command, run_env)
    assert code != 0
    assert lines == [
        f"error: timed out after 3 s waiting for the SuperLink at 127.0.0.1:{port} (unreachable)"
    ]
    assert survivors(run_env[MARK]) == []


@pytest.mark.slow
def test_certificate_of_another_ca_never_reaches_the_world(tmp_path, run_env, model_file):
    """The world listens with our CA's certificate; a drone presenting another CA's is not
    let in, and says so after its start timeout."""
    ours = make_certificates(tmp_path / "ours", [1])
    theirs = make_certificates(tmp_path / "theirs", [1])
    port = free_port_block(4)
    superlink = socket.socket()  # something listens where the SuperLink would
    superlink.bind(("127.0.0.1", port + 2))
    superlink.listen()
    world = subprocess.Popen(
        cli("world", "--listen", f"127.0.0.1:{port}", "--tls-dir", str(ours.folder),
            "--start-timeout", "60", "--out", str(tmp_path / "world")),
        env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        command = cli(
            "drone", "--id", "1", "--model", str(model_file), "--tls-dir", str(theirs.folder),
            "--superlink", f"127.0.0.1:{port + 2}", "--start-timeout", "4",
            "--connect", f"127.0.0.1:{port},127.0.0.1:{port + 1}",
            "--data-dir", str(tmp_path / "disk"),
        )  # fmt: skip
        code, lines = _run(command, run_env)
    finally:
        world.kill()
        world.wait()
        superlink.close()
    assert code != 0
    assert lines[-1].startswith("error: ")
    assert "did not" in lines[-1] and len(lines) == 1
    assert survivors(run_env[MARK]) == []


def test_the_supernode_s_refusal_line_beats_a_connection_retry():
    # On a loaded machine a refused SuperNode may also log connection retries, before or
    # after the refusal, or an attempt may end on retries alone: the refusal is the reason.
    refusal = "ERROR :   Failed to activate SuperNode: permission denied"
    retry = "WARNING :   Connection attempt failed, retrying in 0.84 seconds"
    assert _refusal(f"{refusal}\n{retry}\n") == refusal
    assert _refusal(f"{retry}\n{refusal}\n") == refusal
    assert _refusal(f"{retry}\n", earlier=refusal) == refusal
    assert _refusal(f"{retry}\n", earlier=None) == retry
    assert _refusal("", earlier=None) == "(no output)"


NEITHER = (
    "error: --tls-dir: give the certificate folder of `dronefl deploy certs`, or --insecure for "
    "plain TCP without authentication"
)


def test_a_process_runs_in_the_clear_only_when_asked(tmp_path, run_env, model_file, certs):
    world = cli("world", "--out", str(tmp_path / "world"))
    assert _run(world, run_env) == (2, [NEITHER])
    both = [*world, "--tls-dir", str(certs.folder), "--insecure"]
    assert _run(both, run_env) == (2, ["error: --insecure: not with --tls-dir (give one of them)"])
    assert _run(cli("drone", "--id", "1", "--model", str(model_file)), run_env) == (2, [NEITHER])


@pytest.mark.parametrize("listen", ["notaport", "127.0.0.1:99999"])
def test_bad_listen_endpoint_is_named(listen, tmp_path, run_env):
    command = cli("world", "--listen", listen, "--insecure", "--out", str(tmp_path / "world"))
    assert _run(command, run_env) == (
        2,
        [f"error: --listen: {listen!r} is not host:port (a port in 1-65535)"],
    )


def test_a_file_where_a_folder_belongs_is_named(tmp_path, run_env):
    file = tmp_path / "file"
    file.write_text("not a folder")
    assert _run(cli("deploy", "certs", str(file)), run_env) == (
        2,
        [f"error: FOLDER: {file} is a file, not a folder"],
    )
    command = cli(
        "deploy", "up", "--pretrained", str(file), "--base-port", str(free_port_block()),
        "--out", str(tmp_path / "d"),
    )  # fmt: skip
    assert _run(command, run_env) == (2, [f"error: --pretrained: {file} is a file, not a folder"])


def test_sigterm_stops_a_drone_and_its_supernode(tmp_path, run_env, model_file, certs):
    """SIGTERM to a drone whose SuperNode is trying to reach the SuperLink: one line, exit
    143 (128 + SIGTERM), and neither is left running."""
    port = free_port_block(4)
    superlink = socket.socket()  # something listens where the SuperLink would, never answers
    superlink.bind(("127.0.0.1", port + 2))
    superlink.listen()
    command = cli(
        "drone", "--id", "1", "--model", str(model_file), "--tls-dir", str(certs.folder),
        "--superlink", f"127.0.0.1:{port + 2}", "--runtime-port", str(port + 3),
        "--connect", f"127.0.0.1:{port},127.0.0.1:{port + 1}",
        "--data-dir", str(tmp_path / "disk"), "--start-timeout", "60",
    )  # fmt: skip
    drone = subprocess.Popen(
        command, env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 60
        while not any("flower-supernode" in line for line in survivors(run_env[MARK])):
            assert drone.poll() is None, drone.stderr.read()
            assert time.monotonic() < deadline, "the drone never started its SuperNode"
            time.sleep(0.1)
        drone.send_signal(signal.SIGTERM)
        _, stderr = drone.communicate(timeout=60)
    finally:
        if drone.poll() is None:
            drone.kill()
        superlink.close()
    assert drone.returncode == 143
    assert [ln for ln in stderr.splitlines() if ln.strip()] == [
        "terminated (SIGTERM); every process started was stopped"
    ]
    assert survivors(run_env[MARK]) == []
