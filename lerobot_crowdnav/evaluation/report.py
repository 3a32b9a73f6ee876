"""Benchmark tables from ``metrics.json`` files (of ``lerobot-crowdnav-eval``), in markdown and CSV,
and the main job's report from typed inputs (:class:`ReportInputs`, built by the main job,
``lerobot_crowdnav/main/``). docs/data/ keeps these CSV tables; ``tables.py`` writes the docs'
tables from them.

A table row is one method; each cell is the mean over the metrics files of that method (one per
training seed) and, where there are several, ``mean +- std`` (population std). Rates are shown
in %, NT in s, PL and SD in m, as in docs/simulator.md.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from ..checkpoint_files import BEST_INFO, POLICY_CONFIG, WEIGHTS
from ..cli import machine_description
from ..measure.metrics import OUTCOMES, goal_in_wall_zone, outcome, wilson_interval
from ..measure.parameters import parameter_counts
from ..sim.config import SEED_SPLITS
from .generalization import (CROWD_LABELS, TRAINED, crowds_sentence, generalization_csv, generalization_markdown,
                             read_csv)

# column -> (metrics key, scale, digits, header)
COLUMNS = {
    "SR": ("sr", 100.0, 1, "SR (%)"),
    "SR95": ("sr", 100.0, 1, "SR 95 % CI"),  # Wilson interval over every seed's episodes
    "NT": ("nt", 1.0, 2, "NT (s)"),
    "PL": ("pl", 1.0, 2, "PL (m)"),
    "ITR": ("itr", 100.0, 2, "ITR (%)"),
    "SD": ("sd", 1.0, 2, "SD (m)"),
    "CR": ("cr", 100.0, 1, "CR (%)"),
    "TR": ("tr", 100.0, 1, "TR (%)"),
    "OOB": ("oob", 100.0, 1, "OOB (%)"),
}
RESULT_COLUMNS = ["SR", "SR95", "NT", "PL", "ITR", "SD"]


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
    """Formatted cell, mean and std (scaled units) of ``column`` for ``row``; for ``SR95`` the
    interval's bounds instead of mean and std (the episodes of all seeds pooled)."""
    key, scale, digits, _ = COLUMNS[column]
    if column == "SR95":
        counts = [(round(m[key] * m["n_episodes"]), m["n_episodes"]) for m in row.metrics if m.get("n_episodes")]
        if not counts or len(counts) < len(row.metrics):
            return "n/a", math.nan, math.nan
        lo, hi = (scale * v for v in wilson_interval(sum(k for k, _ in counts), sum(n for _, n in counts)))
        return f"[{lo:.{digits}f}, {hi:.{digits}f}]", lo, hi
    mean, std, n = _stats([m.get(key) for m in row.metrics])
    if n == 0:
        return "n/a", math.nan, math.nan
    mean, std = mean * scale, std * scale
    text = f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if n > 1 else "")  # a spread needs two defined values
    return text, mean, std


def markdown_table(rows: list[Row], columns: list[str] = RESULT_COLUMNS, first: str = "Method") -> str:
    lines = ["| " + " | ".join([first] + [COLUMNS[c][3] for c in columns]) + " |",
             "|" + "---|" * (len(columns) + 1)]
    for row in rows:
        lines.append("| " + " | ".join([row.label] + [cell(row, c)[0] for c in columns]) + " |")
    return "\n".join(lines)


