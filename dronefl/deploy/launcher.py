"""``dronefl deploy up``: the whole deployment on one machine, as separate OS processes.

It checks the setup before starting anything (scenario, free ports, certificates), writes the
pretrained model where every process reads it, starts the cloud (SuperLink + ServerApp), the
world and one drone process (+ SuperNode) per drone, each in its own process group with its
log in ``<out>/logs/``, and waits until all are healthy: the cloud announces itself on the
Zenoh link only once the world, every drone and every SuperNode are up. Then it watches the
episode (restarting a drone that dies, with ``restart_drones``), samples the memory of all
processes, and when the world and the cloud have finished writes ``<out>/metrics.json``.
Every process it started is stopped when it returns, fails or is interrupted
(:class:`~dronefl.deploy.processes.Children`).

Secure unless ``insecure``: every Zenoh link is mutual TLS with access control by role
(:mod:`dronefl.deploy.link`), the SuperLink serves HTTPS and admits only the drones'
registered SuperNode keys, all from the certificate folder given or a fresh one in
``<out>/certs``.

Ports (``base_port`` B, all on 127.0.0.1): world Zenoh B, cloud Zenoh B+1, SuperLink B+2,
drone i's SuperNode runtime API B+10+i.
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import psutil
import torch

from dronefl.config import ENVIRONMENTS, Scenario, load_scenario
from dronefl.deploy import check_deploy_method
from dronefl.deploy.certs import CertificateFolder, make_certificates
from dronefl.deploy.link import LAUNCHER, Link, LinkConfig, roles
from dronefl.deploy.processes import Child, Children, DeployError, marked, port_in_use, wait_for
from dronefl.deploy.results import DeploymentMetrics, RunInfo, deployment_metrics
from dronefl.io import atomic_write_text
from dronefl.models.model import PredictorConfig
from dronefl.settings import Setting
from dronefl.validation import check_duration, check_one_of, check_positive, check_seeds

HOST = "127.0.0.1"
#: The file in ``--out`` with the episode's resolved setting, which every process reads.
SETTING_FILE = "setting.toml"


@dataclass(frozen=True)
class DeployConfig:
    """One deployed episode on this machine (see ``dronefl deploy up --help``): ``scenario``
    flown for ``duration`` s in ``environment`` by ``method`` as ``setting`` says, seeded by
    ``seed``; ``out`` the episode folder; secure with the certificates of ``certs`` (default:
    a fresh folder in ``out``) unless ``insecure`` (plain TCP, no authentication);
    ``base_port`` the first of its ports; ``deadline_ms`` the wall ms the cloud waits for a
    step's predictions; ``start_timeout`` s for the processes to come up; ``pretrained`` the
    cache of pretrained models; ``restart_drones`` restarts a drone that dies."""

    scenario: str
    out: Path
    setting: Setting = field(default_factory=Setting.load)
    method: str = "dronefl"
    duration: float = 120.0
    seed: int = 0
    environment: str = "orchard"
    insecure: bool = False
    certs: Path | None = None
    base_port: int = 7440
    deadline_ms: float = 150.0
    start_timeout: float = 120.0
    pretrained: Path = Path("runs/pretrained")
    restart_drones: bool = False

    def __post_init__(self) -> None:
        check_deploy_method(self.method)
        check_one_of(self.environment, ENVIRONMENTS, "--env")
        if self.setting.learning.labels == "ground_truth":
            raise ValueError(
                "learning.labels: a deployed cloud does not know the truth; use smoothed or "
                "filtered"
            )
        for name in ("deadline_ms", "start_timeout"):
            check_positive(getattr(self, name), f"--{name.replace('_', '-')}")
        check_seeds([self.seed])
        if not 1024 <= self.base_port <= 65000:
            raise ValueError(f"--base-port: must be in [1024, 65000], got {self.base_port}")
        if self.insecure and self.certs is not None:
            raise ValueError("--certs: an --insecure deployment uses no certificates")
        if self.pretrained.exists() and not self.pretrained.is_dir():
            raise ValueError(f"--pretrained: {self.pretrained} is a file, not a folder")

    def ports(self, scenario: Scenario) -> dict[str, int]:
        """Every port of the deployment, by what listens there."""
        ports = {
            "world Zenoh": self.base_port,
            "cloud Zenoh": self.base_port + 1,
            "SuperLink": self.base_port + 2,
        }
        for d in scenario.drone_ids:
            ports[f"drone {d} SuperNode"] = self.base_port + 10 + d
        return ports

    def describe(self) -> dict[str, str | int | float | bool | None]:
        """What ran, for ``metrics.json``'s config (the setting recorded apart)."""
        values = {k: v for k, v in asdict(self).items() if k != "setting"}
        return {k: str(v) if isinstance(v, Path) else v for k, v in values.items()}


