"""Deployment: the closed loop as separate processes (SPEC §11).

One module per role, plus what they share::

    world.py      the simulator (stands in for vehicles and autopilots); owns the clock
    drone.py      one per drone: predictor on ONNX Runtime, onboard record on its disk,
                  and a Flower SuperNode whose ClientApp (clientapp.py) trains on that disk
    cloud.py      the ServerApp: fusion, planning, an FL round every ``fl_period`` s
    superlink.py  the cloud host's process: a Flower SuperLink and ``flwr run`` of cloud.py
    launcher.py   ``dronefl deploy up``: every process above on one machine, health, cleanup
    link.py       the per-step link over Zenoh (peer mode, explicit endpoints, TLS), its
                  key expressions and who sends on each
    access.py     Zenoh access control by certificate: who may send which message to whom
    messages.py   world <-> drone/cloud messages (the drone <-> cloud radio link keeps
                  the wire formats of :mod:`dronefl.wire`)
    grid.py       the Flower Grid as the cloud uses it: only live drones, fast polling
    flower.py     command lines of the Flower executables and their connection file
    processes.py  owned child processes (process groups, stopped on every exit path)
    certs.py      CA, SuperLink/Zenoh certificates (common name: the role) and SuperNode
                  key pairs
    results.py    the episode's metrics from the world's and the cloud's logs

Lock-step: the world publishes step ``k`` (telemetry to the cloud, each drone's odometry and
detections to that drone); each drone predicts and publishes; the cloud waits for the
predictions up to a wall-clock deadline, fuses what arrived (a late drone is silent that
step), plans and sends each drone its control, which the drone hands to its autopilot (the
world); after an FL round, if one is due, the cloud releases the step and the world moves on.

Secure by default: every link is mutual TLS, each Zenoh session allows each peer, known by
its certificate, only what its role sends (:mod:`~dronefl.deploy.access`), and the SuperLink
admits only registered SuperNodes. ``--insecure`` runs everything in the clear.
"""

from pathlib import Path

#: The closed-loop methods (:data:`dronefl.learners.LEARNERS`) a deployment runs: those whose
#: model flies on the drones (the centralized baselines predict in the cloud from raw inputs).
DEPLOY_METHODS = ("dronefl", "fixed")


def check_deploy_method(method: str) -> None:
    """``ValueError`` naming ``--method`` unless a deployment runs ``method``."""
    if method not in DEPLOY_METHODS:
        raise ValueError(
            f"--method: {method!r} is not one of {', '.join(DEPLOY_METHODS)} (a deployment "
            "flies the methods whose model runs on the drones)"
        )


#: What ``--insecure`` gives up, printed (to stderr) by every command that takes it.
INSECURE_WARNING = (
    "warning: --insecure: every link is plain TCP without authentication; any process that "
    "reaches a port can join, read the sensors and send controls"
)


def check_security(tls_dir: str, insecure: bool) -> None:
    """``ValueError`` unless exactly one of ``--tls-dir`` (a certificate folder) and
    ``--insecure`` is given: a process never runs in the clear unless asked to."""
    if insecure and tls_dir:
        raise ValueError("--insecure: not with --tls-dir (give one of them)")
    if not insecure and not tls_dir:
        raise ValueError(
            "--tls-dir: give the certificate folder of `dronefl deploy certs`, or --insecure "
            "for plain TCP without authentication"
        )
    if tls_dir and not Path(tls_dir).is_dir():
        raise FileNotFoundError(f"--tls-dir: {tls_dir} is not a folder")


class CloudError(RuntimeError):
    """The cloud could not run the episode (a peer missing, a round impossible)."""