def csv_table(rows: list[Row], columns: list[str] = RESULT_COLUMNS) -> str:
    """Machine-readable: for each column its mean and std (scaled units; SR95: the interval's
    bounds) and the seed count."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["method", "n_seeds"] + [f"{c}_{s}" for c in columns
                                             for s in (("low", "high") if c == "SR95" else ("mean", "std"))])
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


WALL_AUDIT_HEADERS = {"success": "SR", "human_collision": "human CR", "wall_at_start": "wall CR, at the start",
                      "wall_goal_in_zone": "wall CR, goal in the wall zone", "wall_other": "wall CR, other",
                      "timeout": "TR"}


def wall_audit(rows: list[Row]) -> tuple[str, str, str]:
    """Bounded benchmark: how each method's episodes end, in % of its episodes over all seeds,
    wall collisions split by cause (``metrics.outcome``; n/a for records without goals). Returns
    markdown, CSV and a sentence with the shares that no policy changes: episodes starting with
    the robot touching a wall, episodes whose goal lies in the wall zone."""
    md = ["| Method | episodes | " + " | ".join(f"{WALL_AUDIT_HEADERS[o]} (%)" for o in OUTCOMES) + " |",
          "|" + "---|" * (len(OUTCOMES) + 2)]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["method", "episodes", *OUTCOMES])
    facts = []
    for row in rows:
        episodes = [(e, m["env"]) for m in row.metrics for e in m.get("episodes", [])]
        kinds = Counter(outcome(e, env["arena_size"], env["robot_radius"]) for e, env in episodes)
        n = len(episodes)
        shares = {o: 100.0 * kinds[o] / n if n else math.nan for o in OUTCOMES}
        if kinds[None]:
            shares["wall_goal_in_zone"] = shares["wall_other"] = math.nan
        md.append(f"| {row.label} | {n} | " + " | ".join("n/a" if math.isnan(v) else f"{v:.1f}" for v in shares.values()) + " |")
        writer.writerow([row.label, n, *("" if math.isnan(v) else f"{v:.6g}" for v in shares.values())])
        if not facts and n and all(e.get("goal") is not None for e, _ in episodes):
            in_zone = sum(goal_in_wall_zone(e["goal"], env["arena_size"], env["robot_radius"]) for e, env in episodes)
            facts = [f"{shares['wall_at_start']:.1f} % of the episodes start with the robot touching a wall (a "
                     f"collision at the first step for every policy: at most {100 - shares['wall_at_start']:.1f} % "
                     f"success) and {100.0 * in_zone / n:.1f} % have their goal inside the wall zone (reaching it "
                     "takes a stop in a band narrower than the robot radius)."]
    return "\n".join(md), buf.getvalue(), " ".join(facts)


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


@dataclass(frozen=True)
class Budget:
    """The run's budget, shown next to the paper's."""

    run: str
    preset: str
    demos: int
    bc_steps: int
    bc_epochs: float
    bc_batch_size: int
    ft_env_steps: int
    seeds: list[int]
    test_episodes: int
    crowdnavpp_env_steps: int = 0
    ft2_env_steps: int = 0
    ft2_from: str = "last"


@dataclass(frozen=True)
class Stage:
    """One stage of the run: its name, the command a user would type and, when it ran in this
    invocation, its wall time (None: complete, skipped)."""

    name: str
    argv: list[str]
    wall_time_s: float | None = None


@dataclass(frozen=True)
class Evaluated:
    """One evaluation in a table row: its ``eval_dir`` (metrics.json, videos/) and the stages that
    made it. A built-in policy has no checkpoint; one trained by the run names its pretraining
    stage and, fine-tuned (checkpoint ``best``, with ``best.json`` beside it, or a numbered one the
    main job chose), its fine-tuning stage; a ``shipped`` model directory's card says how it was made."""

    name: str
    eval_dir: Path
    evaluate: Stage
    checkpoint: Path | None = None
    seed: int | None = None
    pretrain: Stage | None = None
    finetune: Stage | None = None
    shipped: bool = False


@dataclass(frozen=True)
class Method:
    """A table row: its label and its evaluations, one per training seed."""

    label: str
    evaluations: list[Evaluated]


@dataclass(frozen=True)
class TaskResults:
    """One benchmark's section: its rows and its figures (``figures_dir``: storyboard.png and
    multimodality.png, drawn by the ``figures`` stage, None without a PDPO policy; ``curves``:
    (caption, image) of the learning curves)."""

    task: str
    title: str
    short: str  # file names: tables/results_<short>.csv
    methods: list[Method]
    figures_dir: Path
    figures: Stage | None
    curves: list[tuple[str, Path]] = field(default_factory=list)
    bounded: bool = False  # walls: the wall audit; without (the original benchmark): the boundary audit
    missing_models: list[str] = field(default_factory=list)  # shipped models not found (rows left out)
    # The generalization table: crowd (other than the trained one, which is ``methods``) -> the
    # same rows evaluated under it, in the table's column order; empty: no table.
    crowds: dict[str, list[Method]] = field(default_factory=dict)


