"""`dronefl deploy up` and its processes meeting a signal or an intruder: SIGTERM to a running
(secure) deployment stops every process with one line, and a SuperNode whose key is not
registered is refused by the SuperLink. Real processes on 127.0.0.1, as in
test_deploy_faults.py (kept apart so that the two files run side by side)."""

import os
import shutil
import signal
import subprocess
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from deploy_helpers import MARK, cli, free_port_block, survivors, wait_for_line
from quick_models import plant_quick_models

from dronefl.config import load_scenario
from dronefl.deploy.certs import make_certificates
from dronefl.deploy.clientapp import save_model
from dronefl.deploy.processes import port_open, wait_for
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.models.model import build_model
from dronefl.settings import Setting

#: One drone over one vehicle: the fewest processes a deployment has.
ONE_DRONE = Path(__file__).parents[1] / "data" / "scenarios" / "one_drone.yaml"


@pytest.mark.timeout(300)
@pytest.mark.slow
def test_supernode_with_an_unregistered_key_is_refused(tmp_path, run_env):
    certs = make_certificates(tmp_path / "certs", [1, 2])
    # Drone 2 of the intruder's copy has a key pair the cloud never registered.
    intruder = tmp_path / "intruder"
    shutil.copytree(certs.folder, intruder)
    key = ec.generate_private_key(ec.SECP384R1())
    (intruder / "supernode-2").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.OpenSSH,
            serialization.NoEncryption(),
        )
    )
    model = tmp_path / "model.npz"
    config = PretrainSpec(load_scenario("case1"), Setting.load()).model
    save_model(model, build_model(config).state_dict(), 0, config)
    base = free_port_block()
    cloud = subprocess.Popen(
        cli("cloud", "--model", str(model), "--tls-dir", str(certs.folder),
            "--listen", f"127.0.0.1:{base + 1}", "--connect", f"127.0.0.1:{base}",
            "--superlink-port", str(base + 2), "--out", str(tmp_path / "cloud")),
        env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        # Once the SuperLink listens, 14 s leave the drone several tries of its SuperNode
        # (1, 2, 4 s apart), all refused; a loaded machine may take 8 s over the first.
        wait_for(lambda: port_open("127.0.0.1", base + 2), 120, "the cloud's SuperLink")
        drone = subprocess.run(
            cli("drone", "--id", "2", "--model", str(model), "--tls-dir", str(intruder),
                "--superlink", f"127.0.0.1:{base + 2}", "--runtime-port", str(base + 12),
                "--connect", f"127.0.0.1:{base},127.0.0.1:{base + 1}", "--start-timeout", "14",
                "--data-dir", str(tmp_path / "disk")),
            env=run_env, capture_output=True, text=True, timeout=200,
        )  # fmt: skip
    finally:
        os.killpg(cloud.pid, signal.SIGTERM)
        cloud.wait(60)
    lines = [ln for ln in drone.stderr.splitlines() if ln.strip()]
    assert drone.returncode != 0
    assert len(lines) == 1
    assert lines[0].startswith(
        f"error: the SuperLink at 127.0.0.1:{base + 2} refused the SuperNode"
    )
    assert "Failed to activate SuperNode" in lines[0]
    assert survivors(run_env[MARK]) == []


@pytest.mark.timeout(300)
@pytest.mark.slow
def test_sigterm_to_deploy_up_stops_every_process(tmp_path, run_env, quick_pretrained):
    """SIGTERM to a running (secure) deployment: one line on stderr, exit 143 (128 +
    SIGTERM), and none of its processes (SuperLink, ServerApp, SuperNodes, ...) is left."""
    out = tmp_path / "deploy"
    said, errors = tmp_path / "launcher.out", tmp_path / "launcher.err"
    pretrained = plant_quick_models(quick_pretrained, load_scenario(ONE_DRONE), tmp_path / "p")
    command = cli(
        "deploy", "up", "--scenario", str(ONE_DRONE), "--duration", "60",
        "--base-port", str(free_port_block()), "--out", str(out),
        "--pretrained", str(pretrained),
    )  # fmt: skip
    with said.open("w") as stdout, errors.open("w") as stderr:
        launcher = subprocess.Popen(command, env=run_env, stdout=stdout, stderr=stderr)
    try:
        wait_for_line(said, "deploy: all up", launcher, 240)
        assert any("flower-supernode" in line for line in survivors(run_env[MARK]))
        launcher.send_signal(signal.SIGTERM)
        launcher.wait(120)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
    assert launcher.returncode == 143, said.read_text()[-3000:]
    assert [ln for ln in errors.read_text().splitlines() if ln.strip()] == [
        "terminated (SIGTERM); every process started was stopped"
    ]
    assert survivors(run_env[MARK]) == []
    assert (out / "certs" / "ca.crt").is_file()  # secure by default
