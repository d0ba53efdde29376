"""Federated learning on Flower: client and server apps, strategies, records adapter, comm."""
