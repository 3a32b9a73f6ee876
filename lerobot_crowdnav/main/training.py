"""The main job's training stages, for a run that trains from scratch: ORCA demonstrations, PDPO
pretraining with the stock ``lerobot-train`` (in segments around DAgger rounds), one or two
diffusion-PPO fine-tuning stages, CrowdNav++ by PPO, and the hub-format pushes of what was
trained. Each stage runs the command a user would type (lerobot-train as a subprocess, this
project's CLIs in-process) through the ``StageRunner``, skipped when complete and resumed when
interrupted (collection, lerobot-train and fine-tuning from their last checkpoint)."""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from .. import fault
from ..checkpoint_files import (BEST_INFO, FINETUNE_CONFIG, POLICY_DIGEST, PRETRAINED_MODEL, TRAIN_CONFIG,
                                TRAIN_PPO_CONFIG, TRAINING_STATE, TRAINING_STEP, policy_digest)
from ..cli import machine_description
from ..evaluation.report import Stage
from ..rl.run_log import env_steps_by_device, read_progress
from ..sim.config import PPO_STAGE2_ENV_SEED, CrowdSimConfig
from .config import MainConfig
from .paths import (SHORT, RunPaths, collect_stage, crowdnavpp_stage, eval_stage, finetune_stage, pretrain_stage,
                    push_dataset_stage, push_policy_stage, select_stage)
from .rows import Evaluation
from .stages import StageRunner


def restore_last_checkpoint(checkpoints: Path) -> None:
    """Point lerobot-train's ``checkpoints/last`` link at its newest complete checkpoint when the
    link is missing or dangling: lerobot moves it by unlink, then symlink, and a kill between the
    two would otherwise make the run look never checkpointed (and be started again from zero)."""
    last = checkpoints / "last"
    if last.exists() or not checkpoints.is_dir():
        return
    complete = [p for p in checkpoints.iterdir() if p.name.isdigit() and (p / PRETRAINED_MODEL).is_dir()
                and (p / TRAINING_STATE / TRAINING_STEP).exists()]
    if complete:
        if last.is_symlink():
            last.unlink()
        last.symlink_to(max(complete, key=lambda p: int(p.name)).name)


def env_steps_done(checkpoint: Path, settings: str = FINETUNE_CONFIG) -> int:
    """A PPO checkpoint's env steps, from its run settings file (0 when it has none yet)."""
    path = checkpoint / PRETRAINED_MODEL / settings
    return json.loads(path.read_text())["env_steps_done"] if path.exists() else 0


def select_candidates(run: Path, k: int) -> list[tuple[int, float, Path]]:
    """The ``k`` checkpoints of a fine-tuning run with the best validation readings (ties: the
    earlier), as (env steps, reading, pretrained_model dir): the numbered checkpoints saved where a
    reading was taken, and ``best`` (the trainer's choice, wherever it was saved)."""
    readings = {}
    for record in read_progress(run):
        if "val/success_rate" in record:  # a resumed run logs a reading again: the same value
            readings[record["env_steps"]] = record["val/success_rate"]
    ckpts = run / "checkpoints"
    found = {int(d.name): d / PRETRAINED_MODEL for d in ckpts.iterdir()
             if d.name.isdigit() and int(d.name) in readings and (d / PRETRAINED_MODEL).is_dir()}
    best = json.loads((ckpts / "best" / BEST_INFO).read_text())["env_steps"]
    found.setdefault(best, ckpts / "best" / PRETRAINED_MODEL)
    return [(s, readings[s], found[s]) for s in sorted(found, key=lambda s: (-readings[s], s))[:k]]


