"""In-process FedAvg diagnostics of the DroneFL predictor (no Ray, no Flower messages).

Run: ``PYTHONPATH=$PWD .venv/bin/python benchmarks/fl_diagnose.py RUN_DIR [options]`` where
``RUN_DIR`` is a recorded crop-field run (``dronefl simulate`` or the ``data/`` folder of
``dronefl fl-offline``). It plays FedAvg with the project's own local trainer
(:func:`dronefl.models.train.train_local`) on each drone's windows, exactly as the Flower
ClientApp does (model built with the run's seed, global weights loaded, seeded per (round,
drone), sample-weighted average), one drone after the other on one thread, and prints per
round:

* the mean over drones of the global model's test MSE (m^2) and per drone;
* the drift ``||w_i - w_g|| / ||w_g||`` of each drone's weights after local training;
* the round's move ``||w_g' - w_g|| / ||w_g||`` of the global weights, and the coherence of
  the drones' moves ``||sum_i p_i (w_i - w_g)|| / sum_i p_i ||w_i - w_g||`` (1 when every drone
  moved the same way, p_i the aggregation weights); ``--pooled`` prints its own move per round,
  so a federated round's progress can be set beside a pooled round's;
* with ``--verbose``, each drone's loss on its own training windows after local training and
  the global model's MSE on each drone's training windows (``--pooled``: the pooled model's).

``--pooled`` trains the same model on all drones' pooled training windows instead (the
``centralized-small`` bound), ``--local`` each drone alone. Options select the variant, E, the
local optimiser (``--optimizer adam|sgd``) and its lr and schedule (``--lr-decay``, or a step
``--lr-step-round R --lr-step-factor F`` as ``--config metric-scaffold-step``), batch size,
weighting, FedProx's mu on any model (``--proximal-mu``), SCAFFOLD's drift correction
(``--scaffold exact|path``, the library's :func:`~dronefl.models.train.drift_correction`),
AdaIN slopes kept at their start (``--freeze-style-slope``), a server optimiser (``--server-opt
adam|yogi --server-lr``: Flower's FedAdam / FedYogi update, checked against Flower in
``tests/fl/test_fl_diagnose.py``), a server learning rate on the averaged update
(``--server-step``: FedAvgM's ``server_learning_rate``, from round ``--server-step-from``),
rounds and the hold-out:
``--validation`` trains on the first 80 % of each drone's training part and evaluates on the
rest (never the test windows). Numbers claimed in the README and docs/fl.md are confirmed with
``dronefl fl-offline`` (the real Flower path).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import fields, replace

import numpy as np
import torch

from dronefl.experiments.fl_offline import OfflineConfig
from dronefl.fl.methods import METHODS
from dronefl.fl.records import FlSettings
from dronefl.logs import load_run
from dronefl.models.model import BOX_SIZES, STYLE_INITS, build_model
from dronefl.models.train import (
    OPTIMIZERS,
    drift_correction,
    evaluate,
    local_steps,
    proximal_term,
    train_local,
    updated_control_variate,
)
from dronefl.models.windows import WindowSet, build_windows, ground_truth_labels, split_windows


def build(config, seed: int, freeze_slope: bool) -> torch.nn.Module:
    """The model of ``config``; with ``freeze_slope`` its AdaIN styles' A is not trained."""
    model = build_model(config, seed=seed)
    if freeze_slope:
        for name, w in model.named_parameters():
            if name.endswith("style.weight"):
                w.requires_grad_(False)
    return model


def server_step(
    args: argparse.Namespace,
    server_round: int,
    current: dict[str, torch.Tensor],
    average: dict[str, torch.Tensor],
    moments: dict[str, dict[str, torch.Tensor]],
) -> dict[str, torch.Tensor]:
    """Flower's FedAdam / FedYogi server step (Reddi et al., 2021, as in
    ``flwr.serverapp.strategy``; beta_1 0.9, beta_2 0.99, tau 1e-3): with
    ``delta = average - current``, ``m <- b1 m + (1 - b1) delta``; Adam
    ``v <- b2 v + (1 - b2) delta^2``, Yogi ``v <- v - (1 - b2) delta^2 sign(v - delta^2)``;
    ``w <- w + eta_t m / (sqrt(v) + tau)``, ``eta_t`` bias-corrected for Adam as Flower does
    (``eta sqrt(1 - b2^(t+1)) / (1 - b1^(t+1))``) and ``eta`` for Yogi. Updates ``moments``
    in place."""
    b1, b2, tau = 0.9, 0.99, 1e-3
    adam = args.server_opt == "adam"
    eta = args.server_lr
    if adam:
        eta *= np.sqrt(1 - b2 ** (server_round + 1.0)) / (1 - b1 ** (server_round + 1.0))
    m, v = moments["m"], moments["v"]
    new = {}
    for k in current:
        if not current[k].is_floating_point():
            new[k] = average[k]
            continue
        delta = average[k] - current[k]
        m[k] = b1 * m.get(k, torch.zeros_like(delta)) + (1 - b1) * delta
        sq = delta**2
        previous = v.get(k, torch.zeros_like(delta))
        if adam:
            v[k] = b2 * previous + (1 - b2) * sq
        else:
            v[k] = previous - (1 - b2) * sq * torch.sign(previous - sq)
        new[k] = current[k] + eta * m[k] / (v[k].sqrt() + tau)
    return new


