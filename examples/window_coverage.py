"""A pretrained predictor's error by how many detections its window holds, in the orchard.

The closed loop's models are pretrained in the crop field, where a target is almost never
hidden; in the orchard the trees hide it, and a window of L_p steps may hold only a few
detections. This records ``--duration`` s of the orchard under the scripted pilot (seed
``--seed``: use a tuning seed, >= 10), cuts every window of every drone's assigned targets
(L_p -> 1, stride 1, ground-truth labels), and prints, for the crop-field pretraining of each
``--gaps`` probability (:attr:`~dronefl.experiments.pretrain.PretrainSpec.detection_gaps`;
pretrained on demand, 3-4 min each, cached under ``--pretrained``), the one-step prediction
MSE (m²) by the number of detections n in the window, for windows whose target is detected
at their last step (what a drone with ``detected_only`` sends) and for all windows (what
Table I's prediction error averages; ``pretraining.detection_gaps = "auto"`` chooses on the
same figure, over all windows, on a recording with seed 1001). Writes a plot of the same
beside the recording::

    python examples/window_coverage.py --scenario case2 --seed 10 --gaps 0 0.3 \\
        --out runs/gaps/coverage
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from dronefl.config import load_scenario
from dronefl.experiments.gap_choice import window_errors, window_set
from dronefl.experiments.pretrain import PretrainSpec, pretrained_state
from dronefl.experiments.simulate import simulate
from dronefl.models.windows import FEATURE_DIM
from dronefl.report.topdown import save_figure
from dronefl.settings import Setting


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="case2")
    parser.add_argument("--seed", type=int, default=10, help="orchard recording seed (tuning)")
    parser.add_argument("--duration", type=float, default=600.0, help="s of orchard")
    parser.add_argument("--gaps", type=float, nargs="+", default=[0.0, 0.3])
    parser.add_argument("--setting", default="recommended", help="setting name or file")
    parser.add_argument("--pretrained", type=Path, default=Path("runs/pretrained"))
    parser.add_argument("--out", type=Path, default=Path("runs/window_coverage"))
    args = parser.parse_args()
    scenario = load_scenario(args.scenario)
    setting = Setting.load(args.setting)
    specs = {
        g: PretrainSpec(scenario, setting, "dronefl", detection_gaps=g) for g in args.gaps
    }  # every spec is checked before anything runs
    run = args.out / f"orchard-seed{args.seed}"
    if not (run / "ground_truth.npz").is_file():
        simulate(scenario, environment="orchard", duration=args.duration, seed=args.seed,
                 out=run, plot=False)  # fmt: skip
    data = window_set(run, specs[args.gaps[0]], args.pretrained)
    detected = data.features[..., FEATURE_DIM - 1] > 0.5  # (B, L_p)
    count = detected.sum(axis=1)
    now = detected[:, -1]
    errors = {
        g: window_errors(pretrained_state(s, args.pretrained), s, data) for g, s in specs.items()
    }
    header = " | ".join(f"gaps {g:g}" for g in args.gaps)
    print(f"{args.scenario}, orchard seed {args.seed}: one-step MSE (m²) by detections n in the "
          f"window of {data.features.shape[1]}")  # fmt: skip
    print(f"| windows | n | share | {header} |")
    print("|---" * (3 + len(args.gaps)) + "|")
    figure, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for axis, (name, rows) in zip(
        axes, (("target detected now", now), ("all", np.ones_like(now))), strict=True
    ):
        levels = np.arange(1, data.features.shape[1] + 1)
        for g in args.gaps:
            mse = [errors[g][rows & (count == n)].mean() if (rows & (count == n)).any() else np.nan
                   for n in levels]  # fmt: skip
            axis.semilogy(levels, mse, marker="o", label=f"gaps {g:g}")
        for n in levels:
            cell = rows & (count == n)
            if cell.any():
                values = " | ".join(f"{errors[g][cell].mean():.3f}" for g in args.gaps)
                print(f"| {name} | {n} | {cell.sum() / rows.sum():.1%} | {values} |")
        totals = " | ".join(f"**{errors[g][rows].mean():.3f}**" for g in args.gaps)
        print(f"| {name} | all | 100% | {totals} |")
        axis.set(title=f"windows: {name}", xlabel="detections in the window")
        axis.legend()
    axes[0].set_ylabel("one-step MSE (m²)")
    print(f"wrote {save_figure(figure, args.out / 'window_coverage.png')}")


if __name__ == "__main__":
    main()
