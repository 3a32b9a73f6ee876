"""The main job, end to end: ``lerobot-crowdnav-main`` (``make main``).

    lerobot-crowdnav-main                                          # embedded defaults, ~15 min on 2 CPU cores
    lerobot-crowdnav-main --config_path=configs/main/paper.yaml    # the paper's budget (a GPU machine)

For each task (Bounded and original CrowdNav): collect ORCA demonstrations -> pretrain PDPO with
the stock ``lerobot-train`` (H = 5, and H = 1 for the "w/o action chunk" ablation) -> fine-tune
each with diffusion PPO (and, with ``--crowdnavpp_env_steps``, train the CrowdNav++ baseline by
PPO) -> evaluate ORCA, straight and the trained policies on the same test seeds -> push the
datasets and the trained policies to a hub-format directory -> figures; then
``outputs/<run>/report.md`` with the tables (also as CSV), figures and, next to every number,
the command, config and seed that produced it.

Every stage runs the command a user would type (lerobot-train as a subprocess, this project's
CLIs in-process) and is skipped when its output is complete; an interrupted stage resumes
(collection, lerobot-train and fine-tuning from their last checkpoint). Evaluation is
deterministic, so ``--rerun_eval=true`` regenerates identical tables from the saved checkpoints.
A larger budget on a rerun extends the incomplete stages (lerobot-train resumes to the new
``--bc_steps``); stages already complete are not redone: delete a stage's directory to redo it.

    outputs/<run>/
        datasets/<task>/               ORCA demonstrations (LeRobotDataset)
        train/<task>_h<H>_s<seed>/     lerobot-train runs (checkpoints/last/pretrained_model)
        finetune/<task>_h<H>_s<seed>/  diffusion-PPO runs (checkpoints/best/pretrained_model); with
                                       --ft2_env_steps, <...>_stage2/ continues from its best
        crowdnavpp/<task>_s<seed>/     CrowdNav++ PPO runs (checkpoints/best/pretrained_model)
        eval/<task>/<method>/          metrics.json (+ a GIF of the first test episode)
        hub/                           datasets/<org>/<name>, models/<org>/<name>
        figures/<task>/                storyboard, multimodality, fine-tuning curves
        tables/*.csv, commands.json, report.md
"""

from __future__ import annotations

import functools
import json
import math
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import draccus

from . import fault
from .cli import machine_description, run_cli
from .evaluation.report import Budget, Evaluated, Method, ReportInputs, Stage, TaskResults, write_report
from .checkpoint_files import FINETUNE_CONFIG, TRAIN_PPO_CONFIG
from .sim.config import PPO_STAGE2_ENV_SEED, SEED_SPLITS, TASKS, CrowdSimConfig, split_seeds

SHORT = {"BoundedCrowdNav-v0": "bounded", "CrowdNav-v0": "original"}
# The trained models shipped in the repository (hub format: models/<org>/<name>), made by the
# recipes (docs/recipes.md).
SHIPPED_MODELS = Path(__file__).resolve().parents[1] / "models" / "lerobot-crowdnav"
FINETUNED_LABEL = {5: "PDPO (H = 5, fine-tuned)", 1: "PDPO w/o action chunk (H = 1, fine-tuned)"}
CROWDNAVPP_LABEL = "CrowdNav++ (Const. Vel.)"
TITLE = {"BoundedCrowdNav-v0": "Bounded CrowdNav", "CrowdNav-v0": "original CrowdNav"}


