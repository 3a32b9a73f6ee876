"""The main job, end to end: ``lerobot-crowdnav-main`` (``make main``).

    lerobot-crowdnav-main                                             # the shipped models, a few minutes on 2 CPU cores
    lerobot-crowdnav-main --config_path=configs/main/retrain.yaml     # every policy trained from scratch
    lerobot-crowdnav-main --config_path=configs/main/paper.yaml       # the paper's budget (a GPU machine)

For each task (Bounded and original CrowdNav) the rows come from one of two sources
(``main/sources.py``): the trained models shipped in ``models/lerobot-crowdnav`` (the default), or,
with ``--models=null``, training from scratch (collect ORCA demonstrations -> pretrain PDPO with
the stock ``lerobot-train``, H = 5 and H = 1 for the "w/o action chunk" ablation, with DAgger
rounds if asked -> fine-tune each with diffusion PPO, one or two stages -> with
``--crowdnavpp_env_steps``, CrowdNav++ by PPO). Then ORCA, straight and those policies on the same
test seeds, the trained policies and datasets pushed to a hub-format directory, figures, the same
rows under the crowds of ``--crowds`` they were not trained in (reactive ORCA humans, social-force
humans, both: the generalization table), and ``outputs/<run>/report.md`` with the tables (also as
CSV) and, next to every number, the command, config and seed that produced it.

Every stage runs the command a user would type and is skipped when its output is complete; an
interrupted stage resumes (collection, lerobot-train and fine-tuning from their last checkpoint).
Evaluation is deterministic, so ``--rerun_eval=true`` regenerates identical tables. A larger
budget on a rerun extends the incomplete stages (lerobot-train resumes to the new
``--bc_steps``); stages already complete are not redone: delete a stage's directory to redo it.
The run folder: ``main/paths.py``; the parts: ``lerobot_crowdnav/main/``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import draccus

from .cli import run_cli
from .main.config import SHIPPED_MODELS, MainConfig
from .main.evaluation import Evaluator
from .main.paths import RunPaths
from .main.sources import ShippedModels, Source, TrainedFromScratch
from .main.stages import StageRunner
from .main.training import Training

__all__ = ["SHIPPED_MODELS", "MainConfig", "Pipeline", "main"]


class Pipeline:
    """One run: its source of rows (the only place that asks whether the job trains), the
    evaluation of every row on the test seeds, figures and report."""

    def __init__(self, cfg: MainConfig, command: str = "lerobot-crowdnav-main"):
        cfg.validate()
        self.cfg = cfg
        self.paths = RunPaths(cfg.root, cfg.hub_org)
        self.runner = StageRunner(self.paths.stage_times)
        self.evaluator = Evaluator(cfg, self.paths, self.runner)
        if cfg.models is None:
            training = Training(cfg, self.paths, self.runner, command)
            training.check_finetune_commands()
            self.source: Source = TrainedFromScratch(cfg, training)
        else:
            self.source = ShippedModels(cfg, self.paths)

    def run(self) -> Path:
        start = time.perf_counter()
        self.paths.root.mkdir(parents=True, exist_ok=True)
        self.paths.config_file.write_text(json.dumps(draccus.encode(self.cfg), indent=2, default=str))
        tasks = []
        for task in self.cfg.tasks:
            rows = self.evaluator.baseline_rows(task) + self.source.rows(task)
            methods = self.evaluator.evaluate_rows(task, rows)
            self.source.publish(task)
            curves, draw_curves = self.source.curves(task)
            figures, curves = self.evaluator.figures(task, self.source.figure_policy(task), curves, draw_curves,
                                                     self.source.redraw)
            crowds = {crowd: self.evaluator.evaluate_rows(task, rows, crowd)  # the generalization table
                      for crowd in self.cfg.extra_crowds}
            tasks.append(self.evaluator.task_results(task, methods, figures, curves, self.source.missing(task), crowds))
        report = self.evaluator.report(tasks, self.source.budget(), self.source.models, time.perf_counter() - start)
        print(f"[main] report: {report}")
        return report


def main(argv: list[str] | None = None) -> None:
    command = " ".join(["lerobot-crowdnav-main", *(sys.argv[1:] if argv is None else argv)])
    run_cli(MainConfig, lambda cfg: Pipeline(cfg, command).run(), argv,
            "rerun the same command to resume (complete stages are skipped)")


if __name__ == "__main__":
    main()
