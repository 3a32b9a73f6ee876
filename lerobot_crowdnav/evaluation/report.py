"""Benchmark tables from ``metrics.json`` files (of ``lerobot-crowdnav-eval``), in markdown and CSV.

A table row is one method; each cell is the mean over the metrics files of that method (one per
training seed) and, where there are several, ``mean +- std`` (population std). Rates are shown
in %, NT in s, PL and SD in m, as in docs/simulator.md.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from ..sim.config import SEED_SPLITS

# column -> (metrics key, scale, digits, header)
COLUMNS = {
    "SR": ("sr", 100.0, 1, "SR (%)"),
    "NT": ("nt", 1.0, 2, "NT (s)"),
    "PL": ("pl", 1.0, 2, "PL (m)"),
    "ITR": ("itr", 100.0, 2, "ITR (%)"),
    "SD": ("sd", 1.0, 2, "SD (m)"),
    "CR": ("cr", 100.0, 1, "CR (%)"),
    "TR": ("tr", 100.0, 1, "TR (%)"),
    "OOB": ("oob", 100.0, 1, "OOB (%)"),
}
RESULT_COLUMNS = ["SR", "NT", "PL", "ITR", "SD"]


@dataclass
class Row:
    """One method of a table: its label and the metrics of each training seed."""

    label: str
    metrics: list[dict] = field(default_factory=list)
    note: str = ""  # provenance shown in the report (command, config, seeds)


def load_metrics(path: str | Path) -> dict:
    return json.loads(Path(path).read_text())


def _stats(values: list[float | None]) -> tuple[float, float, int]:
    """Mean, population std and count of the defined values (None/NaN = undefined)."""
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not vals:
        return math.nan, math.nan, 0
    mean = sum(vals) / len(vals)
    return mean, math.sqrt(sum((v - mean) ** 2 for v in vals) / len(vals)), len(vals)


def cell(row: Row, column: str) -> tuple[str, float, float]:
    """Formatted cell, mean and std (scaled units) of ``column`` for ``row``."""
    key, scale, digits, _ = COLUMNS[column]
    mean, std, n = _stats([m.get(key) for m in row.metrics])
    if n == 0:
        return "n/a", math.nan, math.nan
    mean, std = mean * scale, std * scale
    text = f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if len(row.metrics) > 1 else "")
    return text, mean, std


def markdown_table(rows: list[Row], columns: list[str] = RESULT_COLUMNS, first: str = "Method") -> str:
    lines = ["| " + " | ".join([first] + [COLUMNS[c][3] for c in columns]) + " |",
             "|" + "---|" * (len(columns) + 1)]
    for row in rows:
        lines.append("| " + " | ".join([row.label] + [cell(row, c)[0] for c in columns]) + " |")
    return "\n".join(lines)


def csv_table(rows: list[Row], columns: list[str] = RESULT_COLUMNS) -> str:
    """Machine-readable: for each column its mean and std (scaled units) and the seed count."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["method", "n_seeds"] + [f"{c}_{s}" for c in columns for s in ("mean", "std")])
    for row in rows:
        values = []
        for c in columns:
            _, mean, std = cell(row, c)
            values += ["" if math.isnan(mean) else f"{mean:.6g}", "" if math.isnan(std) else f"{std:.6g}"]
        writer.writerow([row.label, len(row.metrics)] + values)
    return buf.getvalue()


def boundary_audit(rows: list[Row]) -> tuple[str, str]:
    """Original benchmark: share of successful episodes whose robot left the 12 x 12 m workspace
    (markdown, CSV), counted over all seeds' episode records."""
    md = ["| Method | successful episodes | left the workspace | share (%) |", "|---|---|---|---|"]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["method", "successes", "out_of_bounds", "share_percent"])
    for row in rows:
        episodes = [e for m in row.metrics for e in m.get("episodes", []) if e["event"] == "success"]
        oob = sum(bool(e["out_of_bounds"]) for e in episodes)
        share = 100.0 * oob / len(episodes) if episodes else math.nan
        md.append(f"| {row.label} | {len(episodes)} | {oob} | {'n/a' if math.isnan(share) else f'{share:.1f}'} |")
        writer.writerow([row.label, len(episodes), oob, "" if math.isnan(share) else f"{share:.6g}"])
    return "\n".join(md), buf.getvalue()


