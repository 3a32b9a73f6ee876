"""The PPO loop is policy-agnostic: a tiny Gaussian actor-critic, written here against the
protocol of lerobot_crowdnav.rl.agent and touching nothing of the trainer, learns a trivial task
with the same collect/update code as diffusion PPO; its GRU variant trains on per-env sequences
and learns what a feed-forward policy cannot (remember a cue). This module also makes the MLP a
policy family (rl/families.py) of lerobot-crowdnav-train-ppo, which then trains, checkpoints,
resumes and publishes it with no change elsewhere."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from accelerate import Accelerator
from safetensors.torch import load_file, save_file
from torch import nn

from lerobot_crowdnav.checkpoint_files import POLICY_CONFIG, WEIGHTS
from lerobot_crowdnav.data.hub import policy_card, register_model_card
from lerobot_crowdnav.rl.agent import Scores, Step, check_actor_critic
from lerobot_crowdnav.rl.config import DiffusionPPOConfig, PPOConfig
from lerobot_crowdnav.rl.families import Family, register
from lerobot_crowdnav.rl.loop import Collector, update
from lerobot_crowdnav.rl.ppo import RunningRewardScaler
from lerobot_crowdnav.rl.run_log import RunLog, read_progress

HORIZON = 4


class CueEnv:
    """A batched env: the goal g = +-1 is shown at an episode's first step (``cue_always``: at
    every step); obs = [cue, t / H]; reward -(a - g)^2 per step; episodes time out after H steps."""

    def __init__(self, num_envs: int, cue_always: bool):
        self.num_envs, self.cue_always = num_envs, cue_always

    def _obs(self) -> np.ndarray:
        cue = self.g if self.cue_always else np.where(self.t == 0, self.g, 0.0)
        return np.stack([cue, self.t / HORIZON], axis=1).astype(np.float32)

    def reset(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.g = self.rng.choice([-1.0, 1.0], self.num_envs)
        self.t = np.zeros(self.num_envs)
        return self._obs(), {}

    def step(self, action: np.ndarray):
        reward = -((action[:, 0] - self.g) ** 2)
        self.t += 1
        trunc = self.t >= HORIZON
        info = {"final_obs": self._obs()}
        self.g = np.where(trunc, self.rng.choice([-1.0, 1.0], self.num_envs), self.g)
        self.t[trunc] = 0
        return self._obs(), reward, np.zeros(self.num_envs, bool), trunc, info


class GaussianActorCritic(nn.Module):
    """A Gaussian policy and a value head on a shared MLP (or GRU, ``recurrent``) core."""

    n_parts = 1

    def __init__(self, obs_dim: int, recurrent: bool, hidden: int = 32, act_dim: int = 1):
        super().__init__()
        self.recurrent, self.hidden = recurrent, hidden
        self.dims = {"obs_dim": obs_dim, "recurrent": recurrent, "hidden": hidden, "act_dim": act_dim}
        self.core = nn.GRUCell(obs_dim, hidden) if recurrent else nn.Sequential(nn.Linear(obs_dim, hidden), nn.Tanh())
        self.mu, self.value_head = nn.Linear(hidden, act_dim), nn.Linear(hidden, 1)
        self.log_std = nn.Parameter(torch.full((act_dim,), -0.5))

    def initial_memory(self, num_envs: int):
        return torch.zeros(num_envs, self.hidden) if self.recurrent else None

    def param_groups(self):
        return {"actor": [*self.core.parameters(), *self.mu.parameters(), self.log_std],
                "critic": list(self.value_head.parameters())}

    def _features(self, obs, memory, starts):
        """obs (L, M, D), starts (L, M) -> features (L, M, hidden) and the last memory."""
        if not self.recurrent:
            return self.core(obs), None
        out = []
        for t in range(obs.shape[0]):
            memory = self.core(obs[t], memory * ~starts[t, :, None])
            out.append(memory)
        return torch.stack(out), memory

    @torch.no_grad()
    def act(self, obs, memory, explore, generator):
        h, memory = self._features(obs[None], memory, torch.zeros(1, obs.shape[0], dtype=torch.bool))
        action = self.mu(h[0])
        if explore:
            action = action + self.log_std.exp() * torch.randn(action.shape, generator=generator)
        return Step(action, {"obs": obs, "action": action}, memory)

    def forward(self, samples, memory, episode_start):
        h, _ = self._features(samples["obs"], memory, episode_start)
        dist = torch.distributions.Normal(self.mu(h), self.log_std.exp())
        return Scores(dist.log_prob(samples["action"]).sum(-1, keepdim=True), self.value_head(h).squeeze(-1),
                      dist.entropy().sum(-1))

    @torch.no_grad()
    def value(self, obs, memory):
        h, _ = self._features(obs[None], memory, torch.zeros(1, obs.shape[0], dtype=torch.bool))
        return self.value_head(h[0]).squeeze(-1)

    def save(self, path: Path) -> None:
        path.mkdir(parents=True, exist_ok=True)
        (path / POLICY_CONFIG).write_text(json.dumps({"type": "gaussian_mlp", **self.dims}))
        save_file({k: v.contiguous() for k, v in self.state_dict().items()}, str(path / WEIGHTS))


def deterministic_return(agent, cue_always: bool, n: int = 256) -> float:
    """Mean reward per step of one episode per env, without exploration noise."""
    env = CueEnv(n, cue_always)
    obs, _ = env.reset(seed=123)
    memory, total = agent.initial_memory(n), 0.0
    for _ in range(HORIZON):
        step = agent.act(torch.as_tensor(obs), memory, False, None)
        obs, reward, *_ = env.step(step.action.numpy())
        memory, total = step.memory, total + reward.mean()
    return total / HORIZON


@pytest.mark.parametrize("recurrent", [False, True], ids=["mlp_flat_minibatches", "gru_sequence_minibatches"])
def test_a_second_actor_critic_learns_with_the_same_ppo_loop(recurrent):
    torch.manual_seed(0)
    cue_always = not recurrent  # the GRU must remember the cue: a feed-forward policy cannot
    agent = GaussianActorCritic(2, recurrent)
    cfg = PPOConfig(n_steps=16, batch_size=128, update_epochs=4, actor_lr=3e-3, critic_lr=3e-3, gamma=0.9,
                    clip_ploss_coef=0.2, target_kl=0.0, n_critic_warmup_itr=1)
    env = CueEnv(32, cue_always)
    collector = Collector(env, agent, RunningRewardScaler(env.num_envs, cfg.gamma), torch.Generator().manual_seed(0))
    collector.reset(seed=0)
    optimizers = {name: torch.optim.Adam(params, lr=cfg.actor_lr) for name, params in agent.param_groups().items()}
    rng, acc = np.random.default_rng(0), Accelerator(cpu=True)
    before = deterministic_return(agent, cue_always)
    for iteration in range(60):
        ro = collector.collect(agent, cfg.n_steps)
        assert len(ro.timeouts) == ro.final_obs.shape[0] > 0
        if recurrent:
            assert ro.memory0.shape == (32, agent.hidden) and ro.starts[0].any()
        stats = update(agent, agent, ro, cfg, optimizers, rng, acc, train_actor=iteration >= cfg.n_critic_warmup_itr)
    after = deterministic_return(agent, cue_always)
    # Remembering the cue is worth more than the best memoryless policy (a = 0 after the cue step: -0.75).
    assert after > max(before + 0.4, -0.75 + 0.3 if recurrent else -0.2), (before, after)
    assert stats["explained_variance"] > 0.2 and "entropy" in stats


# -- the MLP as a policy family of lerobot-crowdnav-train-ppo: this module is all it takes ----------
@dataclass
class GaussianPPOConfig(PPOConfig):
    """The family's recipe: tiny, so that a test run is quick."""

    n_steps: int = 8
    batch_size: int = 16
    update_epochs: int = 2
    n_critic_warmup_itr: int = 1