@dataclass
class MainConfig:
    # Run name: everything goes to <output_root>/<run>/.
    run: str = "main"
    output_root: Path = Path("outputs")
    # Trained models to evaluate instead of training: a directory of hub-format model directories
    # named pdpo_<task>_h<H> and crowdnavpp_<task> (<task> = bounded | original). The job then
    # evaluates them and the baselines on the test seeds, draws the figures and writes the report:
    # no demonstrations, no training. Default: the models shipped in the repository. null trains
    # every policy from scratch with the budget below (configs/main/retrain.yaml: the recipes').
    models: Path | None = SHIPPED_MODELS
    # Benchmarks, each with its own demonstrations and policies.
    tasks: list[str] = field(default_factory=lambda: ["BoundedCrowdNav-v0", "CrowdNav-v0"])
    # Simulator preset (paper | crowdnavpp).
    preset: str = "paper"
    # ORCA demonstrations per task, successful episodes (paper: 3,000).
    demos: int = 300
    # Pretraining steps of lerobot-train at bc_batch_size; bc_epochs > 0 replaces it by that many
    # epochs over the demonstrations (paper: 200 epochs at batch 128).
    bc_steps: int = 2000
    bc_epochs: float = 0.0
    bc_batch_size: int = 128
    # lerobot-train data-loader workers: with the plugin's fast loader, 0 is fastest on 2 cores.
    bc_num_workers: int = 0
    # Chunk horizons: 5 = PDPO, 1 = the "w/o action chunk" ablation ([] with a CrowdNav++ budget:
    # no PDPO, no demonstrations).
    horizons: list[int] = field(default_factory=lambda: [5, 1])
    # Diffusion-PPO budget per policy in env steps (paper: about 12 M), envs per process, rollout
    # length, validation episodes and interval (env steps).
    ft_env_steps: int = 16384
    ft_num_envs: int = 32
    ft_n_steps: int = 64
    # Minibatch in env steps, each with its 10 denoising transitions (paper: 500).
    ft_batch_size: int = 500
    ft_val_episodes: int = 20
    ft_val_freq: int = 4096
    # DAgger rounds in pretraining (lerobot_crowdnav.data.dagger; [] = plain behaviour cloning, the
    # paper): at each of these lerobot-train steps (below the BC budget) the policy trained so far
    # drives bc_dagger_episodes learner episodes, the ORCA demonstrator labels every state it
    # visits with its chunk from there, and lerobot-train resumes on the aggregate (each policy
    # aggregates into its own copy of the demonstrations, datasets/<task>_h<H>_s<seed>_dagger).
    bc_dagger_at: list[int] = field(default_factory=list)
    bc_dagger_episodes: int = 500
    # Further flags of every lerobot-train run (e.g. ["--policy.noise_draws=4"]) and of every
    # lerobot-crowdnav-finetune run (e.g. ["--ppo.update_epochs=3"]): a recipe's own settings.
    bc_args: list[str] = field(default_factory=list)
    ft_args: list[str] = field(default_factory=list)
    # A second diffusion-PPO stage per policy (0: none): it continues from the first stage's `best`
    # checkpoint (critic included) for ft2_env_steps env steps with the first stage's flags, then
    # ft2_args on top (later flags win), e.g. ["--ppo.freeze_encoder=false"]: the recipes train the
    # encoder once the cheap frozen-encoder stage has plateaued (docs/recipes.md). Its training
    # episodes and sampling noise come from seeds of their own (seed + 1, env seed 520,000,000).
    ft2_env_steps: int = 0
    ft2_args: list[str] = field(default_factory=list)
    # The CrowdNav++ (Const. Vel.) baseline: PPO env steps per task of CrowdNav++'s network trained
    # from scratch by lerobot-crowdnav-train-ppo with the reference's PPO settings (reference: 10 M;
    # docs/crowdnavpp.md); 0 = no CrowdNav++ row. Further flags of that run (e.g. "--val.freq=...").
    crowdnavpp_env_steps: int = 0
    crowdnavpp_args: list[str] = field(default_factory=list)
    # Training seeds (pretraining and fine-tuning); tables show mean +- std over them.
    seeds: list[int] = field(default_factory=lambda: [1000])
    # Test episodes per method, the first seeds of the test split (paper: 500).
    test_episodes: int = 500
    # Figures: the test episode drawn, its steps and the chunks sampled per step.
    figure_episode: int = 0
    figure_steps: list[int] = field(default_factory=lambda: [0, 4, 8, 12, 16])
    figure_samples: int = 32
    # Organization of the hub-format repositories (<run>/hub/{datasets,models}/<org>/...).
    hub_org: str = "local"
    # Torch device for training and evaluation (default: cuda when available, else cpu).
    device: str | None = None
    # Evaluate again even when metrics exist (the tables come out identical: evaluation is deterministic).
    rerun_eval: bool = False

    def validate(self) -> None:
        bad = [t for t in self.tasks if t not in TASKS]
        if bad or not self.tasks:
            raise ValueError(f"--tasks must be a non-empty subset of {list(TASKS)}, got {self.tasks}")
        if any(h < 1 for h in self.horizons):
            raise ValueError(f"--horizons must be positive, got {self.horizons}")
        if self.crowdnavpp_env_steps < 0 or self.ft2_env_steps < 0:
            raise ValueError("--crowdnavpp_env_steps and --ft2_env_steps must be >= 0")
        if self.models is None and not self.horizons and not self.crowdnavpp_env_steps:
            raise ValueError("nothing to train: give --horizons (PDPO) and/or --crowdnavpp_env_steps (CrowdNav++)")
        if not self.seeds:
            raise ValueError("--seeds needs at least one seed")
        if any(step < 1 for step in self.bc_dagger_at) or len(set(self.bc_dagger_at)) != len(self.bc_dagger_at):
            raise ValueError(f"--bc_dagger_at must be distinct positive lerobot-train steps, got {self.bc_dagger_at}")
        for name in ("demos", "bc_steps", "bc_batch_size", "bc_dagger_episodes", "ft_env_steps", "ft_num_envs", "ft_n_steps", "ft_batch_size",
                     "ft_val_episodes", "test_episodes", "figure_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")
        test_size = SEED_SPLITS["test"][1] - SEED_SPLITS["test"][0]
        if self.test_episodes > test_size or not 0 <= self.figure_episode < test_size:
            raise ValueError(f"--test_episodes and --figure_episode must fit the {test_size} test seeds")
        if self.models is not None and not self.models.is_dir():
            raise ValueError(f"--models={self.models} is not a directory of trained models; pass --models=null "
                             "(or a training config such as configs/main/retrain.yaml) to train from scratch")

    @property
    def root(self) -> Path:
        return self.output_root / self.run