def model_file(state: dict[str, torch.Tensor], model: PredictorConfig, out: Path) -> Path:
    """The pretrained weights ``state`` of ``model`` as the file every process loads by path
    (``<out>/model/pretrained.npz``)."""
    from dronefl.deploy.clientapp import save_model

    path = out / "model" / "pretrained.npz"
    save_model(path, state, 0, model)
    return path


def preflight(config: DeployConfig) -> Scenario:
    """What can be checked before any work: the scenario, free ports, the certificate folder
    given; returns the scenario. :class:`~dronefl.deploy.processes.DeployError` or
    ``ValueError`` naming what is wrong."""
    scenario = load_scenario(config.scenario)
    check_duration(config.duration, scenario.dt)
    for what, port in config.ports(scenario).items():
        if port_in_use(HOST, port):
            raise DeployError(f"port {port} ({what}) is already in use; pick another --base-port")
    if config.certs is not None:
        _given_certificates(config.certs, scenario)
    return scenario


def run_deploy(
    config: DeployConfig, state: dict[str, torch.Tensor], model: PredictorConfig
) -> DeploymentMetrics:
    """Run the episode, every drone starting from the pretrained weights ``state`` of
    ``model`` (:func:`dronefl.experiments.prepare.prepare`, the ones ``dronefl track``
    starts from); returns (and writes) its metrics."""
    scenario = preflight(config)
    ports = config.ports(scenario)
    out = config.out.resolve()
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    certs = None if config.insecure else _certificates(config, scenario, out)
    model_path = model_file(state, model, out)
    atomic_write_text(out / SETTING_FILE, config.setting.to_toml())
    started = time.perf_counter()
    with Children(logs) as children:
        tls = certs.zenoh(LAUNCHER) if certs else None
        link_config = LinkConfig(
            (),
            (f"{HOST}:{ports['world Zenoh']}", f"{HOST}:{ports['cloud Zenoh']}"),
            tls,
            scenario.drone_ids,
        )
        commands = _commands(config, scenario, model_path, certs, out)
        cloud = children.start("cloud", commands["cloud"])
        world = children.start("world", commands["world"])
        drones = {
            d: children.start(f"drone-{d}", commands[f"drone-{d}"]) for d in scenario.drone_ids
        }
        with Link(link_config) as link:
            link.watch_alive()
            wait_for(
                lambda: "cloud" in link.alive(),
                config.start_timeout,
                "the cloud, the world, every drone and every SuperNode to be up",
                children,
            )
        print(f"deploy: all up after {time.perf_counter() - started:.1f} s", flush=True)
        processes = len(marked(children.owner))
        print(f"deploy: {processes} processes", flush=True)
        peak = _watch(children, cloud, world, drones, commands, config)
        for child in drones.values():  # they end when the world has
            try:
                child.process.wait(10)
            except Exception:  # noqa: BLE001 - stopped below in any case
                break
    run = RunInfo(
        method=config.method,
        seed=config.seed,
        environment=config.environment,
        config=config.describe(),
        processes=processes,
        peak_memory_mb=peak / 2**20,
    )
    metrics = deployment_metrics(scenario, out / "world", out / "cloud", out, run)
    metrics.save(out / "metrics.json")
    return metrics


def _certificates(config: DeployConfig, scenario: Scenario, out: Path) -> CertificateFolder:
    """The given certificate folder (checked), or a fresh one in ``<out>/certs``."""
    if config.certs is None:
        return make_certificates(out / "certs", scenario.drone_ids)
    return _given_certificates(config.certs, scenario)