def build_gaussian_agent(source: Path | None, sim_cfg, seed: int) -> GaussianActorCritic:
    if source is None:
        torch.manual_seed(seed)
        return GaussianActorCritic(sim_cfg.obs_dim, False, act_dim=2)
    config = json.loads((source / POLICY_CONFIG).read_text())
    if config.pop("type") != "gaussian_mlp" or config["obs_dim"] != sim_cfg.obs_dim:
        raise ValueError(f"{source} is not a gaussian_mlp policy for this env")
    agent = GaussianActorCritic(**config)
    agent.load_state_dict(load_file(str(source / WEIGHTS)))
    return agent


register(Family("gaussian_mlp", build_gaussian_agent, GaussianPPOConfig, {"num_envs": 4, "seed": 3}))


@register_model_card("gaussian_mlp")
def gaussian_card(pretrained, repo_id, config, metrics=None, recipe=None, curve=None):
    from huggingface_hub import ModelCard

    return ModelCard(f"# {repo_id}\n\nA Gaussian MLP policy ({config['hidden']} hidden units).\n")


def train_gaussian(out: Path, *extra: str) -> list[dict]:
    from lerobot_crowdnav.rl.train_ppo import main

    main(["--policy.type=gaussian_mlp", f"--output_dir={out}", "--val.n_episodes=2", "--save_freq=32", *extra])
    return [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]


