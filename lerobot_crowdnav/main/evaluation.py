"""The main job's evaluation side, whatever source the rows come from: every row's policies on the
same test seeds (``lerobot-crowdnav-eval``; deterministic, so ``--rerun_eval=true`` regenerates
identical tables), the storyboard and multimodality figures of a PDPO policy, and the report
(``evaluation.report`` from typed inputs: tables and CSV, audits, provenance, stages)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..checkpoint_files import POLICY_DIGEST, policy_digest
from ..evaluation.generalization import TRAINED, crowd_flags
from ..evaluation.report import Budget, Evaluated, Method, ReportInputs, Stage, TaskResults, write_report
from ..sim.config import ORCA_ROBOTS, CrowdSimConfig, split_seeds
from .config import MainConfig
from .paths import SHORT, TITLE, RunPaths, eval_stage, figures_stage
from .rows import Evaluation, MethodRow, finetuned_label
from .stages import StageRunner

# A learning curve in the report: (caption, image under the run folder).
Curve = tuple[str, Path]


class Evaluator:
    """Evaluation, figures and report of one run (``cfg``), writing under ``paths``."""

    def __init__(self, cfg: MainConfig, paths: RunPaths, runner: StageRunner):
        self.cfg = cfg
        self.paths = paths
        self.runner = runner

    def _env_flags(self, task: str) -> list[str]:
        return [f"--env.task={task}", f"--env.preset={self.cfg.preset}"]

    def baseline_rows(self, task: str) -> list[MethodRow]:
        """The rows every run has: both ORCA robots, the preset's first (``orca``; the paper's is
        the look-ahead robot, the recipes' demonstrator the current-state one), and the straight line."""
        preset_robot = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve().orca_robot
        robots = sorted(ORCA_ROBOTS, key=lambda robot: robot != preset_robot)
        return [*(MethodRow(f"ORCA ({robot.replace('_', '-')})",
                            [Evaluation("orca")] if robot == preset_robot else
                            [Evaluation(f"orca_{robot}", policy_type="orca", env_flags=(f"--env.orca_robot={robot}",))])
                  for robot in robots),
                MethodRow("straight", [Evaluation("straight")])]

    def evaluate(self, task: str, ev: Evaluation, crowd: str = TRAINED) -> Stage:
        """``ev`` on the test seeds, in the trained crowd (the results tables) or in ``crowd`` (the
        generalization table: its own directory and stage, no GIF)."""
        from ..evaluation.eval import main as eval_main
        from ..evaluation.eval import parse, saved_result

        out = self.paths.eval_dir(task, ev.name, crowd)
        policy = [f"--policy.type={ev.policy_type or ev.name}"] if ev.policy is None else [f"--policy.path={ev.policy}"]
        if self.cfg.device and ev.policy is not None:
            policy.append(f"--policy.device={self.cfg.device}")
        trained = crowd == TRAINED
        argv = ["lerobot-crowdnav-eval", *policy, *self._env_flags(task), *ev.env_flags,
                *([] if trained else crowd_flags(crowd)),
                f"--eval.n_episodes={self.cfg.test_episodes}", "--eval.split=test",
                f"--eval.batch_size={min(256, self.cfg.test_episodes)}", f"--eval.n_videos={int(trained)}",
                f"--output_dir={out}", "--overwrite=true"]
        done = not self.cfg.rerun_eval and saved_result(parse(argv[1:])) is not None
        digest = out / POLICY_DIGEST
        if ev.shipped and trained:
            # A shipped model may have been replaced since its last evaluation (under a minute): always run.
            done = False
        elif ev.policy is not None:  # run again when the model's files changed (another checkpoint chosen)
            done = done and digest.exists() and digest.read_text() == policy_digest(ev.policy)

        def run() -> None:
            eval_main(argv[1:])
            if ev.policy is not None:
                digest.write_text(policy_digest(ev.policy))

        return self.runner.run(eval_stage(task, ev.name, crowd), argv, done, run)

    def evaluate_rows(self, task: str, rows: list[MethodRow], crowd: str = TRAINED) -> list[Method]:
        """Each row's policies on the test seeds in ``crowd``, with the stages that made them (provenance)."""
        return [Method(row.label, [Evaluated(ev.name, self.paths.eval_dir(task, ev.name, crowd),
                                             self.evaluate(task, ev, crowd), ev.policy, ev.seed,
                                             ev.pretrain, ev.finetune, ev.shipped)
                                   for ev in row.evaluations]) for row in rows]

    def figures(self, task: str, shown: Evaluation | None, curves: list[Curve], draw_curves: Callable[[], None],
                redraw: bool) -> tuple[Stage | None, list[Curve]]:
        """Storyboard and multimodality of the PDPO policy ``shown`` (none without one), and the
        learning curves that ``draw_curves`` writes (after the two figures); ``redraw``: draw them
        even when they exist (the policies may have been replaced: seconds)."""
        from ..evaluation.figures import record_snapshots
        from ..measure.plots import plot_multimodality, plot_storyboard

        if shown is None:
            return None, []
        out = self.paths.figures_dir(task)
        policy = shown.policy
        episode_seed = split_seeds("test", self.cfg.figure_episode + 1)[-1]
        paths = {"storyboard": out / "storyboard.png", "multimodality": out / "multimodality.png"}
        steps = ",".join(map(str, self.cfg.figure_steps))
        argv = ["python", "-m", "lerobot_crowdnav.evaluation.figures", f"--policy.path={policy}", *self._env_flags(task),
                f"--seed={episode_seed}", f"--steps={steps}", f"--n_samples={self.cfg.figure_samples}", f"--output_dir={out}"]
        label = finetuned_label(shown.horizon)

        def run() -> None:
            sim_cfg = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve()
            snaps = record_snapshots(policy, sim_cfg, episode_seed, self.cfg.figure_steps, self.cfg.figure_samples,
                                     device=self.cfg.device or "cpu")
            walls = sim_cfg.arena_size if sim_cfg.bounded else None
            plot_storyboard(snaps, paths["storyboard"], sim_cfg.sensing_range, sim_cfg.dt, arena_size=walls,
                            title=f"{TITLE[task]}, test episode {episode_seed}: {label}")
            plot_multimodality(snaps, paths["multimodality"], sim_cfg.sensing_range, sim_cfg.dt, arena_size=walls,
                               title=f"{TITLE[task]}, test episode {episode_seed}: {self.cfg.figure_samples} chunks "
                                     "sampled per observation")
            draw_curves()
            digest.write_text(policy_digest(policy))

        # Drawn again when another policy is shown (a longer run, another checkpoint chosen).
        digest = out / POLICY_DIGEST
        done = (all(p.exists() for p in [*paths.values(), *(image for _, image in curves)]) and not self.cfg.rerun_eval
                and not redraw and digest.exists() and digest.read_text() == policy_digest(policy))
        return self.runner.run(figures_stage(task), argv, done, run), curves

    def task_results(self, task: str, methods: list[Method], figures: Stage | None, curves: list[Curve],
                     missing: list[str], crowds: dict[str, list[Method]] | None = None) -> TaskResults:
        bounded = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve().bounded
        return TaskResults(task, TITLE[task], SHORT[task], methods, self.paths.figures_dir(task), figures, curves,
                           bounded=bounded, missing_models=missing, crowds=crowds or {})

    def report(self, tasks: list[TaskResults], budget: Budget | None, models: Path | None, wall_time_s: float) -> Path:
        """``report.md``, ``tables/*.csv`` and ``commands.json`` (this invocation's stages, in order)."""
        return write_report(ReportInputs(self.paths.root, budget, tasks, list(self.runner.stages.values()), wall_time_s,
                                         self.cfg.test_episodes, self.cfg.preset, models))
