"""Experiments: each writes a run folder of JSON, arrays and plots."""