def tensorboard_scalars(out: Path, tag: str) -> list[tuple[int, float]]:
    """(step, value) of one tag as TensorBoard shows it: restarts purged."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(out / "tensorboard"))
    events.Reload()
    return [(e.step, e.value) for e in events.Scalars(tag)]


def test_a_resumed_run_log_keeps_the_history_up_to_the_checkpoint_and_drops_what_came_after(tmp_path):
    """The interrupted run logged iterations 0-3 (32 env steps each) but was killed after its
    checkpoint at iteration 2 (env step 64); the resumed run logs iterations 3 and 4 again.
    TensorBoard's step is the env step, so the purge must count in env steps too."""
    no_wandb = SimpleNamespace(enable=False)
    interrupted = RunLog(tmp_path, True, 0, False, no_wandb, {})
    for i in range(4):
        interrupted.log({"iteration": i, "env_steps": 32 * i, "x": float(i)})
    interrupted.writer.close()  # killed: no training curves
    time.sleep(1)  # event files are named by the second they were opened in and read in name order
    resumed = RunLog(tmp_path, True, 64, True, no_wandb, {})
    for i in (3, 4):
        resumed.log({"iteration": i, "env_steps": 32 * i, "x": 10.0 * i})
    resumed.writer.close()
    assert tensorboard_scalars(tmp_path, "x") == [(0, 0.0), (32, 1.0), (64, 2.0), (96, 30.0), (128, 40.0)]
    assert [r["x"] for r in read_progress(tmp_path)] == [0.0, 1.0, 2.0, 30.0, 40.0]
    # killed while appending a record: the cut line is left out, and the next resume rewrites the file whole
    progress = tmp_path / "progress.jsonl"
    progress.write_text(progress.read_text() + '{"iteration": 5, "env_st')
    assert [r["x"] for r in read_progress(tmp_path)] == [0.0, 1.0, 2.0, 30.0, 40.0]
    again = RunLog(tmp_path, True, 128, True, no_wandb, {})
    again.writer.close()
    assert progress.read_text().endswith('"x": 40.0}\n') and not list(tmp_path.glob(".*"))
    progress.write_text('{"iteration": 0\n' + progress.read_text())  # damaged before its end: an error
    with pytest.raises(ValueError, match="progress.jsonl:1 is not a JSON record"):
        read_progress(tmp_path)


