"""The closed loop's two halves, one class each: :class:`DroneNode` (detect -> record ->
predict -> correct -> report) and :class:`CloudNode` (fuse -> plan -> label). ``dronefl track``
steps them in one process; ``dronefl.deploy`` carries their messages between processes."""

from dronefl.roles.cloud import CloudNode, Fused, Received, scenario_fuser
from dronefl.roles.drone import DroneNode, Uplink

__all__ = ["CloudNode", "DroneNode", "Fused", "Received", "Uplink", "scenario_fuser"]
