"""The simulator's baseline tables in one command: ``lerobot-crowdnav-baselines``.

    lerobot-crowdnav-baselines                       # every row, 500 test episodes each
    lerobot-crowdnav-baselines --only='[bounded_paper]' --n_episodes=100
    lerobot-crowdnav-baselines --only='[generalization]'   # the crowd-generalization table

Runs ``lerobot-crowdnav-eval`` for each row of :data:`TABLES` (both ORCA robots, wall-unaware and
wall-aware in Bounded, straight; both variants, both presets, randomized attributes on and off,
and CrowdNav++'s ORCA-baseline configuration) on the same test seeds, one ``metrics.json`` per
row under ``<output_dir>/<table>/<row>/``, then writes ``<output_dir>/baselines.md`` (the tables
with wall times, as in docs/simulator.md, and each Bounded table's wall audit). Rerunning skips
rows whose metrics exist for the same episode count, so an interrupted run resumes.

``generalization`` (only when named in ``--only``) is the crowd-generalization table: the ORCA and
straight baselines and every trained model found in ``--models`` (the shipped ones by default),
on each benchmark, under the four crowd settings of ``sim.config.CROWDS`` (the crowd the policies
were trained in; reactive ORCA humans; social-force humans; both), with the outcome split
(success, human and wall collisions, timeouts): the table of ``evaluation/generalization.py``,
the same as in the main job's report. One ``metrics.json`` per row under
``<output_dir>/generalization/<task>/<crowd>/<row>/``; the tables go to
``<output_dir>/generalization.md`` (and into ``baselines.md`` when run with the other tables),
each also as ``<output_dir>/generalization_<task>.csv``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..checkpoint_files import WEIGHTS
from ..cli import run_cli
from ..measure.metrics import markdown_header, markdown_row
from ..sim.config import CROWDS, TASKS, CrowdSimConfig
from .eval import (EvalConfig, EvalSettings, OrcaPolicyConfig, PretrainedPolicyConfig, RobotPolicyConfig,
                   StraightPolicyConfig, evaluate, saved_result)
from .generalization import (CROWD_LABELS, check_crowds, crowd_env, crowds_sentence, generalization_csv,
                             generalization_markdown, read_csv)
from .report import Row, wall_audit

LA, CS = dict(orca_robot="look_ahead"), dict(orca_robot="current_state")
WALLS = dict(orca_robot_wall_aware=True)
ORCA_ROWS = {"ORCA look-ahead": LA, "ORCA current-state": CS}
BOUNDED_ROWS = {**ORCA_ROWS, "ORCA look-ahead, wall-aware": {**LA, **WALLS},
                "ORCA current-state, wall-aware": {**CS, **WALLS}}

# table key -> (title, env fields shared by the rows, {row name: env overrides (None: straight)})
TABLES: dict[str, tuple[str, dict, dict[str, dict | None]]] = {
    "bounded_paper": ("Bounded CrowdNav, `paper` preset (the paper's main table)",
                      dict(task="BoundedCrowdNav-v0", preset="paper"), {**BOUNDED_ROWS, "straight": None}),
    "original_paper": ("original CrowdNav, `paper` preset", dict(task="CrowdNav-v0", preset="paper"),
                       {**ORCA_ROWS, "straight": None}),
    "bounded_crowdnavpp": ("Bounded CrowdNav, `crowdnavpp` preset (randomized attributes, "
                           "neighbour-distance quirk, persistent ORCA simulators)",
                           dict(task="BoundedCrowdNav-v0", preset="crowdnavpp"), {**BOUNDED_ROWS, "straight": None}),
    "original_crowdnavpp": ("original CrowdNav, `crowdnavpp` preset (randomized attributes, "
                            "neighbour-distance quirk, persistent ORCA simulators)",
                            dict(task="CrowdNav-v0", preset="crowdnavpp"), {**ORCA_ROWS, "straight": None}),
    "bounded_crowdnavpp_fixed": ("Bounded CrowdNav, `crowdnavpp`, `randomize_attributes=false`",
                                 dict(task="BoundedCrowdNav-v0", preset="crowdnavpp", randomize_attributes=False),
                                 {**ORCA_ROWS, "straight": None}),
    "original_crowdnavpp_fixed": ("original CrowdNav, `crowdnavpp`, `randomize_attributes=false`",
                                  dict(task="CrowdNav-v0", preset="crowdnavpp", randomize_attributes=False),
                                  {**ORCA_ROWS, "straight": None}),
    "crowdnavpp_orca_baseline": ("CrowdNav++'s ORCA-baseline configuration (original, `crowdnavpp`, "
                                 "`randomize_attributes=false`, `goal_change_prob=0`; "
                                 "configs/eval/crowdnavpp_orca_baseline.yaml)",
                                 dict(task="CrowdNav-v0", preset="crowdnavpp", randomize_attributes=False,
                                      goal_change_prob=0.0), ORCA_ROWS),
}


GENERALIZATION = "generalization"
# The trained models shipped in the repository (hub format), named as the main job finds them
# (lerobot_crowdnav/main/sources.py, shipped_names): model directory (per benchmark) -> row label.
SHIPPED_MODELS = Path(__file__).resolve().parents[2] / "models" / "lerobot-crowdnav"
SHORT = {"BoundedCrowdNav-v0": "bounded", "CrowdNav-v0": "original"}
MODEL_ROWS = {"pdpo_{short}_h1": "PDPO w/o action chunk (H = 1, fine-tuned)",
              "pdpo_{short}_h5": "PDPO (H = 5, fine-tuned)", "crowdnavpp_{short}": "CrowdNav++ (Const. Vel.)"}
GENERALIZATION_BASELINES = {"ORCA look-ahead": LA, "ORCA current-state": CS, "straight": None}


@dataclass
class BaselinesConfig:
    # Test episodes per row (the paper: 500).
    n_episodes: int = 500
    # Environments stepped together per evaluation: the main job's 256 by default, so that a trained
    # model's rows match its report (its sampling noise is drawn per batch).
    batch_size: int = 256
    # Table keys to run (default: all but generalization): bounded_paper, original_paper,
    # bounded_crowdnavpp, original_crowdnavpp, bounded_crowdnavpp_fixed, original_crowdnavpp_fixed,
    # crowdnavpp_orca_baseline; generalization: the baselines and trained models under the four
    # crowd settings (reactive and social-force humans), only when named.
    only: list[str] = field(default_factory=list)
    # generalization: the directory of trained models (hub format, named pdpo_<bounded|original>_h<H>
    # and crowdnavpp_<bounded|original>) whose rows join the baselines'; null: baselines only.
    models: Path | None = SHIPPED_MODELS
    # generalization: the benchmarks (CrowdNav-v0, BoundedCrowdNav-v0).
    generalization_tasks: list[str] = field(default_factory=lambda: ["BoundedCrowdNav-v0", "CrowdNav-v0"])
    # generalization: the simulator preset (paper | crowdnavpp).
    generalization_preset: str = "paper"
    # generalization: the crowd settings (keys of sim.config.CROWDS; the first is the reference
    # of the "SR change" column: the crowd the policies were trained in).
    crowds: list[str] = field(default_factory=lambda: list(CROWDS))
    # generalization: torch device of the trained policies.
    device: str = "cpu"
    # Where the per-row metrics.json files and baselines.md go.
    output_dir: Path = Path("outputs/baselines")


def _slug(name: str) -> str:
    return name.lower().replace(",", "").replace(" ", "_").replace("-", "_")


def run_row(cfg: BaselinesConfig, env: dict, overrides: dict | None, out: Path,
            policy: RobotPolicyConfig | None = None) -> dict:
    """One row's metrics, from its metrics.json when that answers the same evaluation
    (``eval.saved_result``; for a trained model, also newer than its weights). ``policy`` defaults
    to the ORCA robot, or straight when ``overrides`` is None."""
    if policy is None:
        policy = StraightPolicyConfig() if overrides is None else OrcaPolicyConfig()
    eval_cfg = EvalConfig(env=CrowdSimConfig(**env, **(overrides or {})), policy=policy,
                          eval=EvalSettings(n_episodes=cfg.n_episodes, split="test", batch_size=cfg.batch_size),
                          output_dir=out, overwrite=True)
    result = saved_result(eval_cfg)
    if result is not None:
        weights = Path(policy.path) / WEIGHTS if isinstance(policy, PretrainedPolicyConfig) else None
        if weights is None or not weights.exists() or (out / "metrics.json").stat().st_mtime >= weights.stat().st_mtime:
            return result
    return evaluate(eval_cfg)


def trained_models(models: Path | None, task: str) -> dict[str, Path]:
    """Row label -> model directory, for the trained models of ``task`` present in ``models``."""
    if models is None:
        return {}
    found = {}
    for name, label in MODEL_ROWS.items():
        path = Path(models) / name.format(short=SHORT[task])
        if (path / WEIGHTS).exists():
            found[label] = path
    return found


def generalization(cfg: BaselinesConfig, machines: set[str]) -> str:
    """The crowd-generalization tables (markdown; ``evaluation/generalization.py``): per
    benchmark, every policy's SR under each crowd with its change from the first (trained) crowd
    and the outcome split; each also as ``<output_dir>/generalization_<task>.csv``."""
    sections = []
    for task in cfg.generalization_tasks:
        bounded = task == "BoundedCrowdNav-v0"
        env = dict(task=task, preset=cfg.generalization_preset)
        # row label -> (env overrides, policy, output folder name)
        policies: dict[str, tuple[dict | None, RobotPolicyConfig | None, str]] = {
            name: (overrides, None, _slug(name)) for name, overrides in GENERALIZATION_BASELINES.items()}
        for label, path in trained_models(cfg.models, task).items():
            policies[label] = ({}, PretrainedPolicyConfig(path=path, device=cfg.device), path.name)
        results: dict[str, dict[str, list[dict]]] = {}
        for name, (overrides, policy, slug) in policies.items():
            for crowd in cfg.crowds:
                out = cfg.output_dir / GENERALIZATION / SHORT[task] / crowd / slug
                result = run_row(cfg, {**env, **crowd_env(crowd)}, overrides, out, policy)
                machines.add(result["machine"])
                results.setdefault(name, {})[crowd] = [result]
        text = generalization_csv(results, cfg.crowds)
        path = cfg.output_dir / f"{GENERALIZATION}_{SHORT[task]}.csv"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        title = f"{'Bounded' if bounded else 'original'} CrowdNav, `{cfg.generalization_preset}` preset"
        sections.append(f"### Crowd generalization: {title}\n\n"
                        f"{generalization_markdown(read_csv(text), bounded, 'policy')}\n\nCSV: `{path.name}`.\n")
    return "\n".join([f"Every policy on the first {cfg.n_episodes} test seeds in the crowd the trained policies were "
                      f"trained in and in crowds they never saw ({crowds_sentence(cfg.crowds)}; docs/simulator.md, "
                      f"\"Crowd models\"). SR change: in points, against the {CROWD_LABELS[cfg.crowds[0]]} crowd; "
                      "collision and timeout rates in % of the episodes.\n", *sections])


def baselines(cfg: BaselinesConfig) -> str:
    unknown = set(cfg.only) - set(TABLES) - {GENERALIZATION}
    if unknown:
        raise ValueError(f"unknown tables {sorted(unknown)}; choose from {', '.join([*TABLES, GENERALIZATION])}")
    check_crowds(cfg.crowds)
    bad_tasks = [t for t in cfg.generalization_tasks if t not in TASKS]
    if bad_tasks:
        raise ValueError(f"unknown generalization_tasks {bad_tasks}; choose from {', '.join(TASKS)}")
    sections, machines = [], set()
    for key, (title, env, rows) in TABLES.items():
        if cfg.only and key not in cfg.only:
            continue
        bounded = env["task"] == "BoundedCrowdNav-v0"
        header, sep = markdown_header(bounded, "policy").split("\n")
        extra = ["human CR (%)", "wall CR (%)", "TR (%)"] if bounded else []  # where the failures go
        lines = [f"### {title}\n", header + "".join(f" {c} |" for c in extra) + " wall time (s) |",
                 sep + "---|" * (len(extra) + 1)]
        audited = []
        for name, overrides in rows.items():
            result = run_row(cfg, env, overrides, cfg.output_dir / key / _slug(name))
            cells = [100 * result[k] for k in ("cr_human", "cr_wall", "tr")] if bounded else []
            lines.append(markdown_row(result, bounded, name) + "".join(f" {c:.1f} |" for c in cells)
                         + f" {result['wall_time_s']:.1f} |")
            machines.add(result["machine"])
            audited.append(Row(name, [result]))
        if bounded:
            md, _, facts = wall_audit(audited)
            lines += ["", f"Wall audit (% of the episodes; `measure/metrics.outcome`). {facts}", "", md]
        sections.append("\n".join(lines) + "\n")
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    if GENERALIZATION in cfg.only:
        table = generalization(cfg, machines)
        (cfg.output_dir / "generalization.md").write_text(table)
        if not sections:  # the generalization table alone: baselines.md is left as it is
            print(table)
            return table
        sections.append(table)
    text = "\n".join([f"Baselines on the first {cfg.n_episodes} test seeds (`lerobot-crowdnav-baselines`; "
                      f"wall times on {', '.join(sorted(machines))}).\n", *sections])
    (cfg.output_dir / "baselines.md").write_text(text)
    print(text)
    return text


def main(argv: list[str] | None = None) -> None:
    run_cli(BaselinesConfig, baselines, argv, "rerun the same command: finished rows are kept")


if __name__ == "__main__":
    main()
