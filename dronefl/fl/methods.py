"""The compared methods (paper Sec. V-A, SPEC §5): which model each trains and how.

=================== ========= ===== ======== ===================================================
method              model     AdaIN relative  federated behaviour
=================== ========= ===== ======== ===================================================
fedavg              plain     no    no       FedAvg (McMahan et al., 2017)
fedprox             plain     no    no       FedAvg + proximal term mu/2 ||w - w_g||^2 (Li 2020)
fedper              plain     no    no       FedAvg of the body; the output head stays personal
                                             (Arivazhagan et al., 2019)
dronefl             dronefl   yes   yes      FedAvg with the position-invariant model
dronefl-no-adain    dronefl   no    yes      ablation: without AdaIN
dronefl-absolute    dronefl   yes   no       ablation: without relative positions
centralized         large     yes   yes      all windows pooled in the cloud (upper bound)
=================== ========= ===== ======== ===================================================
"""

from __future__ import annotations

from dataclasses import dataclass

from dronefl.models.model import PredictorConfig, Variant, predictor_config


@dataclass(frozen=True)
class Method:
    """One compared method: its ``name``, model ``variant`` with the ``adain``/``relative``
    switches, whether the output head is ``personal`` (FedPer), whether it uses the
    ``proximal`` term (FedProx) and whether it is ``federated`` (else centralized)."""

    name: str
    variant: Variant
    adain: bool
    relative: bool
    personal: bool = False
    proximal: bool = False
    federated: bool = True

    def predictor(self, past_steps: int, future_steps: int) -> PredictorConfig:
        """The model this method trains for windows of ``past_steps`` -> ``future_steps``."""
        return predictor_config(
            self.variant, past_steps, future_steps, adain=self.adain, relative=self.relative
        )


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("fedavg", "plain", adain=False, relative=False),
        Method("fedprox", "plain", adain=False, relative=False, proximal=True),
        Method("fedper", "plain", adain=False, relative=False, personal=True),
        Method("dronefl", "dronefl", adain=True, relative=True),
        Method("dronefl-no-adain", "dronefl", adain=False, relative=True),
        Method("dronefl-absolute", "dronefl", adain=True, relative=False),
        Method("centralized", "large", adain=True, relative=True, federated=False),
    )
}

#: The methods of the paper's Fig. 5, in plotting order.
FIG5_METHODS: tuple[str, ...] = ("fedavg", "fedprox", "fedper", "dronefl", "centralized")
#: The ablation of DroneFL's two design choices.
ABLATION_METHODS: tuple[str, ...] = ("dronefl", "dronefl-no-adain", "dronefl-absolute")
