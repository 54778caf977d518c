"""One figure per task of the policy table (``bench policies --plot DIR``): how each policy
trained and where its checkpoint was chosen.

Left, the training loss against the step (log scale), the chosen checkpoint marked. Right, the
success rate on the validation seeds at every checkpoint, and the test results (sync and
think-act) at the chosen one, each with its Wilson 95 % interval; the scripted expert's test
rate as a dashed line. Where the checkpoints' open-loop fits were measured, a third panel: each
checkpoint's mean action error on its training episodes (has the run learned its own data?).
Matplotlib's Agg backend: no display needed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from beavr_sim.bench.policies.table import LOOPS, POLICY_NAMES
from beavr_sim.scaling.stats import wilson_interval

_COLORS = {"act": "tab:blue", "diffusion": "tab:orange"}
_MARKERS = {"sync": "s", "async": "D"}


def file_name(task: str) -> str:
    """``policies_<task>.png``."""
    return f"policies_{task}.png"


def _rate_and_error(successes: int, episodes: int) -> tuple[float, list[float]]:
    """The rate and its Wilson interval as matplotlib's (below, above) error lengths."""
    rate = successes / episodes
    low, high = wilson_interval(successes, episodes)
    return rate, [rate - low, high - rate]


def task_figure(task: str, rows: Sequence[dict], path: Path) -> Path:
    """The figure of ``task``'s rows (as in the table's JSON) at ``path``."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    trained = [r for r in rows if r.get("validation")]
    # (validation made before every checkpoint's fit was measured has none)
    fits = any("fit" in v for r in trained for v in r["validation"])
    fig = Figure(figsize=(17.0 if fits else 11.5, 4.4), dpi=100, layout="constrained")
    ax_loss, ax_rate, *ax_fit = fig.subplots(1, 3 if fits else 2)
    last_step = 1
    seen: set[str] = set()
    for row in trained:
        policy = row["policy"]
        color = _COLORS.get(policy, "tab:green")
        name = POLICY_NAMES.get(policy, policy)
        step = row["checkpoint_step"]
        last_step = max(last_step, row["train_steps"])
        if policy not in seen:  # one policy has a row per loop; its curves once
            seen.add(policy)
            curve = row.get("loss") or []
            if curve:
                ax_loss.plot(
                    [c["step"] for c in curve], [c["loss"] for c in curve], color=color, label=name
                )
            ax_loss.axvline(step, color=color, ls=":", lw=1.0)
            validation = row["validation"]
            rates = [_rate_and_error(v["successes"], v["episodes"]) for v in validation]
            ax_rate.errorbar(
                [v["step"] for v in validation],
                [r for r, _ in rates],
                yerr=[[e[0] for _, e in rates], [e[1] for _, e in rates]],
                color=color,
                marker="o",
                ms=4,
                capsize=3,
                label=f"{name}, validation ({row['chosen_on'].removeprefix('validation ')})",
            )
            fitted = [v for v in validation if "fit" in v]
            if ax_fit and fitted:
                ax_fit[0].plot([v["step"] for v in fitted], [v["fit"] for v in fitted],
                               color=color, marker="o", ms=4, label=name)  # fmt: skip
                ax_fit[0].axvline(step, color=color, ls=":", lw=1.0)
        rate, error = _rate_and_error(row["successes"], row["episodes"])
        nudge = 0.012 * last_step * (1 if row["mode"] == "async" else -1)
        ax_rate.errorbar(
            [step + nudge],
            [rate],
            yerr=[[error[0]], [error[1]]],
            color=color,
            marker=_MARKERS.get(row["mode"], "^"),
            ms=7,
            mfc="white",
            capsize=3,
            ls="none",
            label=f"{name}, test {LOOPS.get(row['mode'], row['mode'])}: "
            f"{row['successes']}/{row['episodes']}",
        )
    for row in rows:
        if row.get("policy") == "human" and row.get("episodes"):
            rate = row["successes"] / row["episodes"]
            ax_rate.axhline(
                rate,
                color="0.4",
                ls="--",
                lw=1.0,
                label=f"human (scripted expert), test: {row['successes']}/{row['episodes']}",
            )
    ax_loss.set_yscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    ax_loss.yaxis.set_major_formatter(plain)
    ax_loss.yaxis.set_minor_formatter(plain)
    ax_loss.set_xlabel("training step")
    ax_loss.set_ylabel("training loss (LeRobot's, log scale)")
    ax_loss.set_title("training (dotted: the chosen checkpoint)", fontsize=10)
    ax_loss.grid(alpha=0.3, which="both")
    if ax_loss.get_legend_handles_labels()[0]:
        ax_loss.legend(fontsize=8)
    ax_rate.set_xlim(0, last_step * 1.06)
    ax_rate.set_ylim(-0.02, 1.05)
    ax_rate.set_xlabel("training step (checkpoint)")
    ax_rate.set_ylabel("success rate (Wilson 95 %)")
    ax_rate.set_title("success per checkpoint; test at the chosen one", fontsize=10)
    ax_rate.grid(alpha=0.3)
    ax_rate.legend(fontsize=7, loc="best")
    if ax_fit:
        episodes = next((r["fit"]["episodes"] for r in trained if r.get("fit")), [])
        ax_fit[0].set_xlim(0, last_step * 1.06)
        ax_fit[0].set_ylim(bottom=0)
        ax_fit[0].set_xlabel("training step (checkpoint)")
        ax_fit[0].set_ylabel("mean |action error| (rad)")
        ax_fit[0].set_title(
            "open-loop fit on training episodes " + ", ".join(map(str, episodes)), fontsize=10
        )
        ax_fit[0].grid(alpha=0.3)
        ax_fit[0].legend(fontsize=8)
    inputs = trained[0]["inputs"] if trained else ""
    demos = f", {trained[0]['demos']} demonstrations" if trained else ""
    fig.suptitle(f"{task}{demos}" + (f" ({inputs})" if inputs else ""))
    fig.savefig(path)
    return path


def write(result: dict, out: Path) -> list[Path]:
    """One figure per task of ``result`` (the table's JSON) into ``out`` (created)."""
    out.mkdir(parents=True, exist_ok=True)
    tasks = list(dict.fromkeys(r["task"] for r in result["rows"]))
    return [
        task_figure(task, [r for r in result["rows"] if r["task"] == task], out / file_name(task))
        for task in tasks
    ]
