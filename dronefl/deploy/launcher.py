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

Ports (``base_port`` B, all on 127.0.0.1): world Zenoh B, cloud Zenoh B+1, SuperLink B+2,
drone i's SuperNode runtime API B+10+i.
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import psutil

from dronefl.config import Scenario, load_scenario
from dronefl.deploy import DEPLOY_METHODS
from dronefl.deploy.certs import CertificateFolder, make_certificates
from dronefl.deploy.link import Link, LinkConfig
from dronefl.deploy.processes import Child, Children, DeployError, marked, port_in_use, wait_for
from dronefl.deploy.results import DeploymentMetrics, RunInfo, deployment_metrics
from dronefl.fl.records import PRESETS
from dronefl.planning import DISTANCE_POINTS
from dronefl.tracking.fusion import (
    NOISE_SPLITS,
    check_track_psd,
    constant_speed_q,
    has_random_walk,
    planner_track_psd,
)
from dronefl.tracking.labels import LABEL_DRONES
from dronefl.validation import check_one_of, check_pretrain_gaps

HOST = "127.0.0.1"


@dataclass(frozen=True)
class DeployConfig:
    """One deployed episode on this machine (see ``dronefl deploy up --help``)."""

    scenario: str
    out: Path
    method: str = "dronefl"
    duration: float = 120.0
    fl_period: float = 40.0
    seed: int = 0
    environment: str = "orchard"
    tls: bool = False
    certs: Path | None = None
    base_port: int = 7440
    deadline_ms: float = 150.0
    start_timeout: float = 120.0
    preset: str = "ours"
    epochs: int | None = None
    lr: float | None = None
    stride: int = 2
    pretrained: Path = Path("runs/pretrained")
    restart_drones: bool = False
    label_drones: str = "all"
    deshrink_labels: bool = False
    noise_split: str = "adaptive"
    correct_bias: bool = False
    detected_only: bool = False
    coverage_noise: bool = False
    temporal_kernel: bool = False
    pretrain_gaps: float | str = 0.0
    net_reports: bool = False
    planner_distance: str = "next"
    constant_speed_psd: float | None = None
    random_walk_track_psd: float | None = None

    def __post_init__(self) -> None:
        check_one_of(self.noise_split, NOISE_SPLITS, "--noise-split")
        if self.net_reports and self.noise_split != "reported":
            raise ValueError("--net-reports: needs --noise-split reported")
        check_one_of(self.preset, PRESETS, "--config")
        for name in ("epochs", "lr"):  # unset: the preset's, as `dronefl track`
            if getattr(self, name) is None:
                object.__setattr__(self, name, getattr(PRESETS[self.preset], name))
        check_one_of(self.method, DEPLOY_METHODS, "--method")
        check_one_of(self.label_drones, LABEL_DRONES, "--label-drones")
        for name in ("duration", "fl_period", "deadline_ms", "start_timeout", "lr"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')}: must be positive")
        if self.epochs < 1:
            raise ValueError(f"--epochs: must be >= 1, got {self.epochs}")
        if not 1024 <= self.base_port <= 65000:
            raise ValueError(f"--base-port: must be in [1024, 65000], got {self.base_port}")
        check_one_of(self.planner_distance, DISTANCE_POINTS, "--planner-distance")
        constant_speed_q(self.constant_speed_psd)
        check_track_psd("--random-walk-track-psd", self.random_walk_track_psd)
        check_pretrain_gaps(self.pretrain_gaps)

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


def pretrained_model(config: DeployConfig, scenario: Scenario, out: Path) -> Path:
    """The crop-field pretrained DroneFL model of the ``--config`` (:mod:`dronefl.experiments.
    pretrain`, the one ``dronefl track`` starts from), with its architecture, as a model file
    every process loads by path."""
    from dronefl.deploy.clientapp import save_model
    from dronefl.experiments.gap_choice import resolved_gaps
    from dronefl.experiments.pretrain import PretrainSpec, pretrained_state

    spec = PretrainSpec(scenario, "dronefl", stride=config.stride, preset=config.preset)
    spec = resolved_gaps(spec, config.pretrain_gaps, config.pretrained, progress=False)
    state = pretrained_state(spec, config.pretrained, progress=False)
    path = out / "model" / "pretrained.npz"
    save_model(path, state, 0, spec.model)
    return path


def run_deploy(config: DeployConfig) -> DeploymentMetrics:
    """Run the episode; returns (and writes) its metrics."""
    scenario = load_scenario(config.scenario)
    ports = config.ports(scenario)
    for what, port in ports.items():
        if port_in_use(HOST, port):
            raise DeployError(f"port {port} ({what}) is already in use; pick another --base-port")
    out = config.out.resolve()
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    certs = _certificates(config, scenario, out) if config.tls else None
    model = pretrained_model(config, scenario, out)
    started = time.perf_counter()
    with Children(logs) as children:
        tls = certs.zenoh("launcher") if certs else None
        link_config = LinkConfig(
            (), (f"{HOST}:{ports['world Zenoh']}", f"{HOST}:{ports['cloud Zenoh']}"), tls
        )
        commands = _commands(config, scenario, model, certs, out)
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
        config={k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
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
    certs = CertificateFolder(config.certs.resolve())
    roles = ["world", "cloud", "launcher", *(f"drone-{d}" for d in scenario.drone_ids)]
    paths = [certs.ca, *certs.superlink]
    for role in roles:
        identity = certs.zenoh(role)
        paths += [identity.certificate, identity.key]
    for d in scenario.drone_ids:
        paths += [certs.supernode_key(d), certs.supernode_public_key(d)]
    certs.check(paths)
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
    tls = ["--tls-dir", str(certs.folder)] if certs else []
    track_psd = planner_track_psd(scenario, None, config.random_walk_track_psd)  # the cloud's
    kernel = config.temporal_kernel and has_random_walk(scenario)  # as `track`'s
    base = [sys.executable, "-m", "dronefl.cli"]
    common = ["--scenario", config.scenario, "--start-timeout", str(config.start_timeout), *tls]
    commands = {
        "cloud": [
            *base, "cloud", *common,
            "--method", config.method,
            "--duration", str(config.duration),
            "--fl-period", str(config.fl_period),
            "--seed", str(config.seed),
            "--config", config.preset,
            "--epochs", str(config.epochs),
            "--lr", repr(config.lr),
            "--stride", str(config.stride),
            "--label-drones", config.label_drones,
            *(["--deshrink-labels"] if config.deshrink_labels else []),
            "--noise-split", config.noise_split,
            *(["--detected-only"] if config.detected_only else []),
            "--planner-distance", config.planner_distance,
            *(
                ["--constant-speed-psd", repr(config.constant_speed_psd)]
                if config.constant_speed_psd is not None
                else []
            ),
            *(["--track-psd", repr(track_psd)] if track_psd is not None else []),
            *(["--coverage-noise"] if config.coverage_noise else []),
            *(["--temporal-kernel"] if kernel else []),
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
            *base, "drone", *common,
            "--id", str(d),
            "--connect", f"{world_at},{cloud_at}",
            "--superlink", superlink,
            "--runtime-port", str(ports[f"drone {d} SuperNode"]),
            "--model", str(model),
            "--data-dir", str(out / "drones" / f"drone-{d}"),
            *(["--report-noise"] if config.noise_split == "reported" else []),
            *(["--correct-bias"] if config.correct_bias else []),
            *(["--detected-only"] if config.detected_only else []),
            *(["--net-reports"] if config.net_reports else []),
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