def parameter_table(counts: dict[str, dict[str, int]]) -> tuple[str, str]:
    """Parameter counts (markdown, CSV) of each learned policy: actor (encoder + denoiser) and
    critic (value head); the paper reports 0.848 M and 0.201 M."""
    md = ["| Policy | actor (M) | critic (M) |", "|---|---|---|"]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["policy", "actor", "critic"])
    for name, c in counts.items():
        md.append(f"| {name} | {c['actor'] / 1e6:.3f} | {c['critic'] / 1e6:.3f} |")
        writer.writerow([name, c["actor"], c["critic"]])
    md.append("| paper (PDPO) | 0.848 | 0.201 |")
    return "\n".join(md), buf.getvalue()


def _rel(path: Path, root: Path) -> str:
    return str(Path(path).relative_to(root))


def write_report(pipeline, wall_time_s: float) -> Path:
    """``<run>/report.md`` and ``<run>/tables/*.csv`` from the metrics files of a pipeline run
    (:class:`lerobot_crowdnav.pipeline.Pipeline`); every number with its command, config and seed."""
    from .eval import machine_description
    from ..data.hub import parameter_counts
    from ..pipeline import SHORT, TITLE

    cfg, root = pipeline.cfg, pipeline.root
    tables = root / "tables"
    tables.mkdir(parents=True, exist_ok=True)
    cmd = lambda name: " ".join(pipeline.commands[name])  # noqa: E731
    lines = [
        f"# lerobot-crowdnav main job: `{cfg.run}`", "",
        f"Machine: {machine_description()}. Wall time of the last invocation: {wall_time_s / 60:.1f} min "
        "(stages already complete were skipped; see *Stages* below).", "",
        "## Budget", "",
        "| setting | this run | paper |", "|---|---|---|",
        f"| ORCA demonstrations per task (successful episodes) | {cfg.demos} | 3,000 |",
        f"| BC pretraining (lerobot-train, batch {cfg.bc_batch_size}) | "
        + (f"{cfg.bc_epochs:g} epochs" if cfg.bc_epochs > 0 else f"{cfg.bc_steps} steps") + " | 200 epochs |",
        f"| diffusion-PPO fine-tuning per policy | {cfg.ft_env_steps:,} env steps | about 12 M env steps |",
        f"| training seeds | {', '.join(map(str, cfg.seeds))} | n/a |",
        f"| test episodes per method | {cfg.test_episodes} (seeds {SEED_SPLITS['test'][0]} ...) | 500 |",
        f"| simulator preset | `{cfg.preset}` | `paper` |", "",
        "Configuration: `main_config.json`; every stage's exact command: `commands.json` and *Stages* below.", "",
    ]
    counts: dict[str, dict[str, int]] = {}
    for task in cfg.tasks:
        short = SHORT[task]
        rows = []
        notes = []
        for label, evals in pipeline.methods(task):
            rows.append(Row(label, [load_metrics(pipeline.eval_dir(task, ev.name) / "metrics.json") for ev in evals]))
            for ev in evals:
                notes.append(f"- {label}, `{ev.name}`: `{cmd(f'eval {short} {ev.name}')}`")
                if ev.policy is None:
                    continue
                trained = f"H={ev.horizon} seed={ev.seed}"
                if not ev.finetuned:
                    notes.append(f"  - pretrained by `{cmd(f'pretrain {short} {trained}')}` (checkpoint `last`)")
                    continue
                best = json.loads((ev.policy.parent / "best.json").read_text())
                notes.append(f"  - pretrained by `{cmd(f'pretrain {short} {trained}')}`")
                notes.append(f"  - fine-tuned by `{cmd(f'finetune {short} {trained}')}`; checkpoint `best` "
                             f"= {best['env_steps']:,} env steps (validation SR {100 * best['val/success_rate']:.0f} %)"
                             + (": no validation beat the pretrained weights, so they are the best" if best["env_steps"] == 0 else ""))
                counts[f"{TITLE[task]}: {label}, seed {ev.seed}"] = parameter_counts(ev.policy / "model.safetensors")
        (tables / f"results_{short}.csv").write_text(csv_table(rows))
        lines += [f"## {TITLE[task]}", "",
                  f"`{task}`, {cfg.test_episodes} test episodes, the same seeds for every method"
                  + (f"; mean ± std over {len(cfg.seeds)} training seeds" if len(cfg.seeds) > 1 else "") + ". "
                  f"CSV: `tables/results_{short}.csv`.", "", markdown_table(rows), "",
                  "<details><summary>Provenance of each row</summary>", "", *notes, "", "</details>", ""]
        if task == "CrowdNav-v0":
            md, csv_text = boundary_audit(rows)
            (tables / "boundary_audit.csv").write_text(csv_text)
            lines += ["### Boundary audit (original benchmark)", "",
                      "Share of successful episodes in which the robot centre left the 12 x 12 m workspace "
                      "(the original benchmark has no walls). CSV: `tables/boundary_audit.csv`.", "", md, ""]
    md, csv_text = parameter_table(counts)
    (tables / "parameters.csv").write_text(csv_text)
    lines += ["## Parameter counts", "", "Actor = crowd encoder + denoiser; critic = value head (the frozen "
              "pretrained copy that runs the first denoising steps of a fine-tuned policy is not counted). "
              "CSV: `tables/parameters.csv`.", "", md, "", "## Figures", ""]
    for task in cfg.tasks:
        short = SHORT[task]
        fig = root / "figures" / short
        lines += [f"### {TITLE[task]}", "",
                  f"Action-chunk storyboard (`{cmd(f'figures {short}')}`): robot-centred snapshots of one test "
                  "episode; dashed circle = sensing range, blue = humans and their predicted trajectories, "
                  "green = robot, the sampled chunk as a path ending in a red cross.", "",
                  f"![storyboard]({_rel(fig / 'storyboard.png', root)})", "",
                  "Multimodality: many chunks sampled for the same observation at several steps.", "",
                  f"![multimodality]({_rel(fig / 'multimodality.png', root)})", "",
                  "Fine-tuning: training success rate and average episode reward against environment steps "
                  "(lines: training episodes, smoothed; markers: deterministic validation).", "",
                  f"![fine-tuning curves]({_rel(fig / 'finetune_curves.png', root)})", "",
                  "One test episode per method (the first test seed):", ""]
        for label, evals in pipeline.methods(task):
            gifs = sorted((pipeline.eval_dir(task, evals[0].name) / "videos").glob("*.gif"))
            if gifs:
                lines.append(f"- {label}: [{gifs[0].name}]({_rel(gifs[0], root)})")
        lines.append("")
    lines += ["## Stages", "", "| stage | command | wall time of this invocation |", "|---|---|---|"]
    for name, argv in pipeline.commands.items():
        t = pipeline.timings.get(name)
        lines.append(f"| {name} | `{' '.join(argv)}` | {'skipped (complete)' if t is None else f'{t:.0f} s'} |")
    lines += ["", "## Reproduce", "",
              "Rerunning the same `lerobot-crowdnav-main` command skips complete stages; with "
              "`--rerun_eval=true` it evaluates the saved checkpoints again and regenerates identical "
              "tables (evaluation is deterministic: fixed test seeds, policy sampling seed 0).", ""]
    (root / "commands.json").write_text(json.dumps(pipeline.commands, indent=2))
    report = root / "report.md"
    report.write_text("\n".join(lines))
    return report