def _given_certificates(folder: Path, scenario: Scenario) -> CertificateFolder:
    """The certificate folder ``folder``, every file of the scenario's roles checked, and
    every Zenoh certificate's common name (its role, by which access control knows it)."""
    certs = CertificateFolder(folder.resolve())
    identities = [certs.zenoh(role) for role in roles(scenario.drone_ids)]
    paths = [certs.ca, *certs.superlink]
    for identity in identities:
        paths += [identity.certificate, identity.key]
    for d in scenario.drone_ids:
        paths += [certs.supernode_key(d), certs.supernode_public_key(d)]
    certs.check(paths)
    for identity in identities:
        identity.check()
    return certs


def _commands(
    config: DeployConfig,
    scenario: Scenario,
    model: Path,
    certs: CertificateFolder | None,
    out: Path,
) -> dict[str, list[str]]:
    ports = config.ports(scenario)
    world_at, cloud_at = f"{HOST}:{ports['world Zenoh']}", f"{HOST}:{ports['cloud Zenoh']}"
    superlink = f"{HOST}:{ports['SuperLink']}"
    security = ["--tls-dir", str(certs.folder)] if certs else ["--insecure"]
    base = [sys.executable, "-m", "dronefl.cli"]
    common = ["--scenario", config.scenario, "--start-timeout", str(config.start_timeout)]
    common += security
    setting = ["--setting", str(out / SETTING_FILE)]
    commands = {
        "cloud": [
            *base, "cloud", *common, *setting,
            "--method", config.method,
            "--duration", str(config.duration),
            "--seed", str(config.seed),
            "--deadline-ms", str(config.deadline_ms),
            "--listen", cloud_at,
            "--connect", world_at,
            "--superlink-port", str(ports["SuperLink"]),
            "--model", str(model),
            "--out", str(out / "cloud"),
        ],
        "world": [
            *base, "world", *common,
            "--duration", str(config.duration),
            "--seed", str(config.seed),
            "--env", config.environment,
            "--listen", world_at,
            "--grace-ms", str(config.deadline_ms),
            "--out", str(out / "world"),
        ],
    }  # fmt: skip
    for d in scenario.drone_ids:
        commands[f"drone-{d}"] = [
            *base, "drone", *common, *setting,
            "--id", str(d),
            "--connect", f"{world_at},{cloud_at}",
            "--superlink", superlink,
            "--runtime-port", str(ports[f"drone {d} SuperNode"]),
            "--model", str(model),
            "--data-dir", str(out / "drones" / f"drone-{d}"),
        ]  # fmt: skip
    return commands


def _watch(
    children: Children,
    cloud: Child,
    world: Child,
    drones: dict[int, Child],
    commands: dict[str, list[str]],
    config: DeployConfig,
) -> float:
    """Wait for the world and the cloud to finish; returns the peak memory (bytes, RSS summed
    over every process of the deployment). A drone that dies is logged (and restarted with
    ``restart_drones``); the world or the cloud failing ends the deployment."""
    peak = 0.0
    restarts = dict.fromkeys(drones, 0)
    while cloud.process.poll() is None or world.process.poll() is None:
        for child in (cloud, world):
            code = child.process.poll()
            if code not in (None, 0):
                raise DeployError(
                    f"{child.name} exited with code {code}: {child.last_line()} (log: {child.log})"
                )
        for d, child in list(drones.items()):
            code = child.process.poll()
            if code is not None and world.process.poll() is None:
                print(f"deploy: drone {d} exited with code {code}", flush=True)
                if config.restart_drones:
                    restarts[d] += 1
                    drones[d] = children.start(
                        f"drone-{d}-restart{restarts[d]}", commands[f"drone-{d}"]
                    )
                    print(f"deploy: drone {d} restarted", flush=True)
                else:
                    del drones[d]
        peak = max(peak, _memory(children.owner))
        time.sleep(0.5)
    for child in (cloud, world):
        if child.process.returncode != 0:
            raise DeployError(
                f"{child.name} exited with code {child.process.returncode}: {child.last_line()}"
            )
    return peak


def _memory(owner: str) -> float:
    """Resident memory of every process of the deployment, bytes."""
    total = 0.0
    for process in marked(owner):
        try:
            total += process.memory_info().rss
        except psutil.Error:
            continue
    return total
