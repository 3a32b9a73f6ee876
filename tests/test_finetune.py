"""Diffusion-PPO fine-tuning: the DPPO arithmetic, chain log-probabilities, the trainer's first
ratio, checkpoints that load and evaluate, exact resume, bad input and the two-process path."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot_policy_pdpo import PDPOPolicy

from lerobot_crowdnav.data.hub import policy_card
from lerobot_crowdnav.evaluation.eval import main as eval_main
from lerobot_crowdnav.rl import finetune as ft
from lerobot_crowdnav.rl.config import DiffusionPPOConfig
from lerobot_crowdnav.checkpoint_files import CRITIC
from lerobot_crowdnav.rl.dppo import ValueHead, load_agent, transition_log_prob
from lerobot_crowdnav.rl.loop import Collector, Columns, update
from lerobot_crowdnav.rl.ppo import RunningRewardScaler, clip_coefficients, denoising_discounts, gae
from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

from conftest import make_tiny_checkpoint, small_pdpo_config

BIN = Path(sys.executable).parent
TINY_RUN = ["--num_envs=4", "--ppo.n_steps=8", "--ppo.batch_size=16", "--ppo.update_epochs=2",
            "--ppo.n_critic_warmup_itr=1", "--val.n_episodes=2", "--save_freq=32", "--seed=3"]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory) -> Path:
    return make_tiny_checkpoint(tmp_path_factory.mktemp("ft"))


def run(pretrained: Path, out: Path, *extra: str) -> list[dict]:
    ft.main([f"--policy.path={pretrained}", f"--output_dir={out}", *TINY_RUN, *extra])
    return [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]


# -- DPPO arithmetic ------------------------------------------------------------------------------
def test_clip_schedule_and_denoising_discount_values():
    c = clip_coefficients(10, 0.001, 0.01, 3.0)
    assert c[0] == pytest.approx(0.001) and c[-1] == pytest.approx(0.01)
    assert c[5] == pytest.approx(0.001 + 0.009 * (math.exp(3 * 5 / 9) - 1) / (math.exp(3) - 1))
    assert np.all(np.diff(c) > 0)
    assert clip_coefficients(1, 0.001, 0.01, 3.0).tolist() == [0.01]
    # rate 0 is the exponential's limit, a straight line (0/0 in the formula otherwise)
    np.testing.assert_allclose(clip_coefficients(4, 0.001, 0.01, 0.0), [0.001, 0.004, 0.007, 0.01])
    np.testing.assert_allclose(clip_coefficients(4, 0.001, 0.01, 1e-9), [0.001, 0.004, 0.007, 0.01], rtol=1e-5)
    d = denoising_discounts(10, 0.99)
    assert d[-1] == 1.0 and d[0] == pytest.approx(0.99**9) and d[3] == pytest.approx(0.99**6)


def test_gae_matches_a_hand_computation_with_terminations_and_truncations():
    g, lam = 0.9, 0.5
    # env 0: terminates at t=1, then a new episode runs to the end (bootstrap from V after t=2);
    # env 1: truncated at t=0 (bootstraps from its final observation's value 5), then runs on.
    r = np.array([[1.0, 2.0], [3.0, 0.0], [0.5, 1.0]])
    v = np.array([[0.2, 0.4], [0.1, 0.3], [0.6, 0.7]])
    nv = np.array([[0.1, 5.0], [9.9, 0.7], [0.8, 0.9]])  # 9.9 must be ignored (termination)
    term = np.array([[0, 0], [1, 0], [0, 0]], float)
    done = np.array([[0, 1], [1, 0], [0, 0]], float)
    adv, ret = gae(r, v, nv, term, done, g, lam)
    # env 0 by hand
    d2 = 0.5 + g * 0.8 - 0.6
    d1 = 3.0 - 0.1
    d0 = 1.0 + g * 0.1 - 0.2
    a0 = [d0 + g * lam * d1, d1, d2]
    # env 1 by hand
    e2 = 1.0 + g * 0.9 - 0.7
    e1 = 0.0 + g * 0.7 - 0.3 + g * lam * e2
    e0 = 2.0 + g * 5.0 - 0.4
    np.testing.assert_allclose(adv[:, 0], a0)
    np.testing.assert_allclose(adv[:, 1], [e0, e1, e2])
    np.testing.assert_allclose(ret, adv + v)


def test_running_reward_scaler_divides_by_the_return_std_and_resets_on_done():
    s = RunningRewardScaler(2, gamma=0.5, clip=10.0)
    out = s(np.array([1.0, 2.0]), np.array([False, True]))
    # returns [1, 2]: running var from the prior (mean 0, var 1, count 1e-4) and this batch
    n = 1e-4 + 2
    mean = 1.5 * 2 / n
    var = (1e-4 + 0.25 * 2 + 1.5**2 * 1e-4 * 2 / n) / n
    np.testing.assert_allclose(out, np.array([1.0, 2.0]) / math.sqrt(var + 1e-8))
    assert s.mean == pytest.approx(mean) and s.ret.tolist() == [1.0, 0.0]
    assert np.all(np.abs(s(np.array([1e9, -1e9]), np.array([False, False]))) <= 10.0)


# -- chain log-probabilities -------------------------------------------------------------------
@pytest.mark.parametrize("actions", [None, 1, 3])
def test_chain_log_prob_equals_an_independent_computation(actions):
    cfg = small_pdpo_config(ft_denoising_steps=4, use_ema=False)
    torch.manual_seed(1)
    policy = PDPOPolicy(cfg).eval()
    state = torch.randn(3, 269)
    state[:, -20:] = (torch.rand(3, 20) < 0.5).float()
    chain = policy.sample_chain(state, generator=torch.Generator().manual_seed(0), exploration_std=0.1)
    assert chain.shape == (3, 5, 5, 2)
    z = policy.actor.encoder(state)
    logp = transition_log_prob(policy.actor, z, chain, min_std=0.1, actions=actions)

    # Independent: the schedule from its formula in float64, the Gaussian density written out.
    K = cfg.num_diffusion_steps
    s = 0.008
    x = np.linspace(0, K, K + 1)
    ac = np.cos(((x / K) + s) / (1 + s) * np.pi / 2) ** 2
    ac = ac / ac[0]
    betas = np.clip(1 - ac[1:] / ac[:-1], 0, 0.999)
    abar = np.cumprod(1 - betas)
    abar_prev = np.concatenate([[1.0], abar[:-1]])
    expected = np.zeros((3, 4))
    for i, k in enumerate(range(3, -1, -1)):
        xk = chain[:, i].double()
        eps = policy.actor.denoiser(chain[:, i], torch.full((3,), k), z).double()
        x0 = (xk / math.sqrt(abar[k]) - math.sqrt(1 / abar[k] - 1) * eps).clamp(-1, 1)
        mean = (betas[k] * math.sqrt(abar_prev[k]) * x0 + (1 - abar_prev[k]) * math.sqrt(1 - betas[k]) * xk) / (1 - abar[k])
        std = max(math.sqrt(betas[k] * (1 - abar_prev[k]) / (1 - abar[k])), 0.1)
        dens = -((chain[:, i + 1].double() - mean) ** 2) / (2 * std**2) - math.log(std) - 0.5 * math.log(2 * math.pi)
        expected[:, i] = dens.clamp(-5, 2)[:, : actions or cfg.horizon].mean(dim=(1, 2)).detach().numpy()
    np.testing.assert_allclose(logp.detach().numpy(), expected, rtol=1e-4, atol=1e-5)


def test_frozen_base_runs_the_first_steps_and_trained_nets_the_last():
    cfg = small_pdpo_config(ft_denoising_steps=5, use_ema=False)
    policy = PDPOPolicy(cfg).eval()
    state = torch.randn(2, 269)
    state[:, -20:] = 1.0
    sample = lambda: policy.sample_chain(state, generator=torch.Generator().manual_seed(0))  # noqa: E731
    before = sample()
    with torch.no_grad():
        policy.actor.denoiser.net[-1].bias.add_(0.5)  # change the trained denoiser only
    after = sample()
    torch.testing.assert_close(before[:, 0], after[:, 0])  # x_{K'} comes from the frozen steps
    assert not torch.allclose(before[:, 1:], after[:, 1:])
    assert not any(p.requires_grad for p in policy.base.parameters())


def test_ddim_with_eta_one_over_every_step_is_ddpm_and_few_steps_use_spaced_timesteps():
    """DDIM (Song et al.) with eta = 1 on all K timesteps is the DDPM posterior: same means and
    stds from the same weights. With 4 of 20 steps it visits timesteps 15, 10, 5, 0 and samples
    deterministically (eta = 0) outside fine-tuning rollouts."""
    torch.manual_seed(2)
    ddpm = PDPOPolicy(small_pdpo_config(use_ema=False, denoised_clip_value=100.0)).eval()
    ddim = PDPOPolicy(small_pdpo_config(use_ema=False, denoised_clip_value=100.0, ddim_steps=20)).eval()
    ddim.load_state_dict(ddpm.state_dict())
    x, z = torch.randn(6, 5, 2), torch.randn(6, ddpm.config.latent_dim)
    k = torch.tensor([19, 15, 10, 5, 1, 0])
    for a, b in zip(ddpm.actor.p_mean_std(x, k, z), ddim.actor.p_mean_std(x, k, z), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)

    few = PDPOPolicy(small_pdpo_config(use_ema=False, ddim_steps=4)).eval()
    assert few.actor.timestep.tolist() == [0, 5, 10, 15]
    seen = []
    hook = few.actor.denoiser.register_forward_hook(lambda m, args, out: seen.append(args[1][0].item()))
    state = torch.randn(3, 269)
    state[:, -20:] = 1.0
    chain = few.sample_chain(state, generator=torch.Generator().manual_seed(0))
    hook.remove()
    assert chain.shape == (3, 5, 5, 2) and seen == [15, 10, 5, 0]
    explore = [few.sample_chain(state, torch.Generator().manual_seed(0), exploration_std=0.1) for _ in range(2)]
    torch.testing.assert_close(*explore)  # seeded
    assert not torch.allclose(explore[0][:, -1], chain[:, -1])  # exploring adds noise
    with pytest.raises(ValueError, match="ddim_steps"):
        small_pdpo_config(ddim_steps=3)


def test_ddim_sampling_is_deterministic_given_the_start_noise():
    few = PDPOPolicy(small_pdpo_config(use_ema=False, ddim_steps=5)).eval()
    state = torch.randn(4, 269)
    state[:, -20:] = 1.0
    a = few.sample_chain(state, generator=torch.Generator().manual_seed(0))
    b = few.actor.denoise(state, a[:, 0], range(4, -1, -1), 0.0, False, torch.Generator().manual_seed(9))
    torch.testing.assert_close(a, b)  # a different generator after x_S changes nothing


def test_ddim_fine_tuning_scores_its_own_chains(pretrained, tmp_path):
    """--ppo.ddim_steps=5 --ppo.ft_denoising_steps=5: 5-step chains, log-probabilities of the
    transitions the rollout sampled, a run whose checkpoint keeps DDIM and evaluates."""
    cfg = DiffusionPPOConfig(n_steps=4, batch_size=8, update_epochs=1, ddim_steps=5, ft_denoising_steps=5)
    agent = load_agent(pretrained, cfg, seed=3).eval()
    assert agent.policy.config.ddim_steps == 5 and agent.policy.base.ddim
    collector = Collector(CrowdNavVectorEnv(2), agent, None, torch.Generator().manual_seed(0))
    collector.reset(500_000_000)
    ro = collector.collect(agent, cfg.n_steps)
    chain = ro.stored["chain"].flatten(0, 1)
    assert chain.shape[1] == 6
    z = agent.policy.actor.encoder(ro.stored["state"].flatten(0, 1))
    logp = transition_log_prob(agent.policy.actor, z, chain, cfg.min_logprob_denoising_std)
    assert logp.shape == (chain.shape[0], 5) and torch.isfinite(logp).all()
    # each sampled transition is at most 3 floored stds from the mean it is scored against
    ft = chain.shape[1] - 1
    x_k, x_prev = chain[:, :-1].flatten(0, 1), chain[:, 1:].flatten(0, 1)
    k = torch.arange(ft - 1, -1, -1).repeat(chain.shape[0])
    with torch.no_grad():
        mean, std = agent.policy.actor.p_mean_std(x_k, k, z.repeat_interleave(ft, dim=0))
    assert ((x_prev - mean).abs() <= 3 * std.clamp(min=cfg.min_sampling_denoising_std) + 1e-5).all()
    assert (logp > -5).all()
    out = tmp_path / "run"
    run(pretrained, out, "--env_steps=32", "--ppo.ddim_steps=5", "--ppo.ft_denoising_steps=5")
    path = out / "checkpoints" / "last" / "pretrained_model"
    assert PDPOPolicy.from_pretrained(path).config.ddim_steps == 5
    card = str(policy_card(path, "local/ddim"))  # the card says how the policy samples and what was trained
    assert "sampled by DDIM in 5" in card and "all 5 denoising steps trained" in card and "DDPM" not in card
    done = json.loads((path / "finetune_config.json").read_text())["env_steps_done"]
    assert f"for {done:,} environment steps (this checkpoint; the stage's budget: 32)" in card
    with pytest.raises(ValueError, match="ddim_steps"):
        load_agent(path, DiffusionPPOConfig(ft_denoising_steps=5), seed=3)
    eval_main([f"--policy.path={path}", "--eval.n_episodes=2", "--eval.split=val", f"--output_dir={tmp_path / 'eval'}"])
    with pytest.raises(SystemExit, match="fine-tuned with ddim_steps=5"):
        eval_main([f"--policy.path={path}", "--policy.ddim_steps=0", "--eval.n_episodes=2", f"--output_dir={tmp_path / 'e2'}"])
    # a BC checkpoint samples with DDIM on request
    eval_main([f"--policy.path={pretrained}", "--policy.ddim_steps=4", "--eval.n_episodes=2", f"--output_dir={tmp_path / 'e3'}"])
    with pytest.raises(SystemExit, match="ddim_steps must be 0"):
        eval_main([f"--policy.path={pretrained}", "--policy.ddim_steps=3", "--eval.n_episodes=2", f"--output_dir={tmp_path / 'e4'}"])


# -- the trainer ---------------------------------------------------------------------------------
class _Recording(torch.nn.Module):
    """The actor-critic as the update sees it, recording each minibatch's log-probabilities."""

    def __init__(self, agent):
        super().__init__()
        self.agent, self.seen = agent, []

    def forward(self, *args):
        scores = self.agent(*args)
        self.seen.append(scores.logp.detach().clone())
        return scores