@dataclass(frozen=True)
class ReportInputs:
    """Everything the report shows; every path inside ``root`` except the shipped ``models``.
    ``budget`` is the training budget of a run that trains (None: it evaluates ``models``)."""

    root: Path
    budget: Budget | None
    tasks: list[TaskResults]
    stages: list[Stage]  # every stage of this invocation, in order (commands.json)
    wall_time_s: float
    test_episodes: int
    preset: str
    models: Path | None = None


def _budget_lines(b: Budget) -> list[str]:
    return [
        "## Budget", "",
        "| setting | this run | paper |", "|---|---|---|",
        f"| ORCA demonstrations per task (successful episodes) | {b.demos} | 3,000 |",
        f"| BC pretraining (lerobot-train, batch {b.bc_batch_size}) | "
        + (f"{b.bc_epochs:g} epochs" if b.bc_epochs > 0 else f"{b.bc_steps} steps") + " | 200 epochs |",
        f"| diffusion-PPO fine-tuning per policy | {b.ft_env_steps:,} env steps"
        + (f", then {b.ft2_env_steps:,} more from its {b.ft2_from} checkpoint (stage 2)" if b.ft2_env_steps else "")
        + " | about 12 M env steps |",
        *([f"| CrowdNav++ PPO from scratch per task | {b.crowdnavpp_env_steps:,} env steps | 10 M (CrowdNav++'s "
           "holonomic robot) |"] if b.crowdnavpp_env_steps else []),
        f"| training seeds | {', '.join(map(str, b.seeds))} | n/a |",
        f"| test episodes per method | {b.test_episodes} (seeds {SEED_SPLITS['test'][0]} ...) | 500 |",
        f"| simulator preset | `{b.preset}` | `paper` |", "",
        "Configuration: `main_config.json`; every stage's exact command: `commands.json` and *Stages* below.", "",
    ]


def _models_lines(inputs: ReportInputs) -> list[str]:
    return [
        "## Policies", "",
        f"The trained models in `{inputs.models}` (hub format), evaluated on {inputs.test_episodes} test episodes "
        f"(seeds {SEED_SPLITS['test'][0]} ...) of the `{inputs.preset}` preset. Each model's card (its README.md) "
        "gives the recipe, budget, seeds, wall time and the command that retrains it from scratch "
        "(docs/recipes.md); nothing is trained by this job.", "",
        "Configuration: `main_config.json`; every stage's exact command: `commands.json` and *Stages* below.", "",
    ]


def _provenance(ev: Evaluated, label: str, cmd) -> list[str]:
    notes = [f"- {label}, `{ev.name}`: `{cmd(ev.evaluate)}`"]
    if ev.shipped:
        notes.append(f"  - shipped model `{ev.checkpoint}`: its README.md names the recipe and the command that made it")
    elif ev.checkpoint is not None and ev.finetune is None:
        notes.append(f"  - pretrained by `{cmd(ev.pretrain)}` (checkpoint `last`)")
    elif ev.checkpoint is not None:  # fine-tuned after pretraining, or trained from scratch
        start = "pretrained" if ev.pretrain is not None else "initial"
        if ev.pretrain is not None:
            notes.append(f"  - pretrained by `{cmd(ev.pretrain)}`")
        made = f"  - {'fine-tuned' if ev.pretrain is not None else 'trained from scratch'} by `{cmd(ev.finetune)}`; "
        info = ev.checkpoint.parent / BEST_INFO
        if info.exists():  # PPO's `best`
            best = json.loads(info.read_text())
            notes.append(made + f"checkpoint `best` = {best['env_steps']:,} env steps (validation SR "
                         f"{100 * best['val/success_rate']:.0f} %)"
                         + (f": no validation beat the {start} weights, so they are the best" if best["env_steps"] == 0 else ""))
        else:  # a numbered checkpoint: the main job's choice on the validation seeds (--select_top)
            notes.append(made + f"checkpoint at {int(ev.checkpoint.parent.name):,} env steps, chosen on the validation "
                         "seeds (the run's select stage)")
    return notes


