"""The main job's settings: ``MainConfig`` (every ``lerobot-crowdnav-main`` flag) and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..evaluation.generalization import TRAINED, check_crowds
from ..sim.config import CROWDS, ORCA_ROBOTS, SEED_SPLITS, TASKS

# The trained models shipped in the repository (hub format: models/<org>/<name>), made by the
# recipes (docs/recipes.md).
SHIPPED_MODELS = Path(__file__).resolve().parents[2] / "models" / "lerobot-crowdnav"


@dataclass
class MainConfig:
    # Run name: everything goes to <output_root>/<run>/.
    run: str = "main"
    # Folder of the runs (<output_root>/<run>/).
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
    # The ORCA robot that demonstrates and labels the DAgger rounds (look_ahead | current_state);
    # null: the preset's (paper: look_ahead, CrowdNav++'s CrowdSimPred robot; crowdnavpp:
    # current_state). current_state in the paper preset: docs/recipes.md, "A stronger teacher".
    # Its demonstrations publish as crowdnav_orca_<task>, another robot's as
    # crowdnav_orca_<task>_<robot>.
    demonstrator: str | None = None
    # Pretraining steps of lerobot-train at bc_batch_size (see bc_epochs).
    bc_steps: int = 2000
    # > 0: pretrain for this many epochs over the demonstrations instead of bc_steps (paper: 200).
    bc_epochs: float = 0.0
    # lerobot-train batch size (paper: 128).
    bc_batch_size: int = 128
    # lerobot-train data-loader workers: with the plugin's fast loader, 0 is fastest on 2 cores.
    bc_num_workers: int = 0
    # Chunk horizons: 5 = PDPO, 1 = the "w/o action chunk" ablation ([] with a CrowdNav++ budget:
    # no PDPO, no demonstrations).
    horizons: list[int] = field(default_factory=lambda: [5, 1])
    # Diffusion-PPO budget per policy in env steps (paper: about 12 M).
    ft_env_steps: int = 16384
    # Diffusion PPO: envs per process.
    ft_num_envs: int = 32
    # Diffusion PPO: rollout length per env and iteration.
    ft_n_steps: int = 64
    # Minibatch in env steps, each with its 10 denoising transitions (paper: 500).
    ft_batch_size: int = 500
    # Diffusion PPO: validation episodes per reading (the first validation seeds).
    ft_val_episodes: int = 20
    # Diffusion PPO: a validation reading every this many env steps.
    ft_val_freq: int = 4096
    # DAgger rounds in pretraining (lerobot_crowdnav.data.dagger; [] = plain behaviour cloning, the
    # paper): at each of these lerobot-train steps (below the BC budget) the policy trained so far
    # drives bc_dagger_episodes learner episodes, the ORCA demonstrator labels every state it
    # visits with its chunk from there, and lerobot-train resumes on the aggregate (each policy
    # aggregates into its own copy of the demonstrations, datasets/<task>_h<H>_s<seed>_dagger).
    bc_dagger_at: list[int] = field(default_factory=list)
    # Learner episodes per DAgger round.
    bc_dagger_episodes: int = 500
    # Further flags of every lerobot-train run (e.g. ["--policy.noise_draws=4"]): a recipe's own settings.
    bc_args: list[str] = field(default_factory=list)
    # Further flags of every lerobot-crowdnav-finetune run (e.g. ["--ppo.update_epochs=3"]).
    ft_args: list[str] = field(default_factory=list)
    # A second diffusion-PPO stage per policy (0: none): it continues from a checkpoint of the first
    # stage (critic included, ft2_from) for ft2_env_steps env steps with the first stage's flags, then
    # ft2_args on top (later flags win), e.g. ["--ppo.freeze_encoder=false"]: the recipes train the
    # encoder once the cheap frozen-encoder stage has plateaued (docs/recipes.md). Its training
    # episodes and sampling noise come from seeds of their own (seed + 1, env seed 520,000,000).
    ft2_env_steps: int = 0
    # Flags of the second stage only, after ft_args (later flags win).
    ft2_args: list[str] = field(default_factory=list)
    # The first stage's checkpoint the second continues from: `last` (its whole budget, one
    # continuous fine-tuning as the paper runs it) or `best` (its best 100-episode validation
    # reading, which on a plateau picks noise and drops the env steps after it; the plain-BC recipes').
    ft2_from: str = "last"
    # Which checkpoint of an RL run is the policy (PDPO's last diffusion-PPO stage, CrowdNav++'s PPO
    # run). 0: the trainer's `best`, the best validation reading (the paper's; 100 episodes read +-9
    # points, too coarse to rank a plateau's checkpoints). k > 0: the k saved checkpoints with the
    # best readings (ties: the earlier) each run again on the first select_episodes validation seeds,
    # and the best of those (ties: the earlier) is the policy; the test seeds never take part.
    select_top: int = 0
    # Validation episodes per candidate checkpoint (with select_top > 0).
    select_episodes: int = 1000
    # The CrowdNav++ (Const. Vel.) baseline: PPO env steps per task of CrowdNav++'s network trained
    # from scratch by lerobot-crowdnav-train-ppo with the reference's PPO settings (reference: 10 M;
    # docs/crowdnavpp.md); 0 = no CrowdNav++ row.
    crowdnavpp_env_steps: int = 0
    # Further flags of that run (e.g. ["--val.freq=200000"]).
    crowdnavpp_args: list[str] = field(default_factory=list)
    # Training seeds (pretraining and fine-tuning); tables show mean +- std over them.
    seeds: list[int] = field(default_factory=lambda: [1000])
    # Test episodes per method, the first seeds of the test split (paper: 500).
    test_episodes: int = 500
    # Figures: the test episode drawn (index into the test seeds).
    figure_episode: int = 0
    # Figures: the steps of that episode drawn.
    figure_steps: list[int] = field(default_factory=lambda: [0, 4, 8, 12, 16])
    # Figures: action chunks sampled per drawn step.
    figure_samples: int = 32
    # Crowds every row is evaluated in on the test seeds (keys of sim.config.CROWDS): orca, the
    # crowd every policy is trained in (the results tables), and crowds they never saw,
    # reactive_orca (humans that see the robot), social_force, reactive_social_force: the report's
    # generalization table (evaluation/generalization.py). [] or [orca]: the trained crowd only.
    crowds: list[str] = field(default_factory=lambda: list(CROWDS))
    # Organization of the hub-format repositories (<run>/hub/{datasets,models}/<org>/...).
    hub_org: str = "local"
    # Torch device for training and evaluation (default: training on cuda when available, else
    # cpu; evaluation on cpu). A checkpoint trained on one device evaluates on any.
    device: str | None = None
    # Evaluate again even when metrics exist (the tables come out identical: evaluation is deterministic).
    rerun_eval: bool = False

    def validate(self) -> None:
        bad = [t for t in self.tasks if t not in TASKS]
        if bad or not self.tasks:
            raise ValueError(f"--tasks must be a non-empty subset of {list(TASKS)}, got {self.tasks}")
        check_crowds(self.crowds, allow_empty=True)
        if self.demonstrator is not None and self.demonstrator not in ORCA_ROBOTS:
            raise ValueError(f"--demonstrator must be one of {list(ORCA_ROBOTS)} or null, got {self.demonstrator!r}")
        if any(h < 1 for h in self.horizons):
            raise ValueError(f"--horizons must be positive, got {self.horizons}")
        if self.ft2_from not in ("best", "last"):
            raise ValueError(f"--ft2_from must be 'best' or 'last', got {self.ft2_from!r}")
        if self.crowdnavpp_env_steps < 0 or self.ft2_env_steps < 0 or self.select_top < 0:
            raise ValueError("--crowdnavpp_env_steps, --ft2_env_steps and --select_top must be >= 0")
        val_size = SEED_SPLITS["val"][1] - SEED_SPLITS["val"][0]
        if not 1 <= self.select_episodes <= val_size:
            raise ValueError(f"--select_episodes must be in [1, {val_size}] (the validation seeds), got {self.select_episodes}")
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

    @property
    def extra_crowds(self) -> list[str]:
        """The crowds of the generalization table besides the trained one (none: no table)."""
        return [c for c in self.crowds if c != TRAINED]