class Training:
    """The training stages of one run (``cfg``'s budget), writing under ``paths``."""

    def __init__(self, cfg: MainConfig, paths: RunPaths | None = None, runner: StageRunner | None = None,
                 command: str = "lerobot-crowdnav-main"):
        self.cfg = cfg
        self.paths = paths or RunPaths(cfg.root, cfg.hub_org)
        self.runner = runner or StageRunner(self.paths.stage_times)
        self.command = command  # what the user typed: the model cards' "reproduce" line
        self.device = cfg.device

    def _env_flags(self, task: str) -> list[str]:
        return [f"--env.task={task}", f"--env.preset={self.cfg.preset}"]

    @property
    def ft_stages(self) -> list[int]:
        """The diffusion-PPO stages of each policy: [1], or [1, 2] with ``ft2_env_steps``."""
        return [1, 2] if self.cfg.ft2_env_steps else [1]

    @property
    def main_horizon(self) -> int | None:
        """The horizon of the "pretrained only" row and of the figures (PDPO's 5 when run)."""
        return 5 if 5 in self.cfg.horizons else next(iter(self.cfg.horizons), None)

    def demonstration_env(self, task: str) -> CrowdSimConfig:
        """The simulator the demonstrations come from, with ``--demonstrator`` (None: the preset's)."""
        from ..data.collect import demonstration_env

        return demonstration_env(CrowdSimConfig(task=task, preset=self.cfg.preset, orca_robot=self.cfg.demonstrator))

    def repo_id(self, task: str) -> str:
        return self.paths.repo_id(task, self.demonstration_env(task).orca_robot)

    # -- stages --------------------------------------------------------------------------------
    def collect(self, task: str) -> Stage:
        """The demonstrations; a complete collection in another simulator (another preset) is not
        taken: the resume it gets instead refuses the changed settings."""
        from ..data.collect import main as collect_main
        from ..data.dataset import COLLECTION_FILE, collection_complete

        root = self.paths.dataset_root(task)
        info = root / "meta" / "info.json"
        robot = self.cfg.demonstrator  # None: the preset's
        env = self.demonstration_env(task).to_dict()
        done = (collection_complete(root)  # a collection killed before its card resumes
                and json.loads(info.read_text())["total_episodes"] >= self.cfg.demos
                and json.loads((root / COLLECTION_FILE).read_text())["env"] == json.loads(json.dumps(env)))
        argv = ["python", "datasets_scripts/collect_orca.py", f"--episodes={self.cfg.demos}", *self._env_flags(task),
                *([f"--env.orca_robot={robot}"] if robot else []), f"--repo_id={self.repo_id(task)}", f"--root={root}"]
        resume = ["--resume=true"] if root.exists() else []
        return self.runner.run(collect_stage(task), argv, done, lambda: collect_main(argv[2:] + resume))

    def bc_steps(self, task: str) -> int:
        if self.cfg.bc_epochs <= 0:
            return self.cfg.bc_steps
        frames = json.loads((self.paths.dataset_root(task) / "meta" / "info.json").read_text())["total_frames"]
        return math.ceil(self.cfg.bc_epochs * frames / self.cfg.bc_batch_size)

    def pretrain_dataset(self, task: str, h: int, seed: int) -> Path:
        """What the policy is cloned from: the demonstrations, or with DAgger its own copy of them
        that the rounds aggregate into."""
        if not self.cfg.bc_dagger_at:
            return self.paths.dataset_root(task)
        return self.paths.dagger_dataset_root(task, h, seed)

    def pretrain(self, task: str, h: int, seed: int) -> Stage:
        """lerobot-train on the demonstrations; with DAgger, in segments that end at the rounds."""
        from ..data.dagger import main as dagger_main

        out = self.paths.train_dir(task, h, seed)
        steps = self.bc_steps(task)
        last = out / "checkpoints" / "last"
        restore_last_checkpoint(last.parent)
        step_file = last / TRAINING_STATE / TRAINING_STEP

        def step_done() -> int:
            return json.loads(step_file.read_text())["step"] if step_file.exists() else 0

        data = self.pretrain_dataset(task, h, seed)
        segments = [*sorted(s for s in self.cfg.bc_dagger_at if s < steps), steps]
        argv = ["lerobot-train", "--policy.type=pdpo", f"--policy.horizon={h}", f"--dataset.repo_id={self.repo_id(task)}",
                f"--dataset.root={data}", "--policy.push_to_hub=false", f"--output_dir={out}",
                f"--steps={segments[0]}", f"--batch_size={self.cfg.bc_batch_size}", f"--save_freq={max(1, steps // 4)}",
                f"--log_freq={max(1, min(200, steps // 10))}", f"--num_workers={self.cfg.bc_num_workers}",
                f"--seed={seed}", "--wandb.enable=false", f"--job_name={out.name}", *self.cfg.bc_args]
        if self.device:
            argv.append(f"--policy.device={self.device}")

        def resume_argv(target: int) -> list[str]:
            return ["lerobot-train", f"--config_path={last / PRETRAINED_MODEL / TRAIN_CONFIG}", "--resume=true",
                    f"--steps={target}"]

        def dagger_argv(r: int) -> list[str]:
            return [f"--policy_path={last / PRETRAINED_MODEL}", f"--root={data}", f"--round={r}",
                    f"--episodes={self.cfg.bc_dagger_episodes}", f"--seed={seed}",
                    *([f"--device={self.device}"] if self.device else [])]

        # The stage's record (report, commands.json): every segment, so it reads as the whole pretraining.
        record = list(argv)
        for r, target in enumerate(segments[1:], start=1):
            record += ["&&", "python", "-m", dagger_main.__module__, *dagger_argv(r), "&&", *resume_argv(target)]

        def train_to(target: int) -> None:
            cmd = list(argv)
            if last.exists():  # a later segment, or interrupted: lerobot-train resumes from its last checkpoint
                if step_done() >= target:
                    return
                cmd = resume_argv(target)
            elif out.exists():
                shutil.rmtree(out)  # started but never checkpointed: lerobot-train refuses an existing dir
            cmd[0] = str(Path(sys.executable).parent / "lerobot-train")
            # lerobot-train loads the dataset through 🤗 datasets, which keeps an Arrow copy of each
            # content it loads (1.6 GB for 3,000 demonstrations with their DAgger rounds) and never
            # deletes it: each segment's copy goes to the run folder and is removed after it.
            cache = self.paths.datasets_cache
            try:
                subprocess.run(cmd, check=True, env={**os.environ, "HF_DATASETS_CACHE": str(cache)})
            finally:
                shutil.rmtree(cache, ignore_errors=True)

        def run() -> None:
            demos = self.paths.dataset_root(task)
            if data != demos and not data.exists():
                staging = data.with_name(f".{data.name}.tmp")
                shutil.rmtree(staging, ignore_errors=True)
                shutil.copytree(demos, staging)
                staging.replace(data)
            for r, target in enumerate(segments):
                if r:  # a round is skipped once the dataset holds it
                    dagger_main(dagger_argv(r))
                train_to(target)

        return self.runner.run(pretrain_stage(task, h, seed), record, step_done() >= steps, run)

    def finetune(self, task: str, h: int, seed: int, stage: int = 1) -> Stage:
        """Diffusion PPO from the BC checkpoint (stage 1) or from stage 1's ``ft2_from`` (stage 2)."""
        from ..rl.finetune import main as finetune_main

        out = self.paths.finetune_dir(task, h, seed, stage)
        done = env_steps_done(out / "checkpoints" / "last") >= self.ft_budget(stage)
        argv = self.finetune_argv(task, h, seed, stage)
        resume = ["--resume=true"] if out.exists() else []  # also a run killed before its first checkpoint
        if stage == 2:
            self._check_stage2_start(out, self.finetune_source(task, h, seed, stage))
        return self.runner.run(finetune_stage(task, h, seed, stage), argv, done, lambda: finetune_main(argv[1:] + resume))

    def finetune_source(self, task: str, h: int, seed: int, stage: int) -> Path:
        """The checkpoint a fine-tuning stage starts from: BC's ``last`` (stage 1), or stage 1's
        ``ft2_from`` (stage 2)."""
        return (self.paths.train_dir(task, h, seed) / "checkpoints" / "last" if stage == 1
                else self.stage2_start(task, h, seed)) / PRETRAINED_MODEL

    def ft_budget(self, stage: int) -> int:
        """A fine-tuning stage's env steps."""
        return self.cfg.ft_env_steps if stage == 1 else self.cfg.ft2_env_steps

    def finetune_argv(self, task: str, h: int, seed: int, stage: int) -> list[str]:
        """The ``lerobot-crowdnav-finetune`` command of a fine-tuning stage."""
        c = self.cfg
        steps = self.ft_budget(stage)
        argv = ["lerobot-crowdnav-finetune", f"--policy.path={self.finetune_source(task, h, seed, stage)}",
                *self._env_flags(task), f"--num_envs={c.ft_num_envs}", f"--env_steps={steps}",
                f"--ppo.n_steps={c.ft_n_steps}", f"--ppo.batch_size={c.ft_batch_size}", f"--val.n_episodes={c.ft_val_episodes}", f"--val.freq={c.ft_val_freq}",
                f"--save_freq={max(c.ft_val_freq, steps // 4)}", f"--output_dir={self.paths.finetune_dir(task, h, seed, stage)}",
                *c.ft_args]
        argv += [f"--seed={seed}"] if stage == 1 else [f"--seed={seed + 1}", f"--env_seed={PPO_STAGE2_ENV_SEED}", *c.ft2_args]
        return argv + ([f"--device={self.device}"] if self.device else [])

    def check_finetune_commands(self) -> None:
        """Parse and validate every fine-tuning stage's command before anything runs: a setting the
        fine-tuning refuses (``--ft_args``, the ``ft_*`` fields) fails now, not after the
        collection and hours of BC."""
        import draccus
        from draccus.utils import DecodingError

        from ..rl.finetune import FinetuneConfig

        for task, h, seed, stage in itertools.product(self.cfg.tasks, self.cfg.horizons, self.cfg.seeds, self.ft_stages):
            try:
                draccus.parse(FinetuneConfig, args=self.finetune_argv(task, h, seed, stage)[1:]).validate()
            except (ValueError, DecodingError) as e:
                raise ValueError(f"{finetune_stage(task, h, seed, stage)}: {e}") from None

    @staticmethod
    def _check_stage2_start(out: Path, source: Path) -> None:
        """Refuse a stage 2 that continued another checkpoint of stage 1 (``best`` where the config
        now says ``last``, or the reverse): resumed, it would finish a run of the other recipe; done,
        its card and curve would name the wrong start."""
        saved = out / "checkpoints" / "last" / PRETRAINED_MODEL / FINETUNE_CONFIG
        if not saved.exists():
            return
        started = Path(json.loads(saved.read_text())["policy"]["path"]).parent.name
        if started != source.parent.name:
            raise ValueError(f"{out} continued stage 1's `{started}` checkpoint, this config asks for "
                             f"`{source.parent.name}` (--ft2_from): remove {out} to run stage 2 again, "
                             f"or pass --ft2_from={started} to go on with it as it started")

    def stage2_start(self, task: str, h: int, seed: int) -> Path:
        """The checkpoint of stage 1 that stage 2 continues from (``--ft2_from``)."""
        return self.paths.finetune_dir(task, h, seed) / "checkpoints" / self.cfg.ft2_from

    def rl_run(self, task: str, h: int | None, seed: int) -> tuple[Path, str]:
        """The RL run a policy's checkpoint is chosen from, and its settings file: PDPO's last
        diffusion-PPO stage, or with ``h=None`` the CrowdNav++ PPO run."""
        if h is None:
            return self.paths.crowdnavpp_dir(task, seed), TRAIN_PPO_CONFIG
        return self.paths.finetune_dir(task, h, seed, self.ft_stages[-1]), FINETUNE_CONFIG

    def select(self, task: str, h: int | None, seed: int) -> Stage:
        """The policy's checkpoint, chosen on the validation seeds (``--select_top``): its RL run's
        best-read checkpoints each on ``select_episodes`` episodes, the best of them (ties: the
        earlier) written to ``selected.json``. ``h=None``: the CrowdNav++ run. Each candidate's
        evaluation resumes alone; the choice is made again when the run went further or the
        selection settings changed."""
        from ..evaluation.eval import main as eval_main

        c = self.cfg
        out = self.paths.select_dir(task, h, seed)
        run_dir, settings = self.rl_run(task, h, seed)
        last = run_dir / "checkpoints" / "last"
        made_from = {"top": c.select_top, "episodes": c.select_episodes, "env_steps_done": env_steps_done(last, settings),
                     # the run itself: one removed and run again to the same budget is another run
                     "last_digest": policy_digest(last / PRETRAINED_MODEL) if last.exists() else None}
        selected = self.paths.selected_file(task, h, seed)
        done = selected.exists() and all(json.loads(selected.read_text()).get(k) == v for k, v in made_from.items())
        flags = [*self._env_flags(task), f"--eval.n_episodes={c.select_episodes}", "--eval.split=val",
                 f"--eval.batch_size={min(256, c.select_episodes)}", "--overwrite=true",
                 *([f"--policy.device={self.device}"] if self.device else [])]
        argv = ["lerobot-crowdnav-eval", "--policy.path=<each candidate>", *flags, f"--output_dir={out}/<env steps>"]

        def run() -> None:
            results = []
            for steps, reading, path in select_candidates(run_dir, c.select_top):
                metrics, digest = out / f"{steps:09d}" / "metrics.json", out / f"{steps:09d}" / POLICY_DIGEST
                if (not metrics.exists() or json.loads(metrics.read_text())["n_episodes"] != c.select_episodes
                        or not digest.exists() or digest.read_text() != policy_digest(path)):
                    eval_main([f"--policy.path={path}", *flags, f"--output_dir={metrics.parent}"])
                    digest.write_text(policy_digest(path))
                results.append({"env_steps": steps, "reading": reading, "policy": str(path),
                                "val_success_rate": json.loads(metrics.read_text())["sr"]})
            chosen = max(results, key=lambda r: (r["val_success_rate"], -r["env_steps"]))
            fault.write_text(selected, json.dumps({**made_from, "split": "val", "chosen": chosen, "candidates": results},
                                                  indent=2))

        return self.runner.run(select_stage(task, h, seed), argv, done, run)

    def train_crowdnavpp(self, task: str, seed: int) -> Stage:
        """CrowdNav++ from scratch by PPO (the reference's settings are the CLI's defaults)."""
        from ..rl.train_ppo import main as train_ppo_main

        out = self.paths.crowdnavpp_dir(task, seed)
        c = self.cfg
        done = env_steps_done(out / "checkpoints" / "last", TRAIN_PPO_CONFIG) >= c.crowdnavpp_env_steps
        argv = ["lerobot-crowdnav-train-ppo", "--policy.type=crowdnavpp", *self._env_flags(task),
                f"--env_steps={c.crowdnavpp_env_steps}", f"--seed={seed}", f"--output_dir={out}",
                *c.crowdnavpp_args]
        if self.device:
            argv.append(f"--device={self.device}")
        resume = ["--resume=true"] if out.exists() else []
        return self.runner.run(crowdnavpp_stage(task, seed), argv, done, lambda: train_ppo_main(argv[1:] + resume))

    # -- what the stages made ------------------------------------------------------------------
    def pretrained(self, task: str, h: int, seed: int, pretrain: Stage | None = None) -> Evaluation:
        """The BC policy: lerobot-train's ``last`` checkpoint."""
        path = self.paths.train_dir(task, h, seed) / "checkpoints" / "last" / PRETRAINED_MODEL
        return Evaluation(f"pdpo_bc_h{h}_s{seed}", path, h, seed, pretrain=pretrain)

    def chosen(self, task: str, h: int | None, seed: int) -> Path:
        """The policy of an RL run (``h=None``: CrowdNav++'s): its ``best`` checkpoint, or the one
        ``select`` chose."""
        if self.cfg.select_top:
            return Path(json.loads(self.paths.selected_file(task, h, seed).read_text())["chosen"]["policy"])
        return self.rl_run(task, h, seed)[0] / "checkpoints" / "best" / PRETRAINED_MODEL

    def finetuned(self, task: str, h: int, seed: int, pretrain: Stage | None = None,
                  finetune: Stage | None = None) -> Evaluation:
        return Evaluation(f"pdpo_ft_h{h}_s{seed}", self.chosen(task, h, seed), h, seed, pretrain=pretrain, finetune=finetune)

    def crowdnavpp(self, task: str, seed: int, stage: Stage | None = None) -> Evaluation:
        return Evaluation(f"crowdnavpp_s{seed}", self.chosen(task, None, seed), seed=seed, finetune=stage)

    def finetune_curve(self, task: str, h: int, seed: int) -> Path:
        """A policy's fine-tuning curve for its card: the trainer's own with one stage, every stage
        on one axis with two."""
        from ..measure.plots import plot_finetune_curves

        last = self.paths.finetune_dir(task, h, seed, self.ft_stages[-1])
        if len(self.ft_stages) == 1:
            return last / "training_curves.png"
        return plot_finetune_curves(self.finetune_records(task, h, seed, "PDPO"), last / "training_curves_stages.png")

    def finetune_records(self, task: str, h: int, seed: int, label: str) -> dict[str, list[dict]]:
        """The ``progress.jsonl`` records of each fine-tuning stage of one policy, by label, for
        ``plot_finetune_curves``. Stage 2 is drawn from where it starts in env steps (stage 1's
        checkpoint it continued) and after the whole of stage 1 in wall time (the time it cost)."""
        first = read_progress(self.paths.finetune_dir(task, h, seed))
        if 2 not in self.ft_stages:
            return {label: first}
        start = env_steps_done(self.stage2_start(task, h, seed))
        spent = max(r.get("time/wall_s") or 0.0 for r in first)
        second = [{**r, "env_steps": r["env_steps"] + start,
                   "time/wall_s": None if r.get("time/wall_s") is None else r["time/wall_s"] + spent}
                  for r in read_progress(self.paths.finetune_dir(task, h, seed, 2))]
        second[0]["time/wall_s"] = spent  # its starting validation
        return {f"{label}, stage 1": first, f"{label}, stage 2": second}

    # -- pushes --------------------------------------------------------------------------------
    def push(self, task: str) -> None:
        """The dataset and each trained policy (``best``) to the run's hub-format directory."""
        from ..data.hub import push_dataset_to_dir

        hub, short, seed = self.paths.hub, SHORT[task], self.cfg.seeds[0]
        if self.cfg.horizons:
            repo, root = self.repo_id(task), self.paths.dataset_root(task)
            argv = ["python", "-m", "lerobot_crowdnav.data.hub", "--kind=dataset", f"--root={root}",
                    f"--repo_id={repo}", f"--push_to_hub_dir={hub}", "--overwrite=true"]
            self.runner.run(push_dataset_stage(task), argv, (hub / "datasets" / repo).exists(),
                            lambda: push_dataset_to_dir(root, repo, hub, overwrite=True))
        for h in self.cfg.horizons:
            self._push_policy(task, self.finetuned(task, h, seed), f"pdpo_{short}_h{h}",
                              functools.partial(self.finetune_curve, task, h, seed),
                              [collect_stage(task), pretrain_stage(task, h, seed),
                               *(finetune_stage(task, h, seed, n) for n in self.ft_stages),
                               *([select_stage(task, h, seed)] if self.cfg.select_top else [])],
                              {finetune_stage(task, h, seed, n): self.paths.finetune_dir(task, h, seed, n)
                               for n in self.ft_stages},
                              self.selection_line(task, h, seed))
        if self.cfg.crowdnavpp_env_steps:
            self._push_policy(task, self.crowdnavpp(task, seed), f"crowdnavpp_{short}",
                              lambda: self.paths.crowdnavpp_dir(task, seed) / "training_curves.png",
                              [crowdnavpp_stage(task, seed), *([select_stage(task, None, seed)] if self.cfg.select_top else [])],
                              {crowdnavpp_stage(task, seed): self.paths.crowdnavpp_dir(task, seed)},
                              self.selection_line(task, None, seed))

    def selection_line(self, task: str, h: int | None, seed: int) -> str | None:
        """The card's sentence on how ``select`` chose the checkpoint (None without a selection)."""
        if not self.cfg.select_top:
            return None
        sel = json.loads(self.paths.selected_file(task, h, seed).read_text())
        chosen = sel["chosen"]
        others = "".join(f"; {100 * r['val_success_rate']:.1f} % at {r['env_steps']:,}" for r in sel["candidates"] if r != chosen)
        run = "the last fine-tuning stage" if h is not None else "the PPO run"
        return (f"- Checkpoint: the one at {chosen['env_steps']:,} env steps of {run}, chosen among "
                f"its {len(sel['candidates'])} checkpoints with the best validation readings by {sel['episodes']:,} "
                f"validation episodes each ({100 * chosen['val_success_rate']:.1f} %{others}).")

    def _push_policy(self, task: str, ev: Evaluation, name: str, curve: Callable[[], Path], stages: list[str],
                     runs: dict[str, Path], checkpoint: str | None = None) -> None:
        """``<hub>/models/<org>/<name>``: the checkpoint with its card (test metrics, the learning
        curve ``curve()`` gives, the command and the wall time of the ``stages`` that made it, where
        the trainer ``runs`` of those stages ran when not all on the CPU, and ``checkpoint``: how it
        was chosen, when not the run's ``best``). Written on every run (under a second), so that the
        card follows the latest evaluation and checkpoint choice."""
        from ..data.hub import push_policy_to_dir

        hub, repo = self.paths.hub, f"{self.cfg.hub_org}/{name}"
        metrics = self.paths.eval_dir(task, ev.name) / "metrics.json"
        argv = ["python", "-m", "lerobot_crowdnav.data.hub", "--kind=policy", f"--root={ev.policy}",
                f"--repo_id={repo}", f"--push_to_hub_dir={hub}", f"--metrics={metrics}", "--overwrite=true"]
        times, cpu = self.runner.wall_times(), self.runner.cpu_times()
        names = [n for n in [*stages, eval_stage(task, ev.name)] if n in times]
        recipe = {"command": self.command, "machine": machine_description(),
                  "wall_time_s": {n: times[n] for n in names}, "cpu_time": {n: cpu[n] for n in names if n in cpu},
                  **({"checkpoint": checkpoint} if checkpoint else {})}

        def run() -> None:
            devices = {stage: by_device for stage, out in runs.items() if (out / "progress.jsonl").exists()
                       and set(by_device := env_steps_by_device(read_progress(out))) - {"cpu"}}
            if devices:
                recipe["devices"] = devices
            path = curve()
            push_policy_to_dir(ev.policy, repo, hub, True, metrics, path if path.exists() else None, recipe)

        self.runner.run(push_policy_stage(task, name), argv, False, run)
