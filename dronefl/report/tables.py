"""Plain-text summaries printed by the commands."""

from __future__ import annotations


def format_metrics(metrics: dict) -> str:
    """A closed-loop episode's metrics as a short table."""
    comm = metrics["communication_kb_per_s"]["mean_per_drone"]
    rows = [
        ("prediction error", f"{metrics['prediction_error']:.3f} m²"),
        ("tracking distance", f"{metrics['tracking_distance']:.2f} m²"),
        ("uncertainty (mean Tr P)", f"{metrics['uncertainty']:.3f}"),
        ("speed change", f"{metrics['speed_change']:.3f} m/s"),
        ("total cost (mean J)", f"{metrics['total_cost']:.2f}"),
        ("fused-track error", f"{metrics['tracking_error']:.3f} m²"),
        ("prediction coverage", f"{metrics['prediction_coverage']:.3f}"),
        ("gating rejections", f"{metrics['gating_rejections']}"),
        ("FL rounds", f"{len(metrics['fl_rounds'])}"),
        ("communication", f"{comm:.3f} KB/s per drone"),
        ("planner", f"{metrics['planner_ms_per_step']:.2f} ms/step"),
        (
            "speed",
            f"{metrics['sim_seconds']:.0f} s simulated in {metrics['wall_seconds']:.0f} s "
            f"({metrics['realtime_factor']:.1f}x real time)",
        ),
    ]
    head = (
        f"case {metrics['case']} | {metrics['method']} | seed {metrics['seed']} | "
        f"{metrics['environment']} | {metrics['detector']} detector"
    )
    if metrics.get("centralized_inputs"):
        head += f"\n(centralized inputs: {metrics['centralized_inputs']})"
    return head + "\n" + "\n".join(f"  {name:24s} {value}" for name, value in rows)


def comparison(results: list[dict]) -> str:
    """Episodes side by side (one column per method) with Table I's metrics."""
    rows = [
        ("prediction error (m²)", "prediction_error", "{:.3f}"),
        ("tracking distance (m²)", "tracking_distance", "{:.2f}"),
        ("uncertainty (Tr P)", "uncertainty", "{:.3f}"),
        ("speed change (m/s)", "speed_change", "{:.3f}"),
        ("total cost (J)", "total_cost", "{:.2f}"),
        ("fused-track error (m²)", "tracking_error", "{:.3f}"),
        ("FL rounds", "fl_rounds", None),
        ("wall time (s)", "wall_seconds", "{:.0f}"),
    ]
    first = results[0]
    lines = [
        f"case {first['case']}, {first['environment']}, seed {first['seed']}, "
        f"{first['sim_seconds']:.0f} s per episode",
        f"{'':24s}" + "".join(f"{r['method']:>14s}" for r in results),
    ]
    for label, key, fmt in rows:
        cells = [str(len(r[key])) if fmt is None else fmt.format(r[key]) for r in results]
        lines.append(f"{label:24s}" + "".join(f"{c:>14s}" for c in cells))
    comm = [r["communication_kb_per_s"]["mean_per_drone"] for r in results]
    lines.append(f"{'comm. (KB/s per drone)':24s}" + "".join(f"{c:>14.3f}" for c in comm))
    return "\n".join(lines)
