"""Robust aggregation against a drone whose detector returns garbage (offline FL, Case 3).

Run: ``.venv/bin/python benchmarks/robust_aggregation.py [--rounds 10] [--epochs 5] [--seed 0]
[--duration 300] [--garbage 1] [--out runs/robust_aggregation]``.

Records Case 3 in the crop field (4 drones, 6 targets) once, then trains DroneFL for
``--rounds`` rounds with each aggregation rule of ``--aggregation`` (FedAvg's weighted mean,
Flower's FedMedian, FedTrimmedAvg with beta = 1/4, Krum with f = 1) on the same data in which
drone ``--garbage``'s onboard log was replaced by random boxes (every target "detected" at a
uniformly random box, :func:`dronefl.fl.faults.garble_detections`), plus the weighted mean on the
clean data as the reference. The garbage drone's updates are finite and of ordinary size, so the
screening keeps them; only the aggregation rule can limit their effect. Prints and writes
``results.json``: the final test MSE (m^2) of every honest drone, their mean, and the garbage
drone's own.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate
from dronefl.fl.faults import garble_detections
from dronefl.fl.records import AGGREGATIONS, FlSettings
from dronefl.fl.simulation import run_federated


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=300.0)
    parser.add_argument("--garbage", type=int, default=1, help="Drone whose detector fails.")
    parser.add_argument("--aggregation", default=",".join(AGGREGATIONS))
    parser.add_argument("--out", type=Path, default=Path("runs/robust_aggregation"))
    args = parser.parse_args()

    clean, garbled = args.out / "clean", args.out / "garbage"
    if not (clean / "ground_truth.npz").is_file():
        simulate(load_scenario("case3"), environment="crop_field", duration=args.duration,
                 seed=args.seed, out=clean, progress=False, plot=False)  # fmt: skip
        shutil.rmtree(garbled, ignore_errors=True)
    if not garbled.is_dir():
        shutil.copytree(clean, garbled)
        garble_detections(garbled / f"drone_{args.garbage}.npz", seed=args.seed)

    runs = [("mean, clean data", clean, "mean")]
    runs += [
        (f"{a}, drone {args.garbage} garbage", garbled, a) for a in args.aggregation.split(",")
    ]
    results = {"rounds": args.rounds, "epochs": args.epochs, "seed": args.seed,
               "duration_s": args.duration, "garbage_drone": args.garbage, "runs": {}}  # fmt: skip
    for label, data, aggregation in runs:
        settings = FlSettings(str(data), str(args.out / label.replace(" ", "_").replace(",", "")),
                              method="dronefl", rounds=args.rounds, epochs=args.epochs,
                              stride=10, seed=args.seed, aggregation=aggregation)  # fmt: skip
        final = run_federated(settings)[-1]["test_mse"]
        honest = {d: v for d, v in final.items() if int(d) != args.garbage}
        results["runs"][label] = {
            "honest_test_mse": honest,
            "honest_mean_test_mse": float(np.mean(list(honest.values()))),
            "garbage_drone_test_mse": final[str(args.garbage)],
        }
        print(f"{label:34s} honest drones' mean test MSE "
              f"{results['runs'][label]['honest_mean_test_mse']:8.3f} m^2  "
              f"(drone {args.garbage}: {final[str(args.garbage)]:.3f})", flush=True)  # fmt: skip
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