def test_a_registered_family_trains_checkpoints_and_resumes_through_the_ppo_cli(tmp_path):
    straight = train_gaussian(tmp_path / "a", "--env_steps=96")
    path = tmp_path / "a" / "checkpoints" / "last" / "pretrained_model"
    settings = json.loads((path / "train_ppo_config.json").read_text())
    # the family's recipe gave the defaults
    assert settings["policy"]["type"] == "gaussian_mlp" and settings["ppo"]["n_steps"] == 8
    assert (settings["num_envs"], settings["seed"], settings["env_steps_done"]) == (4, 3, 96)
    assert [r.get("critic_warmup") for r in straight] == [None, 1.0, 0.0, 0.0]
    first = train_gaussian(tmp_path / "b", "--env_steps=32")
    assert first[-1]["env_steps"] == 32
    resumed = train_gaussian(tmp_path / "b", "--env_steps=96", "--resume=true")
    for i in (2, 3):
        assert resumed[i]["rollout_digest"] == straight[i]["rollout_digest"]
        assert resumed[i]["loss/policy_loss"] == straight[i]["loss/policy_loss"]
        assert resumed[i]["loss/value_loss"] == straight[i]["loss/value_loss"]
    resumed_path = tmp_path / "b" / "checkpoints" / "last" / "pretrained_model"
    assert (path / WEIGHTS).read_bytes() == (resumed_path / WEIGHTS).read_bytes()  # the last update too
    # TensorBoard keeps the first run's iteration (env step 32) and has the straight run's curve
    assert tensorboard_scalars(tmp_path / "b", "loss/value_loss") == tensorboard_scalars(tmp_path / "a", "loss/value_loss")
    assert [step for step, _ in tensorboard_scalars(tmp_path / "b", "loss/value_loss")] == [32, 64, 96]
    assert "A Gaussian MLP policy (32 hidden units)" in str(policy_card(path, "local/gaussian"))
    (path / POLICY_CONFIG).write_text(json.dumps({"type": "unknown"}))
    with pytest.raises(ValueError, match="'unknown' policy, which has no model card"):
        policy_card(path, "local/unknown")


def test_an_agent_is_checked_against_the_protocol_and_the_ppo_settings():
    agent = GaussianActorCritic(2, False)
    but_save = {m: getattr(agent, m) for m in ("recurrent", "n_parts", "initial_memory", "act", "forward", "value",
                                               "param_groups")}
    with pytest.raises(TypeError, match="it lacks save$"):  # the trainer would fail at its first checkpoint
        check_actor_critic(SimpleNamespace(**but_save), PPOConfig())
    check_actor_critic(agent, PPOConfig())
    with pytest.raises(ValueError, match="clip_per_part has shape \\(3,\\)"):  # one clip per scored part
        check_actor_critic(agent, DiffusionPPOConfig(ft_denoising_steps=3))
    agent.param_groups = lambda: {"actor": list(agent.parameters())}  # a shared trunk: nothing to warm up
    with pytest.raises(ValueError, match="n_critic_warmup_itr=2"):
        check_actor_critic(agent, PPOConfig())
    check_actor_critic(agent, PPOConfig(n_critic_warmup_itr=0))


def test_a_family_module_is_found_by_its_name(tmp_path, monkeypatch):
    """``families.get(T)`` imports the module ``<families.PACKAGE>.T`` (rl/T.py): a new family is that
    one file. Here the package is a temporary one, so that nothing is written into the project."""
    import sys

    from lerobot_crowdnav.rl import families

    assert "crowdnavpp" in families.known()  # rl/crowdnavpp.py, the built-in family
    pkg = tmp_path / "family_pkg_test"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "tiny.py").write_text("from lerobot_crowdnav.rl.families import Family, register\n\n"
                                 "register(Family('tiny', lambda source, sim_cfg, seed: None))\n")
    (pkg / "helper.py").write_text("")  # a module that registers nothing
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(families, "PACKAGE", pkg.name)
    monkeypatch.setattr(families, "_FAMILIES", {})
    assert families.known() == ["tiny"]  # read from the sources, nothing imported yet
    assert f"{pkg.name}.tiny" not in sys.modules
    assert families.get("tiny").name == "tiny"
    for name in ("helper", "nowhere", "../tiny", "tiny.x"):
        with pytest.raises(ValueError, match=f"trains tiny \\(the family T is registered by the module {pkg.name}.T"):
            families.get(name)


class MiscountedParts(GaussianActorCritic):
    """Declares one scored part, scores two."""

    def forward(self, samples, memory, episode_start):
        scores = super().forward(samples, memory, episode_start)
        return scores._replace(logp=torch.cat([scores.logp, scores.logp], -1))


