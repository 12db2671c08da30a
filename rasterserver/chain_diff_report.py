"""A chain comparison (:mod:`rasterserver.chain_diff`) written out: JSON, PNG plots, text.

Files written into one folder:

``diff.json``
    The chains, the summary (counts, distributions, worst cases by uid) and every
    acquisition's measures.
``displacement.png``
    Per changed acquisition: the 95th percentile of ``|z_B - z_A|`` and the signed mean
    (the bias), as histograms.
``renumbering.png``
    Lines renumbered per changed acquisition (histogram) and the number shifts B - A.
``coverage.png``
    Surface area gained and lost per changed acquisition (cm²).
``parameters.png``
    Each clinical parameter's shift B - A over the changed acquisitions (box plots).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rasterserver.chain_diff import ChainDiff

__all__ = ["summary_lines", "write_report"]


def write_report(diff: ChainDiff, folder: Path) -> list[Path]:
    """Write ``diff.json`` and the plots into ``folder`` (created); return the files."""
    import matplotlib

    matplotlib.use("Agg")  # no display: a server or a CI job
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = [folder / "diff.json"]
    written[0].write_text(diff.to_json() + "\n", encoding="utf-8")
    changed = [a for a in diff.acquisitions if a.status == "changed"]
    title = f"A: {diff.chain_a}\nB: {diff.chain_b}  ({len(changed)} changed)"

    def save(fig: Any, name: str) -> None:
        fig.suptitle(title, fontsize=8)
        fig.tight_layout()
        fig.savefig(folder / name, dpi=100)
        plt.close(fig)
        written.append(folder / name)

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.8))
    p95 = [a.displacement["p95_abs"] for a in changed if a.displacement]
    mean = [a.displacement["mean"] for a in changed if a.displacement]
    left.hist(p95 or [0.0], bins=30, color="tab:blue")
    left.set_xlabel("95th percentile |z_B - z_A| (mm)")
    left.set_ylabel("acquisitions")
    right.hist(mean or [0.0], bins=30, color="tab:orange")
    right.set_xlabel("mean z_B - z_A (mm)")
    save(fig, "displacement.png")

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.8))
    lines = [a.numbering["lines_renumbered"] for a in changed if a.numbering]
    left.hist(lines or [0], bins=max(1, min(30, max(lines or [0]) + 1)), color="tab:red")
    left.set_xlabel("lines renumbered")
    left.set_ylabel("acquisitions")
    shifts: dict[int, int] = {}
    for a in changed:
        for shift, count in (a.numbering or {}).get("shifts", {}).items():
            shifts[int(shift)] = shifts.get(int(shift), 0) + count
    keys = sorted(shifts)
    right.bar([str(k) for k in keys], [shifts[k] for k in keys], color="tab:red")
    right.set_xlabel("number shift B - A")
    right.set_ylabel("lines")
    save(fig, "renumbering.png")

    fig, ax = plt.subplots(figsize=(5, 4))
    gained = [a.coverage["gained_cm2"] for a in changed if a.coverage]
    lost = [a.coverage["lost_cm2"] for a in changed if a.coverage]
    ax.scatter(lost, gained, s=12)
    ax.set_xlabel("coverage lost (cm²)")
    ax.set_ylabel("coverage gained (cm²)")
    save(fig, "coverage.png")

    names = sorted({n for a in changed for n, p in a.parameters.items()
                    if p["shift"] is not None})
    fig, ax = plt.subplots(figsize=(max(5, 0.6 * len(names) + 2), 4))
    if names:
        data = [[a.parameters[n]["shift"] for a in changed
                 if n in a.parameters and a.parameters[n]["shift"] is not None] for n in names]
        ax.boxplot(data)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=60, ha="right", fontsize=7)
        ax.axhline(0.0, color="grey", lw=0.5)
    ax.set_ylabel("shift B - A (parameter's unit)")
    save(fig, "parameters.png")
    return written


def summary_lines(diff: ChainDiff, *, worst: int = 5) -> list[str]:
    """A short text report: counts, displacement, renumbering, coverage, worst uids."""
    summary = diff.summary()

    def dist(d: dict[str, Any], unit: str = "") -> str:
        if not d["n"]:
            return "-"
        return (f"median {d['median']:.3g}{unit}, p95 {d['p95']:.3g}{unit}, "
                f"max {d['max']:.3g}{unit} (n={d['n']})")

    lines = [
        f"A: {diff.chain_a}",
        f"B: {diff.chain_b}",
        f"{summary['acquisitions']} acquisition(s): {summary['changed']} changed, "
        f"{summary['unchanged']} unchanged, {summary['missing-a']} without results of A, "
        f"{summary['missing-b']} without results of B",
    ]
    if summary["changed"]:
        first = ", ".join(f"{k} {v}" for k, v in summary["first_changed_stage"].items())
        lines += [
            f"first stage changed: {first}",
            f"displacement p95 per acquisition: {dist(summary['displacement_p95_mm'], ' mm')}",
            f"displacement mean (bias): {dist(summary['displacement_mean_mm'], ' mm')}",
            f"lines renumbered: {summary['acquisitions_renumbered']} acquisition(s); "
            f"{dist(summary['lines_renumbered'])}",
            f"coverage gained: {dist(summary['coverage_gained_cm2'], ' cm²')}",
            f"coverage lost: {dist(summary['coverage_lost_cm2'], ' cm²')}",
        ]
        for name, d in summary["parameter_shifts"].items():
            if d["n"]:
                top = summary["worst"].get(f"parameter {name}") or [{"uid": "-"}]
                lines.append(f"shift of {name}: median {d['median']:+.3g}, "
                             f"range {d['min']:+.3g} .. {d['max']:+.3g} (n={d['n']}); "
                             f"largest {top[0]['uid']}")
        for measure, cases in summary["worst"].items():
            if cases and not measure.startswith("parameter "):
                shown = ", ".join(f"{c['uid']} ({c['value']:g})" for c in cases[:worst])
                lines.append(f"worst {measure}: {shown}")
    return lines
