"""The cloud host's process (``dronefl cloud``): a Flower SuperLink and the ServerApp.

It starts ``flower-superlink`` (a child), waits until it accepts connections, registers every
drone's SuperNode key (with TLS: only registered SuperNodes may join), writes the run config
and launches the ServerApp (:mod:`dronefl.deploy.cloud`) with ``flwr run`` against that
SuperLink (from a copy of just the app in ``OUT/app``, :func:`~dronefl.deploy.flower.stage_app`),
streaming its log. It returns when the run has ended and stops the SuperLink.
"""

from __future__ import annotations

import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import tomli_w

from dronefl.config import load_scenario
from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.cloud import CloudSettings
from dronefl.deploy.flower import (
    CONNECTION,
    executable,
    flower_env,
    stage_app,
    superlink_command,
    write_connection,
)
from dronefl.deploy.link import CLOUD
from dronefl.deploy.processes import Children, DeployError, port_in_use, port_open, wait_for
from dronefl.fl.records import FlSettings


@dataclass(frozen=True)
class SuperLinkSettings:
    """Where the SuperLink listens (``host``, ``port``) and how long it may take to start."""

    host: str = "127.0.0.1"
    port: int = 7442
    start_timeout: float = 60.0


def run_cloud(cloud: CloudSettings, fl: FlSettings, link: SuperLinkSettings, logs: Path) -> Path:
    """Run the cloud side of one episode; returns the path of ``cloud.json``."""
    scenario = load_scenario(cloud.scenario)
    out = Path(cloud.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if port_in_use(link.host, link.port):
        raise DeployError(f"--superlink-port: {link.host}:{link.port} is already in use")
    certs = CertificateFolder(Path(cloud.tls_dir)) if cloud.tls_dir else None
    if certs is not None:
        certs.check(
            [certs.ca, *certs.superlink]
            + [certs.supernode_public_key(d) for d in scenario.drone_ids]
        )
        certs.zenoh(CLOUD).check()  # the ServerApp's, checked before the SuperLink starts
    flwr_home = out / "flwr"
    env = flower_env(flwr_home)
    result = out / "cloud.json"
    result.unlink(missing_ok=True)
    # This host's own clients reach a SuperLink that listens on every interface via loopback.
    local = "127.0.0.1" if link.host in ("0.0.0.0", "") else link.host
    with Children(logs) as children:
        children.start("superlink", superlink_command(link.host, link.port, certs), env)
        wait_for(
            lambda: port_open(local, link.port),
            link.start_timeout,
            f"the SuperLink on {link.host}:{link.port}",
            children,
        )
        write_connection(flwr_home, f"{local}:{link.port}", certs.ca if certs else None)
        if certs is not None:
            for drone_id in scenario.drone_ids:
                _register(certs.supernode_public_key(drone_id), env, link.start_timeout)
        run_config = out / "run_config.toml"
        run_config.write_text(tomli_w.dumps({**fl.to_run_config(), **cloud.to_run_config()}))
        app = stage_app(out / "app")
        command = [executable("flwr"), "run", str(app), CONNECTION, "--stream"]
        flwr_run = children.start("flwr-run", [*command, "--run-config", str(run_config)], env)
        print(f"cloud: SuperLink on {link.host}:{link.port}, ServerApp launched", flush=True)
        while flwr_run.process.poll() is None:
            if (child := children.failed()) is not None:
                raise DeployError(f"{child.name} exited: {child.last_line()} (log: {child.log})")
            time.sleep(0.2)
    if not result.is_file():
        raise DeployError(f"the ServerApp ended without a result; see {flwr_run.log}")
    print(f"cloud: done, wrote {result}", flush=True)
    return result


def _register(public_key: Path, env: dict[str, str], timeout: float) -> None:
    """Register a SuperNode's public key with the SuperLink (``flwr supernode register``)."""
    command = [executable("flwr"), "supernode", "register", str(public_key), CONNECTION]
    done = subprocess.run(
        command, env={**os.environ, **env}, capture_output=True, text=True, timeout=timeout
    )
    if done.returncode != 0:
        lines = (done.stdout + done.stderr).strip().splitlines() or ["(no output)"]
        raise DeployError(f"registering {public_key} failed: {lines[-1]}")
    print(f"cloud: registered SuperNode key {public_key.name}", flush=True)