def test_first_minibatch_ratio_is_exactly_one(pretrained):
    from accelerate import Accelerator

    cfg = DiffusionPPOConfig(n_steps=8, batch_size=16, update_epochs=2)
    agent = load_agent(pretrained, cfg, seed=3).eval()
    collector = Collector(CrowdNavVectorEnv(4), agent, None, torch.Generator().manual_seed(0))
    collector.reset(500_000_000)
    ro = collector.collect(agent, cfg.n_steps)
    rng = np.random.default_rng(0)
    first = torch.as_tensor(np.random.default_rng(0).permutation(32)[:16])
    before = agent(*Columns.of(ro, False, torch.device("cpu"))[first]).logp.detach()  # pre-update weights
    optimizers = {name: torch.optim.AdamW(p, lr=1e-2) for name, p in agent.param_groups().items()}
    spy = _Recording(agent)
    stats = update(spy, agent, ro, cfg, optimizers, rng, Accelerator(cpu=True), train_actor=True)
    assert len(spy.seen) == 4 and stats["update_epochs"] == 2
    assert torch.equal(spy.seen[0], before)  # bitwise: ratio exactly 1
    assert any(not torch.equal(s, before) for s in spy.seen[1:])  # later minibatches see updated weights


def test_two_iterations_write_checkpoints_that_load_and_evaluate(pretrained, tmp_path):
    out = tmp_path / "run"
    records = run(pretrained, out, "--env_steps=64")
    assert [r["iteration"] for r in records] == [0, 1, 2]
    assert records[1]["critic_warmup"] == 1.0 and records[2]["critic_warmup"] == 0.0
    for key in ("train/episodes", "loss/policy_loss", "loss/value_loss", "approx_kl", "clipfrac",
                "explained_variance", "perf/env_steps_per_s"):
        assert key in records[2]
    assert "val/success_rate" in records[0] and "val/success_rate" in records[2]
    assert records[1]["device"] == records[2]["device"] == "cpu"  # a card says where a run's env steps ran
    ckpts = out / "checkpoints"
    assert (ckpts / "last").resolve().name == "000000064"
    assert (ckpts / "best" / "pretrained_model" / "model.safetensors").exists()
    assert (out / "training_curves.png").stat().st_size > 10_000
    saved = torch.load(ckpts / "last" / "training_state" / "optimizers.pt", weights_only=True)
    groups = [g for name in ("actor_opt", "critic_opt") for g in saved[name]["param_groups"]]
    assert groups and all(g["fused"] for g in groups)  # torch's fused AdamW, restored with the state on resume
    assert any((out / "tensorboard").iterdir())

    path = ckpts / "last" / "pretrained_model"
    policy = PDPOPolicy.from_pretrained(path)
    assert policy.config.ft_denoising_steps == 10 and not policy.config.use_ema
    base = PDPOPolicy.from_pretrained(pretrained)
    # frozen copy = the pretrained nets; trained nets moved; the value head is saved
    for a, b in zip(policy.base.denoiser.parameters(), base.actor.denoiser.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    assert any(not torch.equal(a, b) for a, b in zip(policy.actor.denoiser.parameters(), base.actor.denoiser.parameters(), strict=True))
    # the critic is saved beside the policy, trained away from the fresh one a BC checkpoint gets
    assert (path / CRITIC).exists() and not any(k.startswith("value.") for k in policy.state_dict())
    ppo = DiffusionPPOConfig()
    trained, fresh = load_agent(path, ppo, seed=3).critic, load_agent(pretrained, ppo, seed=3).critic
    assert any(not torch.equal(a, b) for a, b in zip(trained.parameters(), fresh.parameters(), strict=True))
    eval_main([f"--policy.path={path}", "--eval.n_episodes=2", "--eval.split=val", f"--output_dir={tmp_path / 'eval'}"])
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["n_episodes"] == 2


def test_executed_log_probabilities_read_the_first_action_only(pretrained):
    """--ppo.logprob_actions=executed scores a chunk's transitions on its first (executed) action:
    changing the later actions of the final sample x_0 (no transition's input) leaves its scores as
    they are and moves the whole-chunk score of the last transition."""
    chunk = load_agent(pretrained, DiffusionPPOConfig(), seed=3).eval()
    executed = load_agent(pretrained, DiffusionPPOConfig(logprob_actions="executed"), seed=3).eval()
    assert chunk.policy.config.horizon > 1
    collector = Collector(CrowdNavVectorEnv(2), chunk, None, torch.Generator().manual_seed(0))
    collector.reset(500_000_000)
    cols = Columns.of(collector.collect(chunk, 4), False, torch.device("cpu"))
    samples, memory, starts = cols[torch.arange(8)]
    later = {**samples, "chain": samples["chain"].clone()}
    later["chain"][..., -1, 1:, :] += 0.3
    with torch.no_grad():
        torch.testing.assert_close(executed(later, memory, starts).logp, executed(samples, memory, starts).logp)
        assert not torch.allclose(chunk(later, memory, starts).logp, chunk(samples, memory, starts).logp)
        z = chunk.policy.actor.encoder(samples["state"].flatten(0, 1))
        first = transition_log_prob(chunk.policy.actor, z, samples["chain"].flatten(0, 1), 0.1, actions=1)
        torch.testing.assert_close(executed(samples, memory, starts).logp, first.view_as(executed(samples, memory, starts).logp))
    with pytest.raises(ValueError, match="logprob_actions"):
        DiffusionPPOConfig(logprob_actions="first").validate()


@pytest.mark.parametrize("bad, message", [(dict(clip_ploss_coef_rate=1e4), "overflows"),
                                          (dict(batch_size=1), "batch_size must be >= 2"),
                                          (dict(reward_clip=0.0), "reward_clip must be > 0")])
def test_ppo_settings_that_would_train_on_nan_or_constant_rewards_are_refused(bad, message):
    """Each of these ran before and silently trained on NaN (an overflowing clip schedule, the std of
    a one-sample minibatch) or on constant rewards (a clip of 0); rate 0 and batch 1 without
    per-minibatch normalization are fine."""
    with pytest.raises(ValueError, match=message):
        DiffusionPPOConfig(**bad).validate()
    DiffusionPPOConfig(clip_ploss_coef_rate=0.0).validate()
    DiffusionPPOConfig(batch_size=1, norm_adv="rollout").validate()


def test_frozen_encoder_scores_from_stored_latents_and_stays_put(pretrained, tmp_path):
    """--ppo.freeze_encoder: the rollout stores each state's latent, the update scores from it
    exactly as from the state, the encoder does not move, and the fine-tuned nets do."""
    frozen = DiffusionPPOConfig(n_steps=8, batch_size=16, update_epochs=2, freeze_encoder=True)
    agent = load_agent(pretrained, frozen, seed=3).eval()
    reference = load_agent(pretrained, DiffusionPPOConfig(), seed=3).eval()
    collector = Collector(CrowdNavVectorEnv(4), agent, None, torch.Generator().manual_seed(0))
    collector.reset(500_000_000)
    ro = collector.collect(agent, frozen.n_steps)
    assert ro.stored["latent"].shape == (8, 4, agent.policy.config.latent_dim)
    # the same chains as an unfrozen agent samples with the same noise
    ref = Collector(CrowdNavVectorEnv(4), reference, None, torch.Generator().manual_seed(0))
    ref.reset(500_000_000)
    torch.testing.assert_close(ref.collect(reference, frozen.n_steps).stored["chain"], ro.stored["chain"])
    cols = Columns.of(ro, False, torch.device("cpu"))
    idx = torch.arange(16)
    with_latent = agent(*cols[idx])
    from_state = agent({k: v for k, v in cols[idx][0].items() if k != "latent"}, None, cols[idx][2])
    torch.testing.assert_close(with_latent.logp, from_state.logp)
    torch.testing.assert_close(with_latent.value, from_state.value)

    encoder = {k: v.clone() for k, v in agent.policy.actor.encoder.state_dict().items()}
    denoiser = {k: v.clone() for k, v in agent.policy.actor.denoiser.state_dict().items()}
    optimizers = {name: torch.optim.AdamW(p, lr=1e-2) for name, p in agent.param_groups().items()}
    from accelerate import Accelerator

    update(agent, agent, ro, frozen, optimizers, np.random.default_rng(0), Accelerator(cpu=True), train_actor=True)
    assert all(torch.equal(v, encoder[k]) for k, v in agent.policy.actor.encoder.state_dict().items())
    assert any(not torch.equal(v, denoiser[k]) for k, v in agent.policy.actor.denoiser.state_dict().items())

    records = run(pretrained, tmp_path / "run", "--env_steps=64", "--ppo.freeze_encoder=true")
    assert records[-1]["env_steps"] == 64
    saved = PDPOPolicy.from_pretrained(tmp_path / "run" / "checkpoints" / "last" / "pretrained_model")
    for a, b in zip(saved.actor.encoder.parameters(), saved.base.encoder.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("critic_input", ["state", "latent+state"])
def test_critic_reads_its_input_and_a_checkpoint_keeps_it(pretrained, tmp_path, critic_input):
    """--ppo.critic_input: V of the normalized observation (and the latent); no value gradient
    reaches the encoder; the saved critic loads with its setting and is refused with another."""
    cfg = DiffusionPPOConfig(critic_input=critic_input)
    agent = load_agent(pretrained, cfg, seed=3).eval()
    obs = torch.as_tensor(CrowdNavVectorEnv(4).reset(seed=500_000_000)[0], dtype=torch.float32)
    state = agent._normalize(obs)
    z = agent.policy.actor.encoder(state)
    x = state if critic_input == "state" else torch.cat([z, state], dim=-1)
    torch.testing.assert_close(agent.value(obs, None), agent.critic.net(x).squeeze(-1))
    agent.critic(z, state).sum().backward()
    assert all(p.grad is None for p in agent.policy.actor.encoder.parameters())

    run(pretrained, tmp_path / "run", "--env_steps=32", f"--ppo.critic_input={critic_input}")
    path = tmp_path / "run" / "checkpoints" / "last" / "pretrained_model"
    saved = load_agent(path, cfg, seed=0).critic
    with torch.no_grad():
        assert not torch.equal(saved.net[0].weight, agent.critic.net[0].weight)  # trained, then loaded
    with pytest.raises(ValueError, match="critic_input"):
        load_agent(path, DiffusionPPOConfig(), seed=0)
    with pytest.raises(SystemExit, match="critic_input"):
        run(pretrained, tmp_path / "bad", "--ppo.critic_input=raw")


def test_resume_continues_the_counter_and_reproduces_the_next_batch(pretrained, tmp_path):
    straight = run(pretrained, tmp_path / "a", "--env_steps=64")
    first = run(pretrained, tmp_path / "b", "--env_steps=32")
    assert first[-1]["env_steps"] == 32
    resumed = run(pretrained, tmp_path / "b", "--env_steps=64", "--resume=true")
    assert [r["iteration"] for r in resumed] == [0, 1, 2]
    assert resumed[2]["rollout_digest"] == straight[2]["rollout_digest"]
    for key in ("loss/policy_loss", "loss/value_loss", "train/episodes"):
        assert resumed[2][key] == straight[2][key]
    with pytest.raises(SystemExit, match="different settings"):
        run(pretrained, tmp_path / "b", "--env_steps=96", "--resume=true", "--ppo.gamma=0.9")


def test_bad_input_is_refused_before_any_work(pretrained, tmp_path):
    from lerobot.policies.act.configuration_act import ACTConfig

    with pytest.raises(SystemExit, match="no config.json"):
        run(tmp_path / "missing", tmp_path / "o1")
    other = tmp_path / "act"
    other.mkdir()
    ACTConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (269,))},
              output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))})._save_pretrained(other)
    with pytest.raises(SystemExit, match="'act' policy"):
        run(other, tmp_path / "o2")
    with pytest.raises(SystemExit, match="observations"):
        run(pretrained, tmp_path / "o3", "--env.num_humans=10")
    with pytest.raises(SystemExit, match="batch_size"):
        run(pretrained, tmp_path / "o4", "--ppo.batch_size=1000")
    # PDPO's state statistics leave out rows of its sentinel_value: another --env.sentinel is refused
    with pytest.raises(SystemExit, match=r"invisible-human rows of 15.0 .*writes 10.0 \(--env.sentinel\)"):
        run(pretrained, tmp_path / "o6", "--env.sentinel=10")
    (tmp_path / "o5").mkdir()
    (tmp_path / "o5" / "keep.txt").write_text("x")
    with pytest.raises(SystemExit, match="exists"):
        run(pretrained, tmp_path / "o5")
    assert (tmp_path / "o5" / "keep.txt").read_text() == "x"
    for out in ("o1", "o2", "o3", "o4", "o6"):
        assert not (tmp_path / out).exists()


