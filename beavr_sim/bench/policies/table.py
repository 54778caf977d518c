"""The policy table as markdown and JSON: one row per (task, policy, evaluation loop), the
success count, the rate with its Wilson 95 % interval, the mean time to success, which
checkpoint (chosen on which validation seeds); rows that could not run say why."""

from __future__ import annotations

import json
from pathlib import Path

from beavr_sim.scaling.stats import wilson_interval

COLUMNS = (
    "task",
    "policy",
    "inputs",
    "loop",
    "successes",
    "success rate (Wilson 95 %)",
    "mean time to success (s)",
    "checkpoint",
)
#: How each evaluation loop reads in the table.
LOOPS = {"sync": "sync", "async": "think-act", "teleop": "teleop pipeline", "": ""}
POLICY_NAMES = {"act": "ACT", "diffusion": "Diffusion", "smolvla": "SmolVLA", "pi0": "pi0",
                "human": "human (scripted expert)"}  # fmt: skip


def rate_cell(successes: int, episodes: int) -> str:
    """``0.80 (0.58-0.92)``: the rate and its Wilson 95 % interval, two decimals."""
    low, high = wilson_interval(successes, episodes)
    return f"{successes / episodes:.2f} ({low:.2f}-{high:.2f})"


def _cells(row: dict) -> list[str]:
    policy = POLICY_NAMES.get(row["policy"], row["policy"])
    if row.get("note") and "episodes" not in row:
        return [row["task"], policy, row.get("inputs", ""), "", "-", row["note"], "-", "-"]
    time_s = row.get("mean_success_time_s")
    step = row.get("checkpoint_step")
    checkpoint = (
        f"step {step} of {row['train_steps']} (best on {row['chosen_on']})" if step else "-"
    )
    return [
        row["task"],
        policy,
        row["inputs"],
        LOOPS.get(row["mode"], row["mode"]),
        f"{row['successes']}/{row['episodes']}",
        rate_cell(row["successes"], row["episodes"]),
        "-" if time_s is None else f"{time_s:.1f}",
        checkpoint,
    ]


def _failures(rows: list[dict]) -> list[str]:
    """What the failed episodes lacked at their end, per row that has failures."""
    lines = []
    for row in rows:
        unmet = row.get("unmet_at_end")
        if not unmet:
            continue
        failed = row["episodes"] - row["successes"]
        loop = LOOPS.get(row["mode"], row["mode"])
        counts = ", ".join(f"{name} {n}" for name, n in unmet.items())
        lines.append(
            f"- {row['task']}, {POLICY_NAMES.get(row['policy'], row['policy'])}, {loop}: "
            f"of {failed} failed, ended without {counts}"
        )
    if lines:
        lines = ["Failed episodes, the checker's conditions unmet at their end:", "", *lines, ""]
    return lines


def _fits(rows: list[dict]) -> list[str]:
    """Each trained policy's open-loop fit at its chosen checkpoint, and at every checkpoint
    where they were measured (once per policy)."""
    lines, seen = [], set()
    for row in rows:
        fit = row.get("fit")  # (absent from tables made before it was measured)
        if not fit or (row["task"], row["policy"]) in seen:
            continue
        seen.add((row["task"], row["policy"]))
        lines.append(
            f"- {row['task']}, {POLICY_NAMES.get(row['policy'], row['policy'])} (step "
            f"{row['checkpoint_step']}): mean |action error| {fit['mean_abs']:.4f}, "
            f"{fit['relative']:.2f} of the recorded actions' spread"
        )
        # (validation entries made before every checkpoint's fit was measured have none)
        each = [v for v in row.get("validation", []) if "fit" in v]
        if len(each) > 1:
            lines[-1] += "; at each checkpoint: " + ", ".join(
                f"{v['step']} {v['fit']:.4f}" for v in each
            )
    if lines:
        first = next(r["fit"] for r in rows if r.get("fit"))
        episodes = ", ".join(map(str, first["episodes"]))
        lines = [
            f"Open-loop fit: each policy's actions on training episodes {episodes}, fed their "
            "recorded observations, against the recorded actions (`python -m "
            "beavr_sim.eval.fit`; 0 is exact, about 1 no better than a constant):",
            "",
            *lines,
            "",
        ]
    return lines


def markdown(result: dict, command: str = "") -> str:
    """The table with its protocol, the command and the budget above it."""
    protocol = result["protocol"]
    budget = result["budget"]
    lines = [
        "# Policy table (`python -m beavr_sim.bench policies`)",
        "",
        f"Embodiment {protocol['embodiment']}; demonstrations from seeds "
        f"{protocol['train_seeds']}; checkpoints chosen on seeds {protocol['validation_seeds']}; "
        f"tested on seeds {protocol['test_seeds']}; device {result['device']}.",
    ]
    if command:
        lines += ["", f"    {command}"]
    lines += [
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
        *("| " + " | ".join(_cells(row)) + " |" for row in result["rows"]),
        "",
        *_failures(result["rows"]),
        *_fits(result["rows"]),
        f"Budget: {budget['wall_s']:.1f} s wall, {budget['cpu_s']:.1f} s CPU over all stages "
        f"({budget['stages_cached']} of them cached from an earlier run)"
        + "".join(
            f"; {stage} {t['wall_s']:.1f} s wall / {t['cpu_s']:.1f} s CPU"
            for stage, t in budget["by_stage"].items()
        )
        + ".",
    ]
    return "\n".join(lines) + "\n"


def write(result: dict, out: Path, command: str = "") -> tuple[Path, Path]:
    """``out/table.md`` and ``out/table.json``."""
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "table.md", out / "table.json"
    md.write_text(markdown(result, command))
    js.write_text(json.dumps({**result, "command": command}, indent=2))
    return md, js
