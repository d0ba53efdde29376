"""The compared methods (paper Sec. V-A, SPEC §5): which model each trains and how.

================= ======== ===== ======== =================================================
method            model    AdaIN relative training
================= ======== ===== ======== =================================================
fedavg            plain    no    no       federated: FedAvg (McMahan et al., 2017)
fedprox           plain    no    no       federated: FedAvg + proximal term mu/2 ||w - w_g||^2
                                          (Li et al., 2020)
fedper            plain    no    no       federated: FedAvg of the body; the output head
                                          stays personal (Arivazhagan et al., 2019)
dronefl           dronefl  yes   yes      federated: FedAvg of the position-invariant model
dronefl-no-adain  dronefl  no    yes      federated; ablation: without altitude conditioning
dronefl-absolute  dronefl  yes   no       federated; ablation: without relative positions
centralized       large    yes   yes      pooled: every drone's windows in the cloud
centralized-small dronefl  yes   yes      pooled: DroneFL's own architecture, pooled windows
local             dronefl  yes   yes      local: each drone trains alone, never aggregated
================= ======== ===== ======== =================================================

Adding a method is one line in :data:`METHODS`; how each ``training`` kind runs is decided
in one place (:func:`dronefl.experiments.fl_offline.train_method`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dronefl.models.model import PredictorConfig, Variant, predictor_config

Training = Literal["federated", "pooled", "local"]


@dataclass(frozen=True)
class Method:
    """One compared method: its ``name``, model ``variant`` with the ``adain``/``relative``
    switches, whether the output head is ``personal`` (FedPer), whether it uses the
    ``proximal`` term (FedProx) and how it is trained: ``federated`` (Flower rounds),
    ``pooled`` (every drone's training windows in the cloud) or ``local`` (each drone alone)."""

    name: str
    variant: Variant
    adain: bool
    relative: bool
    personal: bool = False
    proximal: bool = False
    training: Training = "federated"

    @property
    def federated(self) -> bool:
        return self.training == "federated"

    def predictor(self, past_steps: int, future_steps: int, **overrides: object) -> PredictorConfig:
        """The model this method trains for windows of ``past_steps`` -> ``future_steps``
        (``overrides``: further :class:`PredictorConfig` fields, e.g. the AdaIN sites). The
        FL baselines' ``plain`` model always reads boxes as the image gives them, as the
        paper's baselines do."""
        if self.variant == "plain":
            overrides = {**overrides, "box_size": "image"}
        return predictor_config(
            self.variant,
            past_steps,
            future_steps,
            adain=self.adain,
            relative=self.relative,
            **overrides,
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
        Method("centralized", "large", adain=True, relative=True, training="pooled"),
        Method("centralized-small", "dronefl", adain=True, relative=True, training="pooled"),
        Method("local", "dronefl", adain=True, relative=True, training="local"),
    )
}

#: The methods of the paper's Fig. 5 and the two references that say what FL must reach
#: (``centralized-small``) and beat (``local``), in plotting order.
FIG5_METHODS: tuple[str, ...] = (
    "fedavg",
    "fedprox",
    "fedper",
    "dronefl",
    "centralized",
    "centralized-small",
    "local",
)
#: The ablation of DroneFL's two design choices.
ABLATION_METHODS: tuple[str, ...] = ("dronefl", "dronefl-no-adain", "dronefl-absolute")
