"""Command lines of Flower's executables (flwr 1.41) and the connection file of ``flwr``.

* the SuperLink: one HTTP port for the Fleet, Control and Runtime APIs, runtime dependency
  installation off (the app's dependencies are those of this environment), TLS with the
  deployment's certificates and, with TLS, SuperNode authentication;
* a SuperNode per drone: its own local Runtime API port, node config
  ``drone-id=<id> data-dir="<folder>"``, the CA to check the SuperLink and its private key;
* ``flwr`` (run, register) reads ``$FLWR_HOME/config.toml``: one connection
  :data:`CONNECTION` to the SuperLink.
"""

from __future__ import annotations

import os
import shutil
import sys
import tomllib
from pathlib import Path

from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.processes import DeployError

#: Name of the SuperLink connection in ``$FLWR_HOME/config.toml``.
CONNECTION = "dronefl"


def executable(name: str) -> str:
    """Path of a Flower executable: beside this interpreter, else on ``PATH``."""
    local = Path(sys.executable).parent / name
    if local.is_file():
        return str(local)
    found = shutil.which(name)
    if found is None:
        raise DeployError(f"{name}: not found (is flwr installed in this environment?)")
    return found


def flower_env(flwr_home: Path) -> dict[str, str]:
    """Environment for Flower processes: their own home, no telemetry or update check, and
    this environment's executables first on ``PATH`` (Flower starts its helpers by name)."""
    return {
        "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]),
        "FLWR_HOME": str(flwr_home),
        "FLWR_TELEMETRY_ENABLED": "0",
        "FLWR_DISABLE_UPDATE_CHECK": "1",
    }


def superlink_command(host: str, port: int, certs: CertificateFolder | None) -> list[str]:
    command = [
        executable("flower-superlink"),
        "--host",
        host,
        "--port",
        str(port),
        "--disable-runtime-dependency-installation",
    ]
    if certs is None:
        return [*command, "--insecure"]
    certificate, key = certs.superlink
    certs.check([certs.ca, certificate, key])
    return [
        *command,
        "--ssl-ca-certfile",
        str(certs.ca),
        "--ssl-certfile",
        str(certificate),
        "--ssl-keyfile",
        str(key),
        "--enable-supernode-auth",
    ]


def supernode_command(
    drone_id: int,
    data_dir: Path,
    superlink: str,
    runtime_port: int,
    start_timeout: float,
    certs: CertificateFolder | None,
) -> list[str]:
    """Drone ``drone_id``'s SuperNode: its disk ``data_dir``, the SuperLink at ``superlink``
    (``host:port``), its local Runtime API on ``runtime_port``, ``start_timeout`` s to reach
    the SuperLink; with ``certs``, TLS and this drone's authentication key."""
    node_config = f'drone-id={drone_id} data-dir="{Path(data_dir).resolve()}"'
    command = [
        executable("flower-supernode"),
        "--superlink",
        superlink,
        "--port",
        str(runtime_port),
        "--node-config",
        node_config,
        "--max-wait-time",
        str(start_timeout),
    ]
    if certs is None:
        return [*command, "--insecure"]
    key = certs.supernode_key(drone_id)
    certs.check([certs.ca, key])
    return [
        *command,
        "--root-certificates",
        str(certs.ca),
        "--auth-supernode-private-key",
        str(key),
    ]


def write_connection(flwr_home: Path, address: str, ca: Path | None) -> Path:
    """Write ``$FLWR_HOME/config.toml`` with the connection :data:`CONNECTION`."""
    flwr_home.mkdir(parents=True, exist_ok=True)
    security = f'root-certificates = "{ca.resolve()}"' if ca is not None else "insecure = true"
    path = flwr_home / "config.toml"
    path.write_text(
        f'[superlink]\ndefault = "{CONNECTION}"\n\n'
        f'[superlink.{CONNECTION}]\naddress = "{address}"\n{security}\n'
    )
    os.chmod(path, 0o600)
    return path


def app_dir() -> Path:
    """The folder of the Flower app (the project root with ``[tool.flwr.app]``)."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "pyproject.toml").is_file():
        raise DeployError(f"{root}: no pyproject.toml with [tool.flwr.app] (run from a checkout)")
    return root


def stage_app(folder: Path) -> Path:
    """Copy the Flower app into ``folder`` and return it: ``pyproject.toml`` and the files its
    ``fab-include`` patterns name, found by globbing from the project root.

    ``flwr run DIR`` walks (and resolves) every file under ``DIR`` before it applies those
    patterns; run on a checkout with its ``.venv`` that walk took 8 s and 6 CPU-s of each
    deployment's start. The staged copy holds only the app's ~110 files, and the FAB built
    from it is the one the checkout gives."""
    root = app_dir()
    with (root / "pyproject.toml").open("rb") as handle:
        patterns = tomllib.load(handle)["tool"]["flwr"]["app"]["fab-include"]
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    shutil.copy2(root / "pyproject.toml", folder / "pyproject.toml")
    for pattern in patterns:
        for path in root.glob(pattern):
            target = folder / path.relative_to(root)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
    return folder