def full_gradient(model: torch.nn.Module, data: WindowSet, seed: int) -> dict[str, torch.Tensor]:
    """The gradient of the mean MSE (m^2) over all of ``data`` at the model's current weights,
    per trainable parameter, in training mode (dropout on, seeded by ``seed``) as the local
    steps see it: SCAFFOLD's control variate c_i (Karimireddy et al., 2020, option I)."""
    features, altitude, labels = (
        torch.from_numpy(data.features),
        torch.from_numpy(data.altitude),
        torch.from_numpy(data.labels),
    )
    torch.manual_seed(seed)
    model.train()
    model.zero_grad(set_to_none=True)
    for i in range(0, len(data), 1024):
        prediction = model(features[i : i + 1024], altitude[i : i + 1024])
        loss = (
            torch.nn.functional.mse_loss(prediction, labels[i : i + 1024], reduction="sum")
            / labels.numel()
        )
        loss.backward()
    return {n: w.grad.detach().clone() for n, w in model.named_parameters() if w.grad is not None}


def weighted_mean(
    variates: dict[int, dict[str, torch.Tensor]], counts: dict[int, float]
) -> dict[str, torch.Tensor]:
    """The server's control variate c: the drones' c_i weighted as their models are."""
    total = sum(counts[d] for d in variates)
    first = next(iter(variates.values()))
    return {k: sum(counts[d] * v[k] for d, v in variates.items()) / total for k in first}