def _generalization_lines(t: TaskResults, rows: list[Row], tables: Path, test_episodes: int, seeds: int,
                          cmd) -> list[str]:
    """The task's generalization table (``evaluation/generalization.py``): every row of its
    results table (``rows``, the trained crowd) and the same rows under ``t.crowds``; written to
    ``tables/generalization_<short>.csv`` (removed when the run has no other crowd)."""
    path = tables / f"generalization_{t.short}.csv"
    if not t.crowds:
        path.unlink(missing_ok=True)  # an earlier invocation's, with crowds this one did not ask for
        return []
    results = {row.label: {TRAINED: row.metrics} for row in rows}
    notes = []
    for crowd, methods in t.crowds.items():
        for method in methods:
            results[method.label][crowd] = [load_metrics(ev.eval_dir / "metrics.json") for ev in method.evaluations]
            notes += [f"- {method.label}, `{ev.name}`, {CROWD_LABELS[crowd]}: `{cmd(ev.evaluate)}`"
                      for ev in method.evaluations]
    crowds = [TRAINED, *t.crowds]
    csv_text = generalization_csv(results, crowds)
    path.write_text(csv_text)
    return ["### Generalization: crowds it was not trained in", "",
            f"Every row above on the same {test_episodes} test seeds, in the crowd every policy was trained in and "
            f"in crowds none of them saw ({crowds_sentence(crowds)}; docs/simulator.md, \"Crowd models\"): SR with "
            "its 95 % Wilson interval, its change from the trained crowd (points), and how the other episodes "
            "ended, in % of the episodes" + (f" (means over {seeds} training seeds)" if seeds > 1 else "")
            + f". CSV: `tables/{path.name}`.", "",
            generalization_markdown(read_csv(csv_text), t.bounded), "",
            "<details><summary>Commands of the other crowds</summary>", "", *notes, "", "</details>", ""]