@dataclass(frozen=True)
class Evaluation:
    """One policy evaluated on the test seeds: a built-in (``policy`` None), a checkpoint trained
    by this run with ``horizon`` and ``seed`` (``finetuned``: the diffusion-PPO ``best``), or a
    ``shipped`` model directory."""

    name: str  # the directory under eval/<task>/
    policy: Path | None = None
    horizon: int | None = None
    seed: int | None = None
    finetuned: bool = False
    shipped: bool = False


class Pipeline:
    def __init__(self, cfg: MainConfig, command: str = "lerobot-crowdnav-main"):
        cfg.validate()
        self.cfg = cfg
        self.command = command  # what the user typed: the model cards' "reproduce" line
        self.root = cfg.root
        self.stages: dict[str, Stage] = {}  # this invocation's stages, in order
        self.device = cfg.device

    # -- helpers -------------------------------------------------------------------------------
    def _stage(self, name: str, argv: list[str], done: bool, run) -> Stage:
        """Run the stage unless its output is complete; record its command (and wall time)."""
        if done:
            print(f"[main] {name}: complete, skipped")
            stage = Stage(name, argv)
        else:
            print(f"[main] {name}: {' '.join(argv)}", flush=True)
            start = time.perf_counter()
            try:
                run()
            finally:
                elapsed = time.perf_counter() - start
                self._add_wall_time(name, elapsed)
            stage = Stage(name, argv, elapsed)
        self.stages[name] = stage
        return stage

    @property
    def _times_path(self) -> Path:
        return self.root / "stage_times.json"

    def wall_times(self) -> dict[str, float]:
        """Wall time of each stage summed over every invocation that ran it (a resumed stage's
        time includes the interrupted attempts, Ctrl-C and SIGTERM included; not SIGKILL)."""
        return json.loads(self._times_path.read_text()) if self._times_path.exists() else {}

    def _add_wall_time(self, name: str, seconds: float) -> None:
        times = self.wall_times()
        times[name] = times.get(name, 0.0) + seconds
        fault.write_text(self._times_path, json.dumps(times, indent=2))

    def _env_flags(self, task: str) -> list[str]:
        return [f"--env.task={task}", f"--env.preset={self.cfg.preset}"]

    def dataset_root(self, task: str) -> Path:
        return self.root / "datasets" / SHORT[task]

    def repo_id(self, task: str) -> str:
        return f"{self.cfg.hub_org}/crowdnav_orca_{SHORT[task]}"

    def train_dir(self, task: str, h: int, seed: int) -> Path:
        return self.root / "train" / f"{SHORT[task]}_h{h}_s{seed}"

    def finetune_dir(self, task: str, h: int, seed: int, stage: int = 1) -> Path:
        return self.root / "finetune" / (f"{SHORT[task]}_h{h}_s{seed}" + ("" if stage == 1 else f"_stage{stage}"))

    @property
    def ft_stages(self) -> list[int]:
        """The diffusion-PPO stages of each policy: [1], or [1, 2] with ``ft2_env_steps``."""
        return [1, 2] if self.cfg.ft2_env_steps else [1]

    def finetune_stage_name(self, task: str, h: int, seed: int, stage: int) -> str:
        return f"finetune{'' if stage == 1 else stage} {SHORT[task]} H={h} seed={seed}"

    def crowdnavpp_dir(self, task: str, seed: int) -> Path:
        return self.root / "crowdnavpp" / f"{SHORT[task]}_s{seed}"

    # -- stages --------------------------------------------------------------------------------
    def collect(self, task: str) -> Stage:
        from .data.collect import main as collect_main

        root = self.dataset_root(task)
        info = root / "meta" / "info.json"
        done = ((root / "README.md").exists()  # written last: a collection killed before it resumes
                and json.loads(info.read_text())["total_episodes"] >= self.cfg.demos)
        argv = ["python", "datasets_scripts/collect_orca.py", f"--episodes={self.cfg.demos}", *self._env_flags(task),
                f"--repo_id={self.repo_id(task)}", f"--root={root}"]
        resume = ["--resume=true"] if root.exists() else []
        return self._stage(f"collect {SHORT[task]}", argv, done, lambda: collect_main(argv[2:] + resume))

    def bc_steps(self, task: str) -> int:
        if self.cfg.bc_epochs <= 0:
            return self.cfg.bc_steps
        frames = json.loads((self.dataset_root(task) / "meta" / "info.json").read_text())["total_frames"]
        return math.ceil(self.cfg.bc_epochs * frames / self.cfg.bc_batch_size)

    def pretrain_dataset(self, task: str, h: int, seed: int) -> Path:
        """What the policy is cloned from: the demonstrations, or with DAgger its own copy of them
        that the rounds aggregate into."""
        if not self.cfg.bc_dagger_at:
            return self.dataset_root(task)
        return self.root / "datasets" / f"{SHORT[task]}_h{h}_s{seed}_dagger"

    def pretrain(self, task: str, h: int, seed: int) -> Stage:
        """lerobot-train on the demonstrations; with DAgger, in segments that end at the rounds."""
        from .data.dagger import main as dagger_main

        out = self.train_dir(task, h, seed)
        steps = self.bc_steps(task)
        last = out / "checkpoints" / "last"
        step_file = last / "training_state" / "training_step.json"

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

        def train_to(target: int) -> None:
            cmd = list(argv)
            if last.exists():  # a later segment, or interrupted: lerobot-train resumes from its last checkpoint
                if step_done() >= target:
                    return
                cmd = ["lerobot-train", f"--config_path={last / 'pretrained_model' / 'train_config.json'}", "--resume=true",
                       f"--steps={target}"]
            elif out.exists():
                shutil.rmtree(out)  # started but never checkpointed: lerobot-train refuses an existing dir
            cmd[0] = str(Path(sys.executable).parent / "lerobot-train")
            subprocess.run(cmd, check=True)

        def run() -> None:
            if data != self.dataset_root(task) and not data.exists():
                staging = data.with_name(f".{data.name}.tmp")
                shutil.rmtree(staging, ignore_errors=True)
                shutil.copytree(self.dataset_root(task), staging)
                staging.replace(data)
            for r, target in enumerate(segments):
                if r:  # a round is skipped once the dataset holds it
                    dagger_main([f"--policy_path={last / 'pretrained_model'}", f"--root={data}", f"--round={r}",
                                 f"--episodes={self.cfg.bc_dagger_episodes}", f"--seed={seed}",
                                 *([f"--device={self.device}"] if self.device else [])])
                train_to(target)

        return self._stage(f"pretrain {SHORT[task]} H={h} seed={seed}", argv, step_done() >= steps, run)

    def finetune(self, task: str, h: int, seed: int, stage: int = 1) -> Stage:
        """Diffusion PPO from the BC checkpoint (stage 1) or from stage 1's ``best`` (stage 2)."""
        from .rl.finetune import main as finetune_main

        c = self.cfg
        out = self.finetune_dir(task, h, seed, stage)
        steps = c.ft_env_steps if stage == 1 else c.ft2_env_steps
        saved = out / "checkpoints" / "last" / "pretrained_model" / FINETUNE_CONFIG
        done = saved.exists() and json.loads(saved.read_text())["env_steps_done"] >= steps
        source = (self.train_dir(task, h, seed) / "checkpoints" / "last" if stage == 1
                  else self.finetune_dir(task, h, seed) / "checkpoints" / "best") / "pretrained_model"
        argv = ["lerobot-crowdnav-finetune", f"--policy.path={source}",
                *self._env_flags(task), f"--num_envs={c.ft_num_envs}", f"--env_steps={steps}",
                f"--ppo.n_steps={c.ft_n_steps}", f"--ppo.batch_size={c.ft_batch_size}", f"--val.n_episodes={c.ft_val_episodes}", f"--val.freq={c.ft_val_freq}",
                f"--save_freq={max(c.ft_val_freq, steps // 4)}", f"--output_dir={out}", *c.ft_args]
        argv += [f"--seed={seed}"] if stage == 1 else [f"--seed={seed + 1}", f"--env_seed={PPO_STAGE2_ENV_SEED}", *c.ft2_args]
        if self.device:
            argv.append(f"--device={self.device}")
        resume = ["--resume=true"] if out.exists() else []  # also a run killed before its first checkpoint
        return self._stage(self.finetune_stage_name(task, h, seed, stage), argv, done,
                           lambda: finetune_main(argv[1:] + resume))

    def train_crowdnavpp(self, task: str, seed: int) -> Stage:
        """CrowdNav++ from scratch by PPO (the reference's settings are the CLI's defaults)."""
        from .rl.train_ppo import main as train_ppo_main

        out = self.crowdnavpp_dir(task, seed)
        saved = out / "checkpoints" / "last" / "pretrained_model" / TRAIN_PPO_CONFIG
        c = self.cfg
        done = saved.exists() and json.loads(saved.read_text())["env_steps_done"] >= c.crowdnavpp_env_steps
        argv = ["lerobot-crowdnav-train-ppo", "--policy.type=crowdnavpp", *self._env_flags(task),
                "--env.compute_intrusion=false", f"--env_steps={c.crowdnavpp_env_steps}", f"--seed={seed}",
                f"--output_dir={out}", *c.crowdnavpp_args]
        if self.device:
            argv.append(f"--device={self.device}")
        resume = ["--resume=true"] if out.exists() else []
        return self._stage(f"train crowdnavpp {SHORT[task]} seed={seed}", argv, done,
                           lambda: train_ppo_main(argv[1:] + resume))

    def crowdnavpp(self, task: str, seed: int) -> Evaluation:
        return Evaluation(f"crowdnavpp_s{seed}", self.crowdnavpp_dir(task, seed) / "checkpoints" / "best" / "pretrained_model",
                          seed=seed, finetuned=True)

    @property
    def main_horizon(self) -> int | None:
        """The horizon of the "pretrained only" row and of the figures (PDPO's 5 when run)."""
        return 5 if 5 in self.cfg.horizons else next(iter(self.cfg.horizons), None)

    def finetuned(self, task: str, h: int, seed: int) -> Evaluation:
        """The policy's final diffusion-PPO stage's ``best`` checkpoint."""
        out = self.finetune_dir(task, h, seed, self.ft_stages[-1])
        return Evaluation(f"pdpo_ft_h{h}_s{seed}", out / "checkpoints" / "best" / "pretrained_model", h, seed, finetuned=True)

    def methods(self, task: str) -> list[tuple[str, list[Evaluation]]]:
        """The table rows: (label, the evaluations averaged in it, one per training seed)."""
        robot = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve().orca_robot.replace("_", "-")
        rows = [(f"ORCA ({robot})", [Evaluation("orca")]), ("straight", [Evaluation("straight")])]
        if self.cfg.models is not None:
            return rows + [(label, [ev]) for label, ev in self.shipped(task)]
        h0 = self.main_horizon
        if h0 is not None:
            rows.append((f"PDPO pretrained only (H = {h0}, BC)",
                         [Evaluation(f"pdpo_bc_h{h0}_s{s}", self.train_dir(task, h0, s) / "checkpoints" / "last" / "pretrained_model", h0, s)
                          for s in self.cfg.seeds]))
        for h in sorted(self.cfg.horizons):
            rows.append((FINETUNED_LABEL.get(h, f"PDPO (H = {h}, fine-tuned)"), [self.finetuned(task, h, s) for s in self.cfg.seeds]))
        if self.cfg.crowdnavpp_env_steps:
            rows.append((CROWDNAVPP_LABEL, [self.crowdnavpp(task, s) for s in self.cfg.seeds]))
        return rows

    def shipped_names(self, task: str) -> dict[str, str]:
        """Row label -> the model directory's name, for every policy the job can show."""
        short = SHORT[task]
        return {FINETUNED_LABEL[1]: f"pdpo_{short}_h1", FINETUNED_LABEL[5]: f"pdpo_{short}_h5",
                CROWDNAVPP_LABEL: f"crowdnavpp_{short}"}

    @functools.cache
    def shipped(self, task: str) -> list[tuple[str, Evaluation]]:
        """The shipped models of ``task`` that exist in ``--models``, as table rows (read once
        per run: the rows, the figures and the curves all ask)."""
        found = []
        for label, name in self.shipped_names(task).items():
            path = self.cfg.models / name
            if (path / "model.safetensors").exists():
                config = json.loads((path / "config.json").read_text())
                horizon = config["horizon"] if config.get("type") == "pdpo" else None
                if horizon is not None and not name.endswith(f"_h{horizon}"):
                    raise ValueError(f"{path} holds a PDPO policy with H = {horizon}: its row ({label}) needs H = "
                                     f"{name.rsplit('_h', 1)[-1]}")
                found.append((label, Evaluation(name, path, horizon, shipped=True)))
        return found

    def figure_policy(self, task: str) -> Evaluation | None:
        """The PDPO policy drawn in the figures: H = 5 when there is one."""
        if self.cfg.models is None:
            return None if self.main_horizon is None else self.finetuned(task, self.main_horizon, self.cfg.seeds[0])
        pdpo = sorted((ev for _, ev in self.shipped(task) if ev.horizon is not None), key=lambda ev: ev.horizon != 5)
        return pdpo[0] if pdpo else None

    def eval_dir(self, task: str, name: str) -> Path:
        return self.root / "eval" / SHORT[task] / name

    def evaluate(self, task: str, ev: Evaluation) -> Stage:
        from .evaluation.eval import main as eval_main

        out = self.eval_dir(task, ev.name)
        metrics = out / "metrics.json"
        policy = [f"--policy.type={ev.name}"] if ev.policy is None else [f"--policy.path={ev.policy}"]
        if self.device and ev.policy is not None:
            policy.append(f"--policy.device={self.device}")
        argv = ["lerobot-crowdnav-eval", *policy, *self._env_flags(task), f"--eval.n_episodes={self.cfg.test_episodes}",
                "--eval.split=test", f"--eval.batch_size={min(256, self.cfg.test_episodes)}", "--eval.n_videos=1",
                f"--output_dir={out}", "--overwrite=true"]
        # A shipped model may have been replaced since its last evaluation (under a minute): always run.
        done = (not self.cfg.rerun_eval and not ev.shipped and metrics.exists()
                and json.loads(metrics.read_text())["n_episodes"] == self.cfg.test_episodes)
        return self._stage(f"eval {SHORT[task]} {ev.name}", argv, done, lambda: eval_main(argv[1:]))

    def push(self, task: str) -> None:
        """The dataset and each trained policy (``best``) to the run's hub-format directory."""
        from .data.hub import push_dataset_to_dir

        hub, short, seed = self.root / "hub", SHORT[task], self.cfg.seeds[0]
        if self.cfg.horizons:
            repo = self.repo_id(task)
            argv = ["python", "-m", "lerobot_crowdnav.data.hub", "--kind=dataset", f"--root={self.dataset_root(task)}",
                    f"--repo_id={repo}", f"--push_to_hub_dir={hub}", "--overwrite=true"]
            self._stage(f"push dataset {short}", argv, (hub / "datasets" / repo).exists(),
                        lambda: push_dataset_to_dir(self.dataset_root(task), repo, hub, overwrite=True))
        for h in self.cfg.horizons:
            self._push_policy(task, self.finetuned(task, h, seed), f"pdpo_{short}_h{h}",
                              functools.partial(self.finetune_curve, task, h, seed),
                              [f"collect {short}", f"pretrain {short} H={h} seed={seed}",
                               *(self.finetune_stage_name(task, h, seed, n) for n in self.ft_stages)])
        if self.cfg.crowdnavpp_env_steps:
            self._push_policy(task, self.crowdnavpp(task, seed), f"crowdnavpp_{short}",
                              lambda: self.crowdnavpp_dir(task, seed) / "training_curves.png",
                              [f"train crowdnavpp {short} seed={seed}"])

    def _push_policy(self, task: str, ev: Evaluation, name: str, curve: Callable[[], Path], stages: list[str]) -> None:
        """``<hub>/models/<org>/<name>``: the checkpoint with its card (test metrics, the learning
        curve ``curve()`` gives, the command and the wall time of the ``stages`` that made it)."""
        from .data.hub import push_policy_to_dir

        hub, repo = self.root / "hub", f"{self.cfg.hub_org}/{name}"
        metrics = self.eval_dir(task, ev.name) / "metrics.json"
        argv = ["python", "-m", "lerobot_crowdnav.data.hub", "--kind=policy", f"--root={ev.policy}",
                f"--repo_id={repo}", f"--push_to_hub_dir={hub}", f"--metrics={metrics}", "--overwrite=true"]
        times = self.wall_times()
        recipe = {"command": self.command, "machine": machine_description(),
                  "wall_time_s": {n: times[n] for n in [*stages, f"eval {SHORT[task]} {ev.name}"] if n in times}}

        def run() -> None:
            path = curve()
            push_policy_to_dir(ev.policy, repo, hub, True, metrics, path if path.exists() else None, recipe)

        self._stage(f"push policy {SHORT[task]} {name}", argv, (hub / "models" / repo).exists() and not self.cfg.rerun_eval, run)

    def finetune_curve(self, task: str, h: int, seed: int) -> Path:
        """A policy's fine-tuning curve for its card: the trainer's own with one stage, every stage
        on one axis with two."""
        from .evaluation.plots import plot_finetune_curves

        last = self.finetune_dir(task, h, seed, self.ft_stages[-1])
        if len(self.ft_stages) == 1:
            return last / "training_curves.png"
        return plot_finetune_curves(self.finetune_records(task, h, seed, "PDPO"), last / "training_curves_stages.png")

    def finetune_records(self, task: str, h: int, seed: int, label: str) -> dict[str, list[dict]]:
        """The ``progress.jsonl`` records of each fine-tuning stage of one policy, by label, for
        ``plot_finetune_curves``. Stage 2 is drawn from where it starts in env steps (stage 1's
        best checkpoint) and after the whole of stage 1 in wall time (the time it cost)."""
        def read(run: Path) -> list[dict]:
            return [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]

        first = read(self.finetune_dir(task, h, seed))
        if 2 not in self.ft_stages:
            return {label: first}
        best = self.finetune_dir(task, h, seed) / "checkpoints" / "best" / "pretrained_model" / FINETUNE_CONFIG
        start = json.loads(best.read_text())["env_steps_done"]
        spent = max(r.get("time/wall_s") or 0.0 for r in first)
        second = [{**r, "env_steps": r["env_steps"] + start,
                   "time/wall_s": None if r.get("time/wall_s") is None else r["time/wall_s"] + spent}
                  for r in read(self.finetune_dir(task, h, seed, 2))]
        second[0]["time/wall_s"] = spent  # its starting validation
        return {f"{label}, stage 1": first, f"{label}, stage 2": second}

    def figures(self, task: str) -> tuple[Stage | None, list[tuple[str, Path]]]:
        """Storyboard and multimodality of the PDPO policy (none without one), and the learning
        curves: (caption, image) of this run's fine-tuning, or each shipped model's card curve."""
        from .data.hub import CURVE_FILE
        from .evaluation.figures import record_snapshots
        from .evaluation.plots import plot_finetune_curves, plot_multimodality, plot_storyboard

        out = self.figures_dir(task)
        seed = self.cfg.seeds[0]
        if self.cfg.models is None:
            copies = []
            curves = [("Fine-tuning: training success rate and average episode reward against environment steps "
                       "(lines: training episodes, smoothed; markers: deterministic validation).", out / "finetune_curves.png")]
        else:  # each shipped model's curve, from its card
            copies = [(ev.policy / CURVE_FILE, out / f"curve_{ev.name}.png", label)
                      for label, ev in self.shipped(task) if (ev.policy / CURVE_FILE).exists()]
            curves = [(f"{label}: the learning curve from its model card (`{src.parent.name}`).", dst) for src, dst, label in copies]
        shown = self.figure_policy(task)
        if shown is None:
            return None, []
        policy = shown.policy
        episode_seed = split_seeds("test", self.cfg.figure_episode + 1)[-1]
        paths = {"storyboard": out / "storyboard.png", "multimodality": out / "multimodality.png"}
        steps = ",".join(map(str, self.cfg.figure_steps))
        argv = ["python", "-m", "lerobot_crowdnav.evaluation.figures", f"--policy.path={policy}", *self._env_flags(task),
                f"--seed={episode_seed}", f"--steps={steps}", f"--n_samples={self.cfg.figure_samples}", f"--output_dir={out}"]
        label = FINETUNED_LABEL.get(shown.horizon, f"PDPO (H = {shown.horizon}, fine-tuned)")

        def run() -> None:
            sim_cfg = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve()
            snaps = record_snapshots(policy, sim_cfg, episode_seed, self.cfg.figure_steps, self.cfg.figure_samples,
                                     device=self.device or "cpu")
            walls = sim_cfg.arena_size if sim_cfg.bounded else None
            plot_storyboard(snaps, paths["storyboard"], sim_cfg.sensing_range, sim_cfg.dt, arena_size=walls,
                            title=f"{TITLE[task]}, test episode {episode_seed}: {label}")
            plot_multimodality(snaps, paths["multimodality"], sim_cfg.sensing_range, sim_cfg.dt, arena_size=walls,
                               title=f"{TITLE[task]}, test episode {episode_seed}: {self.cfg.figure_samples} chunks "
                                     "sampled per observation")
            for src, dst, _ in copies:
                shutil.copyfile(src, dst)
            if self.cfg.models is not None:
                return
            runs = {}
            for h in sorted(self.cfg.horizons, reverse=True):
                run_label = FINETUNED_LABEL.get(h, f"PDPO (H = {h})").replace(", fine-tuned", "")
                runs.update(self.finetune_records(task, h, seed, run_label))
            plot_finetune_curves(runs, curves[0][1])

        done = (all(p.exists() for p in [*paths.values(), *(image for _, image in curves)]) and not self.cfg.rerun_eval
                and self.cfg.models is None)  # shipped models may have been replaced: redraw (seconds)
        return self._stage(f"figures {SHORT[task]}", argv, done, run), curves

    def figures_dir(self, task: str) -> Path:
        return self.root / "figures" / SHORT[task]

    # -- the whole job -------------------------------------------------------------------------
    def train(self, task: str) -> dict[tuple[int | None, int], tuple[Stage | None, Stage]]:
        """Demonstrations, then every PDPO policy's pretraining and fine-tuning, (H, seed) ->
        stages, and CrowdNav++'s PPO run, (None, seed) -> (None, stage)."""
        trained: dict[tuple[int | None, int], tuple[Stage | None, Stage]] = {}
        if self.cfg.horizons:
            self.collect(task)
        for seed in self.cfg.seeds:
            for h in self.cfg.horizons:
                pretrain = self.pretrain(task, h, seed)
                trained[h, seed] = (pretrain, [self.finetune(task, h, seed, n) for n in self.ft_stages][-1])
            if self.cfg.crowdnavpp_env_steps:
                trained[None, seed] = (None, self.train_crowdnavpp(task, seed))
        return trained

    def run(self) -> Path:
        start = time.perf_counter()
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / "main_config.json").write_text(json.dumps(draccus.encode(self.cfg), indent=2, default=str))
        tasks = []
        for task in self.cfg.tasks:
            trained = self.train(task) if self.cfg.models is None else {}
            methods = []
            for label, evals in self.methods(task):
                evaluated = []
                for ev in evals:
                    stage = self.evaluate(task, ev)
                    pretrain, finetune = trained.get((ev.horizon, ev.seed), (None, None))
                    evaluated.append(Evaluated(ev.name, self.eval_dir(task, ev.name), stage, ev.policy, ev.seed,
                                               pretrain, finetune if ev.finetuned else None, ev.shipped))
                methods.append(Method(label, evaluated))
            if self.cfg.models is None:
                self.push(task)
            figures, curves = self.figures(task)
            bounded = CrowdSimConfig(task=task, preset=self.cfg.preset).resolve().bounded
            shown = {method.label for method in methods}
            missing = [name for label, name in self.shipped_names(task).items() if label not in shown] if self.cfg.models else []
            tasks.append(TaskResults(task, TITLE[task], SHORT[task], methods, self.figures_dir(task), figures, curves,
                                     bounded=bounded, missing_models=missing))
        c = self.cfg
        budget = None if c.models is not None else Budget(
            c.run, c.preset, c.demos, c.bc_steps, c.bc_epochs, c.bc_batch_size, c.ft_env_steps, list(c.seeds), c.test_episodes,
            c.crowdnavpp_env_steps, c.ft2_env_steps)
        report = write_report(ReportInputs(self.root, budget, tasks, list(self.stages.values()),
                                           time.perf_counter() - start, c.test_episodes, c.preset, c.models))
        print(f"[main] report: {report}")
        return report


def main(argv: list[str] | None = None) -> None:
    command = " ".join(["lerobot-crowdnav-main", *(sys.argv[1:] if argv is None else argv)])
    run_cli(MainConfig, lambda cfg: Pipeline(cfg, command).run(), argv,
            "rerun the same command to resume (complete stages are skipped)")


if __name__ == "__main__":
    main()
