"""Two flights of one episode, step by step: where they part, and how far apart they end.

Compares the ``episode.npz`` of two folders (e.g. ``dronefl deploy up`` against ``dronefl
track`` with the same scenario, seed and setting, or one episode flown twice), array by array
(which predictions were sent, and those predictions, the fused tracks, Tr P, the planner's
cost): the number of steps
equal to the bit from the start and the first step that differs, then the closing metrics of
both (``metrics.json``)::

    python examples/episode_parity.py runs/deploy runs/t/case2/dronefl/seed0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

#: ``episode.npz`` arrays compared, by the name printed.
ARRAYS: dict[str, str] = {
    "predictions": "prediction",
    "fused tracks": "track_position",
    "Tr P": "trace",
    "cost": "cost",
}
#: ``metrics.json`` tracking figures printed side by side.
FIGURES: tuple[str, ...] = (
    "prediction_error", "sent_prediction_error", "tracking_distance", "tracking_error",
    "uncertainty", "total_cost",
)  # fmt: skip


def equal_steps(a: np.ndarray, b: np.ndarray) -> int:
    """How many leading steps (first axis) of ``a`` and ``b`` are equal to the bit (NaN equal
    to NaN); ``len(a)`` when all are."""
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} against {b.shape}")
    same = (a == b) | (np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f" else a == b
    same = same.reshape(len(a), -1).all(axis=1)
    return len(a) if same.all() else int(np.argmin(same))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("first", type=Path, help="an episode folder (episode.npz, metrics.json)")
    parser.add_argument("second", type=Path, help="the other flight of the same episode")
    args = parser.parse_args()
    with np.load(args.first / "episode.npz") as a, np.load(args.second / "episode.npz") as b:
        print(
            f"{'sent':13s} {equal_steps(a['sent'], b['sent']):5d} of {len(a['sent'])} steps equal"
        )
        for name, key in ARRAYS.items():
            first, second = a[key], b[key]
            if key == "prediction":  # a deployment's cloud knows only what was sent to it
                sent = (a["sent"] | b["sent"])[..., None]
                first, second = np.where(sent, first, np.nan), np.where(sent, second, np.nan)
            steps = equal_steps(first, second)
            where = "all" if steps == len(a[key]) else f"first differs at step {steps}"
            print(f"{name:13s} {steps:5d} of {len(a[key])} steps equal to the bit ({where})")
    metrics = [
        json.loads((f / "metrics.json").read_text())["tracking"] for f in (args.first, args.second)
    ]
    for figure in FIGURES:
        print(f"{figure:22s} {metrics[0][figure]:10.4f} {metrics[1][figure]:10.4f}")


if __name__ == "__main__":
    main()