def test_evaluation_refuses_an_env_with_another_sentinel(pretrained):
    from lerobot_crowdnav.measure.episodes import LearnedPolicy

    with pytest.raises(ValueError, match="--env.sentinel"):
        LearnedPolicy(pretrained, "cpu", 269, sentinel=10.0)


def test_accelerate_two_processes_run_one_iteration(pretrained, tmp_path):
    out = tmp_path / "ddp"
    # accelerate's DDP launcher; --device=cpu makes the processes join a gloo process group
    cmd = [str(BIN / "accelerate"), "launch", "--multi_gpu", "--num_processes=2", "--num_machines=1",
           "--mixed_precision=no", "--dynamo_backend=no", "-m", "lerobot_crowdnav.rl.finetune",
           f"--policy.path={pretrained}", f"--output_dir={out}", *TINY_RUN, "--env_steps=64", "--device=cpu"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "2 processes (MULTI_CPU)" in proc.stdout
    records = [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]
    assert records[-1]["env_steps"] == 64  # 2 processes x 4 envs x 8 steps in one iteration
    assert len(records) == 2
    state = out / "checkpoints" / "last" / "training_state"
    assert (state / "env_rank0.npz").exists() and (state / "env_rank1.npz").exists()
    config = json.loads((out / "checkpoints" / "last" / "pretrained_model" / "finetune_config.json").read_text())
    assert config["world_size"] == 2


@pytest.mark.parametrize("path", sorted((Path(__file__).resolve().parents[1] / "configs" / "finetune").glob("*.yaml")),
                         ids=lambda p: p.stem)
def test_finetune_configs_parse_and_validate(path):
    import draccus

    cfg = draccus.parse(ft.FinetuneConfig, config_path=str(path), args=[])
    cfg.validate()
    assert cfg.ppo.batch_size == 500 and cfg.ppo.ft_denoising_steps == 10 and cfg.ppo.update_epochs == 5
    assert cfg.env.task in path.read_text() and cfg.policy.path is not None


def test_checkpoints_from_before_the_actor_critic_split_still_load(tmp_path):
    """Legacy layout: actor at encoder.* / denoiser.*, value head at value.* in model.safetensors."""
    from safetensors.torch import load_file, save_file

    cfg = small_pdpo_config(ft_denoising_steps=4, use_ema=False)
    torch.manual_seed(2)
    policy = PDPOPolicy(cfg)
    critic = ValueHead(cfg.latent_dim, cfg.value_mlp_dims)
    policy.save_pretrained(tmp_path)
    weights = load_file(str(tmp_path / "model.safetensors"))
    legacy = {k.removeprefix("actor."): v for k, v in weights.items()}
    legacy.update({f"value.{k}": v for k, v in critic.state_dict().items()})
    save_file(legacy, str(tmp_path / "model.safetensors"))
    loaded = PDPOPolicy.from_pretrained(tmp_path)
    for k, v in policy.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    from lerobot_crowdnav.rl.dppo import _saved_critic

    restored = ValueHead(cfg.latent_dim, cfg.value_mlp_dims)
    restored.load_state_dict(_saved_critic(tmp_path))
    for a, b in zip(restored.parameters(), critic.parameters(), strict=True):
        assert torch.equal(a, b)
    del legacy["actor.encoder.latent_mlp.0.bias".removeprefix("actor.")]  # a missing weight is an error
    save_file(legacy, str(tmp_path / "model.safetensors"))
    with pytest.raises(RuntimeError, match="Missing key"):
        PDPOPolicy.from_pretrained(tmp_path)
    # a fine-tuned policy saved without its critic (lerobot's own push): one clear error, not a KeyError
    save_file({k: v for k, v in legacy.items() if not k.startswith("value.")}, str(tmp_path / "model.safetensors"))
    with pytest.raises(FileNotFoundError, match="without its critic"):
        _saved_critic(tmp_path)