def write_report(inputs: ReportInputs) -> Path:
    """``<root>/report.md``, ``<root>/tables/*.csv`` and ``<root>/commands.json`` from the metrics
    files of a main-job run; every number with its command, config and seed."""
    b, root = inputs.budget, inputs.root
    tables = root / "tables"
    tables.mkdir(parents=True, exist_ok=True)
    cmd = lambda stage: " ".join(stage.argv)  # noqa: E731
    run = b.run if b is not None else root.name
    lines = [
        f"# lerobot-crowdnav main job: `{run}`", "",
        f"Machine: {machine_description()}. Wall time of the last invocation: {inputs.wall_time_s / 60:.1f} min "
        "(stages already complete were skipped; see *Stages* below).", "",
        *(_budget_lines(b) if b is not None else _models_lines(inputs)),
    ]
    counts: dict[str, dict[str, int]] = {}
    for t in inputs.tasks:
        rows = []
        notes = []
        for method in t.methods:
            rows.append(Row(method.label, [load_metrics(ev.eval_dir / "metrics.json") for ev in method.evaluations]))
            for ev in method.evaluations:
                notes += _provenance(ev, method.label, cmd)
                if ev.checkpoint is not None and (ev.finetune is not None or ev.shipped) and _is_pdpo(ev.checkpoint):
                    counts[f"{t.title}: {method.label}" + (f", seed {ev.seed}" if ev.seed is not None else "")] = \
                        parameter_counts(ev.checkpoint / WEIGHTS)
        seeds = len(b.seeds) if b is not None else 1
        (tables / f"results_{t.short}.csv").write_text(csv_table(rows))
        lines += [f"## {t.title}", "",
                  f"`{t.task}`, {inputs.test_episodes} test episodes, the same seeds for every method"
                  + (f"; mean ± std over {seeds} training seeds" if seeds > 1 else "") + ". "
                  f"CSV: `tables/results_{t.short}.csv`.", "", markdown_table(rows), ""]
        if t.missing_models:
            lines += ["Not shipped yet (no row): " + ", ".join(f"`{name}`" for name in t.missing_models) + ".", ""]
        lines += ["<details><summary>Provenance of each row</summary>", "", *notes, "", "</details>", ""]
        if t.bounded:
            md, csv_text, facts = wall_audit(rows)
            (tables / "wall_audit.csv").write_text(csv_text)
            lines += ["### Wall audit (Bounded)", "",
                      "How each method's episodes end (% of its test episodes), wall collisions split by cause: "
                      "at the first step (the robot starts touching a wall), later with the goal inside the wall "
                      f"zone, other. {facts} CSV: `tables/wall_audit.csv`.", "", md, ""]
        else:
            md, csv_text = boundary_audit(rows)
            (tables / "boundary_audit.csv").write_text(csv_text)
            lines += ["### Boundary audit (original benchmark)", "",
                      "Share of successful episodes in which the robot centre left the 12 x 12 m workspace "
                      "(the original benchmark has no walls). CSV: `tables/boundary_audit.csv`.", "", md, ""]
        lines += _generalization_lines(t, rows, tables, inputs.test_episodes, seeds, cmd)
    md, csv_text = parameter_table(counts)
    (tables / "parameters.csv").write_text(csv_text)
    lines += ["## Parameter counts", "", "Actor = crowd encoder + denoiser; critic = value head (the frozen "
              "pretrained copy that runs the first denoising steps of a fine-tuned policy is not counted). "
              "CSV: `tables/parameters.csv`.", "", md, "", "## Figures", ""]
    for t in inputs.tasks:
        fig = t.figures_dir
        lines += [f"### {t.title}", ""]
        if t.figures is not None:
            lines += [f"Action-chunk storyboard (`{cmd(t.figures)}`): robot-centred snapshots of one test "
                      "episode; dashed circle = sensing range, blue = humans and their predicted trajectories, "
                      "green = robot, the sampled chunk as a path ending in a red cross.", "",
                      f"![storyboard]({_rel(fig / 'storyboard.png', root)})", "",
                      "Multimodality: many chunks sampled for the same observation at several steps.", "",
                      f"![multimodality]({_rel(fig / 'multimodality.png', root)})", ""]
        for caption, image in t.curves:
            lines += [caption, "", f"![learning curve]({_rel(image, root)})", ""]
        lines += ["One test episode per method (the first test seed):", ""]
        for method in t.methods:
            gifs = sorted((method.evaluations[0].eval_dir / "videos").glob("*.gif"))
            if gifs:
                lines.append(f"- {method.label}: [{gifs[0].name}]({_rel(gifs[0], root)})")
        lines.append("")
    lines += ["## Stages", "", "| stage | command | wall time of this invocation |", "|---|---|---|"]
    for stage in inputs.stages:
        t = stage.wall_time_s
        lines.append(f"| {stage.name} | `{cmd(stage)}` | {'skipped (complete)' if t is None else f'{t:.0f} s'} |")
    lines += ["", "## Reproduce", "",
              "Rerunning the same `lerobot-crowdnav-main` command skips complete stages; with "
              "`--rerun_eval=true` it evaluates the " + ("shipped models" if b is None else "saved checkpoints")
              + " again and regenerates identical tables (evaluation is deterministic: fixed test seeds, policy "
              "sampling seed 0).", ""]
    (root / "commands.json").write_text(json.dumps({stage.name: stage.argv for stage in inputs.stages}, indent=2))
    report = root / "report.md"
    report.write_text("\n".join(lines))
    return report


def _is_pdpo(checkpoint: Path) -> bool:
    return json.loads((Path(checkpoint) / POLICY_CONFIG).read_text()).get("type") == "pdpo"