def flat(state: dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([v.reshape(-1).float() for v in state.values()])


def splits_of(settings: FlSettings, validation: bool) -> dict[int, tuple[WindowSet, WindowSet]]:
    """Per drone (train, evaluation) windows: the chronological 80/20 split, or with
    ``validation`` the first 80 % of the training part and the remaining 20 % of it."""
    logs, truth = load_run(settings.run_dir)
    spec = settings.windows
    out = {}
    for d, log in sorted(logs.items()):
        labels = ground_truth_labels(log, truth)
        if not validation:
            out[d] = split_windows(log, labels, spec)
            continue
        n_train = int(log.t.shape[0] * spec.train_fraction)
        cut = int(n_train * 0.8)
        out[d] = (
            build_windows(log, labels, spec, (0, cut)),
            build_windows(log, labels, spec, (cut, n_train)),
        )
    return out


def round_lr(args: argparse.Namespace, r: int) -> float:
    """The local lr of round ``r``: ``--lr`` x decay^(r - 1), x the step factor after the
    step round."""
    step = args.lr_step_factor if 0 < args.lr_step_round < r else 1.0
    return args.lr * args.lr_decay ** (r - 1) * step


#: The window stride of ``dronefl fl-offline`` (samples), which the Fig. 5 numbers are measured at.
EVALUATION_STRIDE: int = next(f.default for f in fields(OfflineConfig) if f.name == "stride")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--method", default="dronefl", choices=list(METHODS))
    p.add_argument("--rounds", type=int, default=50)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--optimizer", choices=OPTIMIZERS, default="adam", help="local optimiser")
    p.add_argument("--lr-decay", type=float, default=1.0, help="lr x decay^(round - 1)")
    p.add_argument(
        "--lr-step-round",
        type=int,
        default=0,
        help="rounds after this one train with lr x --lr-step-factor (0: no step)",
    )
    p.add_argument("--lr-step-factor", type=float, default=0.1)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--stride", type=int, default=EVALUATION_STRIDE)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weighting", choices=("samples", "uniform"), default="samples")
    p.add_argument(
        "--server-momentum",
        type=float,
        default=0.0,
        help="FedAvgM's server momentum (Flower's update rule, server lr 1)",
    )
    p.add_argument(
        "--server-opt",
        choices=("none", "adam", "yogi"),
        default="none",
        help="server optimiser on the averaged update, as Flower's FedAdam / FedYogi",
    )
    p.add_argument("--server-lr", type=float, default=1e-2, help="FedAdam / FedYogi's eta")
    p.add_argument(
        "--server-step",
        type=float,
        default=1.0,
        help="FedAvg(M)'s server learning rate eta_g (Flower's server_learning_rate): "
        "w_g <- w_g - eta_g (w_g - average), with --server-momentum on the velocity",
    )
    p.add_argument(
        "--server-step-from", type=int, default=1, help="first round of --server-step (1 before)"
    )
    p.add_argument(
        "--proximal-mu", type=float, default=0.0, help="FedProx's mu on every drone (0: none)"
    )
    p.add_argument(
        "--scaffold",
        choices=("none", "exact", "path"),
        default="none",
        help="SCAFFOLD's drift correction with control variates c_i: 'exact', the full "
        "gradient at each round's global model (option I); 'path', the mean gradient of the "
        "drone's previous local steps (option II)",
    )
    p.add_argument(
        "--scaffold-from",
        type=int,
        default=1,
        help="first round whose local steps are corrected (variates are kept from round 1)",
    )
    p.add_argument("--pooled", action="store_true")
    p.add_argument("--local", action="store_true")
    p.add_argument("--validation", action="store_true")
    p.add_argument("--sites", default=None, help="AdaIN sites, e.g. encoder,head")
    p.add_argument("--head-init", default=None, choices=STYLE_INITS)
    p.add_argument("--box-size", default=None, choices=BOX_SIZES)
    p.add_argument(
        "--freeze-style-slope",
        action="store_true",
        help="keep every AdaIN style's altitude slope A at its start (train b only)",
    )
    p.add_argument("--every", type=int, default=5, help="print every N rounds")
    p.add_argument("--verbose", action="store_true")
    args = p.parse_args()
    if args.scaffold != "none" and args.proximal_mu:
        p.error("--scaffold and --proximal-mu are alternatives; give one")
    torch.set_num_threads(1)
    settings = FlSettings(
        run_dir=args.run_dir,
        out_dir="/tmp/unused",
        method=args.method,
        rounds=args.rounds,
        stride=args.stride,
        epochs=args.epochs,
        lr=args.lr,
        batch_size=args.batch,
        seed=args.seed,
    )
    splits = splits_of(settings, args.validation)
    overrides = {}
    if args.sites is not None:
        overrides["adain_sites"] = tuple(args.sites.split(","))
    if args.head_init is not None:
        overrides["head_style_init"] = args.head_init
    if args.box_size is not None:
        overrides["box_size"] = args.box_size
    model_config = replace(settings.model, **overrides)
    drones = list(splits)
    print(
        f"{args.method} {model_config.adain_sites if model_config.adain else 'no AdaIN'} "
        f"head init {model_config.head_style_init} box size {model_config.box_size} "
        f"E={args.epochs} {args.optimizer} lr={args.lr} "
        f"decay={args.lr_decay} step {args.lr_step_factor} after round {args.lr_step_round} "
        f"batch={args.batch} stride={args.stride} weighting={args.weighting} "
        f"server momentum {args.server_momentum} step {args.server_step} mu {args.proximal_mu} "
        f"frozen slopes {args.freeze_style_slope} windows per drone (train/eval): "
        + ", ".join(f"{d}: {len(tr)}/{len(te)}" for d, (tr, te) in splits.items())
    )
    if args.stride != EVALUATION_STRIDE:
        print(
            f"note: dronefl fl-offline evaluates at --stride {EVALUATION_STRIDE} by default; "
            f"a setting tuned at --stride {args.stride} sees "
            f"{EVALUATION_STRIDE / args.stride:g}x the windows (and SGD steps) per epoch"
        )
    started = time.perf_counter()
    if args.pooled or args.local:
        groups = {0: drones} if args.pooled else {d: [d] for d in drones}
        for g, members in groups.items():
            model = build(model_config, settings.seed, args.freeze_style_slope)
            data = WindowSet.concat([splits[d][0] for d in members])
            for r in range(1, args.rounds + 1):
                config = replace(
                    settings.train_config(r, g),
                    lr=round_lr(args, r),
                    optimizer=args.optimizer,
                )
                before = flat(model.state_dict())
                train_local(model, data, config)
                move = float((flat(model.state_dict()) - before).norm() / before.norm())
                if r % args.every == 0 or r == args.rounds or r == 1:
                    test = {d: evaluate(model, splits[d][1]) for d in members}
                    line = (
                        f"{'pooled' if args.pooled else f'drone {g} alone'} round {r:3d} "
                        f"mean {np.mean(list(test.values())):8.3f}  "
                        + " ".join(f"{v:7.3f}" for v in test.values())
                        + f"  move {move:.4f}"
                    )
                    if args.verbose:
                        line += "\n    model on each drone's train " + " ".join(
                            f"{evaluate(model, splits[d][0]):7.3f}" for d in members
                        )
                    print(line, flush=True)
        print(f"wall {time.perf_counter() - started:.1f} s")
        return
    global_state = build(model_config, settings.seed, args.freeze_style_slope).state_dict()
    velocity: dict[str, torch.Tensor] = {}
    moments: dict[str, dict[str, torch.Tensor]] = {"m": {}, "v": {}}
    variates: dict[int, dict[str, torch.Tensor]] = {}
    zeros = {
        n: torch.zeros_like(w)
        for n, w in build(model_config, settings.seed, False).named_parameters()
    }
    counts = {d: len(splits[d][0]) if args.weighting == "samples" else 1.0 for d in drones}
    for r in range(1, args.rounds + 1):
        new_variates: dict[int, dict[str, torch.Tensor]] = {}
        states, moves, weights, losses, drift = [], [], [], {}, {}
        g = flat(global_state)
        if args.scaffold == "exact":
            model = build(model_config, settings.seed, args.freeze_style_slope)
            model.load_state_dict(global_state)
            variates = {d: full_gradient(model, splits[d][0], settings.seed + r) for d in drones}
        server_variate = weighted_mean(variates, counts) if variates else {}
        for d in drones:
            model = build(model_config, settings.seed, args.freeze_style_slope)
            model.load_state_dict(global_state)
            config = replace(
                settings.train_config(r, d),
                lr=round_lr(args, r),
                optimizer=args.optimizer,
            )
            prox = proximal_term(global_state, args.proximal_mu) if args.proximal_mu else None
            corrected = args.scaffold != "none" and r >= args.scaffold_from and bool(variates)
            if corrected:
                prox = drift_correction(server_variate, variates[d])
            stats = train_local(model, splits[d][0], config, prox)
            if args.scaffold == "path":
                new_variates[d] = updated_control_variate(
                    variates[d] if corrected else zeros,
                    server_variate if corrected else zeros,
                    global_state,
                    dict(model.named_parameters()),
                    local_steps(len(splits[d][0]), config),
                    config,
                )
            states.append(model.state_dict())
            weights.append(stats.num_examples if args.weighting == "samples" else 1.0)
            losses[d] = evaluate(model, splits[d][0])
            moves.append(flat(states[-1]) - g)
            drift[d] = float(moves[-1].norm() / g.norm())
        if args.scaffold == "path":
            variates = new_variates
        total = sum(weights)
        average = {
            k: sum(w * s[k] for w, s in zip(weights, states, strict=True)) / total
            for k in global_state
        }
        # Flower's FedAvgM: pseudo-gradient g = w_g - avg, v <- beta v + g, w_g <- w_g - v.
        pseudo = {k: global_state[k] - average[k] for k in global_state}
        if args.server_momentum > 0 and r > 1:
            velocity = {k: args.server_momentum * velocity[k] + pseudo[k] for k in pseudo}
        else:
            velocity = pseudo
        if args.server_opt == "none":
            step = args.server_step if r >= args.server_step_from else 1.0
            global_state = {k: global_state[k] - step * velocity[k] for k in global_state}
        else:
            global_state = server_step(args, r, global_state, average, moments)
        coherence = float(
            sum(w * m for w, m in zip(weights, moves, strict=True)).norm()
            / sum(w * m.norm() for w, m in zip(weights, moves, strict=True))
        )
        move = float((flat(global_state) - g).norm() / g.norm())
        if r % args.every == 0 or r == args.rounds or r == 1:
            model = build(model_config, settings.seed, args.freeze_style_slope)
            model.load_state_dict(global_state)
            test = {d: evaluate(model, splits[d][1]) for d in drones}
            line = (
                f"round {r:3d} mean {np.mean(list(test.values())):8.3f} per drone "
                + " ".join(f"{v:7.3f}" for v in test.values())
                + "  drift "
                + " ".join(f"{v:.3f}" for v in drift.values())
                + f"  move {move:.4f} coherence {coherence:.2f}"
            )
            if args.verbose:
                on_train = {d: evaluate(model, splits[d][0]) for d in drones}
                line += "\n    local model on own train " + " ".join(
                    f"{v:7.3f}" for v in losses.values()
                )
                line += "\n    global model on own train " + " ".join(
                    f"{v:7.3f}" for v in on_train.values()
                )
            print(line, flush=True)
    print(f"wall {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
