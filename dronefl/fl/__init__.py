"""Federated learning on Flower: client and server apps, strategies, records adapter, comm."""


class TrainingError(RuntimeError):
    """A federated training run that did not produce the model it was asked for (it stopped
    early, wrote no result, or played a round in which no drone's update was accepted)."""
