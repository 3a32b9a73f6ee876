"""The simulator's baseline tables in one command: ``lerobot-crowdnav-baselines``.

    lerobot-crowdnav-baselines                       # every row, 500 test episodes each
    lerobot-crowdnav-baselines --only='[bounded_paper]' --n_episodes=100

Runs ``lerobot-crowdnav-eval`` for each row of :data:`TABLES` (both ORCA robots, wall-unaware and
wall-aware in Bounded, straight; both variants, both presets, randomized attributes on and off,
and CrowdNav++'s ORCA-baseline configuration) on the same test seeds, one ``metrics.json`` per
row under ``<output_dir>/<table>/<row>/``, then writes ``<output_dir>/baselines.md`` (the tables
with wall times, as in docs/simulator.md, and each Bounded table's wall audit). Rerunning skips
rows whose metrics exist for the same episode count, so an interrupted run resumes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from ..cli import run_cli
from ..sim.config import CrowdSimConfig
from .eval import EvalConfig, EvalSettings, OrcaPolicyConfig, StraightPolicyConfig, evaluate
from .metrics import markdown_header, markdown_row
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


@dataclass
class BaselinesConfig:
    # Test episodes per row (the paper: 500).
    n_episodes: int = 500
    # Environments stepped together per evaluation.
    batch_size: int = 250
    # Table keys to run (default: all): bounded_paper, original_paper, bounded_crowdnavpp,
    # original_crowdnavpp, bounded_crowdnavpp_fixed, original_crowdnavpp_fixed, crowdnavpp_orca_baseline.
    only: list[str] = field(default_factory=list)
    # Where the per-row metrics.json files and baselines.md go.
    output_dir: Path = Path("outputs/baselines")


def _slug(name: str) -> str:
    return name.lower().replace(",", "").replace(" ", "_").replace("-", "_")


def run_row(cfg: BaselinesConfig, env: dict, overrides: dict | None, out: Path) -> dict:
    """One row's metrics, from its metrics.json when that holds the same episode count."""
    path = out / "metrics.json"
    if path.exists():
        result = json.loads(path.read_text())
        if result["n_episodes"] == cfg.n_episodes:
            return result
    policy = StraightPolicyConfig() if overrides is None else OrcaPolicyConfig()
    return evaluate(EvalConfig(env=CrowdSimConfig(**env, **(overrides or {})), policy=policy,
                               eval=EvalSettings(n_episodes=cfg.n_episodes, split="test",
                                                 batch_size=cfg.batch_size),
                               output_dir=out, overwrite=True))


def baselines(cfg: BaselinesConfig) -> str:
    unknown = set(cfg.only) - set(TABLES)
    if unknown:
        raise ValueError(f"unknown tables {sorted(unknown)}; choose from {', '.join(TABLES)}")
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
            lines += ["", f"Wall audit (% of the episodes; `evaluation/metrics.outcome`). {facts}", "", md]
        sections.append("\n".join(lines) + "\n")
    text = "\n".join([f"Baselines on the first {cfg.n_episodes} test seeds (`lerobot-crowdnav-baselines`; "
                      f"wall times on {', '.join(sorted(machines))}).\n", *sections])
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "baselines.md").write_text(text)
    print(text)
    return text


def main(argv: list[str] | None = None) -> None:
    run_cli(BaselinesConfig, baselines, argv, "rerun the same command: finished rows are kept")


if __name__ == "__main__":
    main()