def test_scores_of_another_shape_than_n_parts_are_refused_by_the_update():
    """The clip and advantage weights have ``n_parts`` entries (checked where the agent is built);
    the update checks the scores' last dimension against it before it uses them."""
    agent = MiscountedParts(2, False)
    cfg = PPOConfig(n_steps=4, batch_size=16, update_epochs=1, n_critic_warmup_itr=0)
    check_actor_critic(agent, cfg)  # what it declares fits the settings
    env = CueEnv(4, True)
    collector = Collector(env, agent, None, torch.Generator().manual_seed(0))
    collector.reset(seed=0)
    ro = collector.collect(agent, cfg.n_steps)
    optimizers = {name: torch.optim.Adam(params) for name, params in agent.param_groups().items()}
    with pytest.raises(ValueError, match="scored a decision as 2 parts, not its n_parts=1"):
        update(agent, agent, ro, cfg, optimizers, np.random.default_rng(0), Accelerator(cpu=True), train_actor=True)


def test_a_sampling_stream_saved_on_another_device_type_continues_from_a_seed_derived_from_it():
    """A run moved between a CPU and a GPU machine resumes: CUDA generators save 16 bytes, CPU ones
    5,056, and neither loads the other's. The same saved state gives the same stream, another one
    another; a state of this device type continues exactly."""
    from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

    def loaded(state: dict) -> torch.Tensor:
        collector = Collector(CrowdNavVectorEnv(2), GaussianActorCritic(2, False), None, torch.Generator().manual_seed(1))
        collector.reset(seed=0)
        collector.load_state_dict(state)
        return torch.rand(8, generator=collector.generator)

    source = Collector(CrowdNavVectorEnv(2), GaussianActorCritic(2, False), None, torch.Generator().manual_seed(7))
    source.reset(seed=0)
    state = source.state_dict()
    assert torch.equal(loaded(state), torch.rand(8, generator=source.generator))
    cuda_like = {**state, "torch": list(range(16))}
    assert torch.equal(loaded(cuda_like), loaded(cuda_like))
    assert not torch.equal(loaded(cuda_like), loaded({**state, "torch": list(range(1, 17))}))


def test_training_mode_survives_env_flags_and_the_intrusion_test_may_change_on_resume():
    """Both PPO CLIs train with the intrusion test off even when an --env.* flag is given (draccus
    then builds ``env`` from its type's defaults), and switching it is no conflict on resume: it
    changes the metrics only."""
    import draccus

    from lerobot_crowdnav.rl.checkpoints import resume_conflicts
    from lerobot_crowdnav.rl.finetune import FinetuneConfig
    from lerobot_crowdnav.rl.train_ppo import TrainPPOConfig

    for cls in (FinetuneConfig, TrainPPOConfig):
        for args in ([], ["--env.task=CrowdNav-v0"], ["--env.preset=crowdnavpp", "--env.num_humans=10"]):
            assert draccus.parse(cls, args=args).env.compute_intrusion is False
        assert draccus.parse(cls, args=["--env.compute_intrusion=true"]).env.compute_intrusion is True
    saved = {"env": {"task": "CrowdNav-v0", "compute_intrusion": True}, "seed": 1}
    now = {"env": {"task": "CrowdNav-v0", "compute_intrusion": False}, "seed": 1}
    assert resume_conflicts(saved, now, 1) == []
    assert resume_conflicts(saved, {**now, "env": {**now["env"], "task": "BoundedCrowdNav-v0"}}, 1) == ["env"]


def test_episode_stats_give_rates_mean_return_and_its_prediction_penalty_part():
    from lerobot_crowdnav.rl.validation import episode_stats

    episodes = [{"event": "success", "return": 20.0, "prediction_penalty": -2.0, "length": 40},
                {"event": "human_collision", "return": -25.0, "prediction_penalty": -6.0, "length": 10},
                {"event": "timeout", "return": 2.0, "prediction_penalty": -1.0, "length": 196},
                {"event": "human_collision", "return": -21.0, "prediction_penalty": -3.0, "length": 6}]
    stats = episode_stats(episodes, Accelerator(cpu=True))
    assert stats["train/episodes"] == 4
    assert stats["train/success_rate"] == 0.25 and stats["train/human_collision_rate"] == 0.5
    assert stats["train/timeout_rate"] == 0.25 and stats["train/wall_collision_rate"] == 0.0
    assert stats["train/episode_return"] == pytest.approx(-6.0)
    assert stats["train/prediction_penalty"] == pytest.approx(-3.0)
    assert stats["train/episode_length"] == pytest.approx(63.0)
    assert episode_stats([], Accelerator(cpu=True)) == {"train/episodes": 0}
