"""CrowdNav++ (--policy.type=crowdnavpp): the reference's parameter count, the observation
mapping, masking, recurrence with resets, lerobot save/load and plugin discovery."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot_policy_crowdnavpp import CrowdNavPPConfig, CrowdNavPPPolicy
from lerobot_policy_crowdnavpp.modeling_crowdnavpp import DEAD_HEAD_PARAMETERS, split_obs

N, L, D = 20, 5, 269


def make_config(**overrides) -> CrowdNavPPConfig:
    return CrowdNavPPConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (D,))},
                            output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))}, device="cpu",
                            **overrides)


def random_obs(b: int, visible: list[int], seed: int = 0) -> torch.Tensor:
    """Observations with the first visible[i] rows of env i visible, the rest sentinel rows."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(b, D, generator=g)
    for i, n in enumerate(visible):
        rows = obs[i, 9:249].view(N, 12)
        rows[n:] = 15.0
        obs[i, 249:] = (torch.arange(N) < n).float()
    return obs


@pytest.fixture(scope="module")
def policy() -> CrowdNavPPPolicy:
    torch.manual_seed(0)
    return CrowdNavPPPolicy(make_config()).eval()


def test_parameter_count_matches_the_reference(policy):
    counts = policy.parameter_counts()
    assert counts["trainable"] == 2_502_021
    # The reference network, with its unused Linear(256, 2): the paper's 2.503 M.
    assert counts["reference_with_dead_head"] == 2_502_535 == 2_502_021 + DEAD_HEAD_PARAMETERS
    assert round(counts["reference_with_dead_head"] / 1e6, 3) == 2.503


def test_split_obs_maps_a_hand_built_observation():
    o = torch.zeros(D)
    o[:7] = torch.tensor([1.0, 2.0, 0.3, 4.0, 5.0, 1.0, math.pi / 2])  # px py r gx gy v_pref theta
    o[7:9] = torch.tensor([0.5, -0.5])  # vx vy
    rows = torch.arange(N * 12, dtype=torch.float32).view(N, 12)
    rows[3:] = 15.0
    o[9:249] = rows.flatten()
    o[249:252] = 1.0  # 3 visible
    x = split_obs(o[None], N, L)
    torch.testing.assert_close(x.robot[0], torch.tensor([0.5, -0.5, 1.0, 2.0, 0.3, 4.0, 5.0, 1.0, math.pi / 2]))
    torch.testing.assert_close(x.humans[0], rows)
    assert x.humans.shape == (1, N, 12) and x.detected.tolist() == [3]
    assert x.visible[0].tolist() == [True] * 3 + [False] * 17
    # Nobody visible: the count is clamped to 1 (slot 0, a sentinel row, as the reference env does).
    o[249:] = 0.0
    x = split_obs(o[None], N, L)
    assert x.detected.tolist() == [1] and x.visible[0].tolist() == [True] + [False] * 19
    # Sizes come from the config: 10 humans, L = 1 -> 4 floats a row, 9 + 40 + 10 = 59.
    x = split_obs(torch.zeros(2, 59), 10, 1)
    assert x.humans.shape == (2, 10, 4) and x.visible.shape == (2, 10)


def test_no_visible_human_gives_finite_outputs(policy):
    obs = random_obs(3, [0, 0, 5])
    net = policy.net
    _, _, weights = net.encode(obs)
    assert torch.all(weights[:2, 0] == 1.0) and torch.all(weights[:2, 1:] == 0.0)
    mean, value, memory = net.step(obs, net.initial_memory(3))
    assert torch.isfinite(mean).all() and torch.isfinite(value).all() and torch.isfinite(memory).all()


def test_padded_rows_do_not_change_the_outputs(policy):
    obs = random_obs(4, [0, 3, 7, 20], seed=1)
    other = obs.clone()
    for i, n in enumerate([0, 3, 7, 20]):
        rows = other[i, 9:249].view(N, 12)
        rows[max(n, 1):] = torch.randn(N - max(n, 1), 12) * 4  # anything in the padded slots
    net = policy.net
    m = torch.randn(4, 128)
    a, b = net.step(obs, m), net.step(other, m)
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-6)


@pytest.mark.parametrize("repeat", [1, 4])  # 200 bucketed human rows: maps in turn; 800: composed
def test_visible_humans_only_gives_what_all_slots_give(policy, repeat):
    """The speed-ups that run the self-attention per group of similar visible counts over the
    visible prefix only and, for many rows, apply the out-projection and the spatial linear as
    one map: outputs and gradients as when every one of the N slots is encoded by the
    reference's layers in turn."""
    counts = [0, 1, 2, 3, 5, 7, 8, 11, 13, 16, 19, 20, 4, 6, 0, 9, 12, 20, 1, 3] * repeat
    # In float64, so that only a wrong regrouping, not float32 rounding in another summation
    # order (which differs between CPUs), can exceed the tolerance.
    obs = random_obs(len(counts), counts, seed=3).double()
    net = copy.deepcopy(policy.net).double()
    assert net.composed_out(200) is None and net.composed_out(800) is not None

    def every_slot(state):
        o = split_obs(state, N, L)
        robot = net.robot_linear(o.robot)
        humans = net.spatial_linear(net.human_attn(o.humans, o.visible))
        return (robot, *net.robot_human_attn(robot, humans, o.visible))

    with torch.enable_grad():
        fast, full = net.encode(obs), every_slot(obs)
        for x, y in zip(fast, full, strict=True):
            torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12)
        params = [*net.human_attn.parameters(), *net.spatial_linear.parameters()]
        grads = [torch.autograd.grad(out[1].square().sum(), params) for out in (fast, full)]
    for x, y in zip(*grads, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("batch", [5, 60])  # 100 human rows: the two maps in turn; 1,200: composed
def test_human_self_attention_is_the_reference_two_stage_attention(policy, batch):
    """The human self-attention (q/k/v linears, then the MultiheadAttention's in-projection,
    composed into one map for large batches): outputs and parameter gradients as the reference's
    nn.MultiheadAttention call on q/k/v linears, with key padding for the invisible humans."""
    attn = policy.net.human_attn
    counts = ([1, 4, 9, 20, 2] * 12)[:batch]
    o = split_obs(random_obs(len(counts), counts, seed=5), N, L)

    def reference(humans, visible):
        e = attn.embedding(humans)
        return attn.attention(attn.q_linear(e), attn.k_linear(e), attn.v_linear(e), key_padding_mask=~visible,
                              need_weights=False)[0]

    with torch.enable_grad():
        rows = o.humans[..., 0].numel()
        assert (attn.composed_qkv(rows) is None) == (batch == 5)
        outs = [attn(o.humans, o.visible, attn.composed_qkv(rows)), reference(o.humans, o.visible)]
        torch.testing.assert_close(outs[0], outs[1], rtol=1e-4, atol=1e-5)
        weights = torch.randn_like(outs[0])
        grads = [torch.autograd.grad((out * weights).sum(), list(attn.parameters())) for out in outs]
    for x, y in zip(*grads, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-3, atol=1e-4)


def test_a_sequence_scored_at_once_equals_acting_step_by_step(policy):
    T, B = 7, 3
    obs = torch.stack([random_obs(B, [t % 5, 0, 20], seed=t) for t in range(T)])  # (T, B, D)
    starts = torch.zeros(T, B, dtype=torch.bool)
    starts[0] = True
    starts[3, 0] = starts[5, 2] = True
    net = policy.net
    with torch.enable_grad():
        mean, value, memory = net.unroll(obs, torch.randn(B, 128), starts)  # starts[0]: the memory is unused
    policy.reset()
    means, values, mem = [], [], net.initial_memory(B)
    for t in range(T):
        means.append(policy.select_action({"observation.state": obs[t]}, episode_start=starts[t]))
        m, v, mem = net.step(obs[t], mem * ~starts[t, :, None])
        values.append(v)
    torch.testing.assert_close(torch.stack(means), mean.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(torch.stack(values), value.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(policy._memory, memory.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(mem, memory.detach(), rtol=1e-5, atol=1e-5)
    # reset() restarts the memory: the first action again.
    policy.reset()
    torch.testing.assert_close(policy.select_action({"observation.state": obs[0]}), means[0])


def test_forward_refuses_supervised_training(policy):
    with pytest.raises(NotImplementedError, match="PPO"):
        policy.forward({"observation.state": torch.zeros(1, D)})


def test_saves_gru_weights_packed_into_one_buffer(policy, tmp_path: Path):
    """On a GPU cuDNN makes the GRU's weights views of one flat buffer (flatten_parameters);
    safetensors refuses such a tensor, so reproduce the packing on the CPU and save."""
    gru = policy.net.node_rnn.gru
    weights = list(gru.parameters())
    flat = torch.cat([w.detach().flatten() for w in weights])
    offset = 0
    for w in weights:
        w.data = flat[offset:offset + w.numel()].view_as(w)
        offset += w.numel()
    assert weights[0].untyped_storage().nbytes() > weights[0].numel() * weights[0].element_size()
    policy.save_pretrained(tmp_path)
    loaded = type(policy).from_pretrained(tmp_path)
    for (k, a), b in zip(policy.state_dict().items(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a, b), k


def test_gru_runs_without_cudnn_when_trained_in_eval_mode(monkeypatch):
    """PPO backpropagates through the GRU in eval mode, which cuDNN refuses ("cudnn RNN backward
    can only be called in training mode"): there the GRU must run with cuDNN off, and only there."""
    torch.manual_seed(0)
    net = CrowdNavPPPolicy(make_config()).net
    seen = []
    gru_forward = type(net.node_rnn.gru).forward
    monkeypatch.setattr(type(net.node_rnn.gru), "forward",
                        lambda self, *a: (seen.append(torch.backends.cudnn.enabled), gru_forward(self, *a))[1])
    obs, memory, starts = random_obs(2, [3, 0])[None], net.initial_memory(2), torch.zeros(1, 2, dtype=torch.bool)
    net.eval()
    net.unroll(obs, memory, starts)[1].sum().backward()  # PPO's update
    with torch.no_grad():
        net.unroll(obs, memory, starts)  # a rollout
    net.train()
    net.unroll(obs, memory, starts)
    assert seen == [False, True, True] and torch.backends.cudnn.enabled


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_ppo_backward_through_the_gru_on_a_gpu():
    torch.manual_seed(0)
    net = CrowdNavPPPolicy(make_config()).net.cuda().eval()
    obs = random_obs(2, [3, 0])[None].cuda()
    net.unroll(obs, net.initial_memory(2).cuda(), torch.zeros(1, 2, dtype=torch.bool, device="cuda"))[1].sum().backward()
    assert all(p.grad is not None for p in net.node_rnn.gru.parameters())


def test_save_load_round_trip_through_lerobot_plugin_discovery(policy, tmp_path: Path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    policy.save_pretrained(tmp_path)
    register_third_party_plugins()
    assert "crowdnavpp" in PreTrainedConfig.get_known_choices()
    cfg = PreTrainedConfig.from_pretrained(tmp_path)
    assert cfg.type == "crowdnavpp" and cfg.optimizer_lr == 4e-5
    optim = cfg.get_optimizer_preset()
    assert optim.lr == 4e-5 and optim.eps == 1e-5
    loaded = get_policy_class(cfg.type).from_pretrained(tmp_path, config=cfg).eval()
    for (k, a), (k2, b) in zip(policy.state_dict().items(), loaded.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(a, b), k
    pre, post = make_pre_post_processors(cfg)
    obs = random_obs(2, [4, 0])
    batch = pre({"observation.state": obs})
    torch.testing.assert_close(batch["observation.state"], obs)  # identity
    loaded.reset()
    policy.reset()
    torch.testing.assert_close(post(loaded.select_action(batch)), policy.select_action({"observation.state": obs}))


# -- PPO options CrowdNav++ needs (default off: PDPO's runs are unchanged) ------------------------
def test_clipped_value_loss_matches_a_hand_computation():
    from lerobot_crowdnav.rl.ppo import ppo_losses

    one = torch.ones(1)
    v = torch.tensor([1.0, 0.0, 2.0])
    v_old = torch.tensor([0.5, 0.5, 2.1])
    ret = torch.tensor([2.0, 0.4, 0.0])
    zeros = torch.zeros(3, 1)
    plain = ppo_losses(zeros, zeros, torch.randn(3), 0.2 * one, one, v, ret)["value_loss"]
    clipped = ppo_losses(zeros, zeros, torch.randn(3), 0.2 * one, one, v, ret, old_values=v_old, value_clip=0.2)
    # clipped V: 0.5 + clamp(0.5) = 0.7; 0.5 + clamp(-0.5) = 0.3; 2.1 + (-0.1) = 2.0
    by_hand = 0.5 * (max(1.0**2, 1.3**2) + max(0.4**2, 0.1**2) + max(2.0**2, 2.0**2)) / 3
    assert float(plain) == pytest.approx(0.5 * (1.0 + 0.16 + 4.0) / 3)
    assert float(clipped["value_loss"]) == pytest.approx(by_hand)


def test_advantages_normalized_per_minibatch_or_left_as_given():
    from lerobot_crowdnav.rl.ppo import normalize_advantages, ppo_losses

    adv = torch.tensor([1.0, 2.0, 6.0])
    one = torch.ones(1)
    zeros = torch.zeros(3, 1)  # ratio 1: the policy loss is -mean(advantage used)
    per_mb = ppo_losses(zeros, zeros, adv, 0.2 * one, one, torch.zeros(3), torch.zeros(3))["policy_loss"]
    given = ppo_losses(zeros, zeros, adv, 0.2 * one, one, torch.zeros(3), torch.zeros(3), normalize=False)["policy_loss"]
    assert float(per_mb) == pytest.approx(0.0, abs=1e-6) and float(given) == pytest.approx(-3.0)
    n = normalize_advantages(adv, 1e-5)
    std = math.sqrt(((1 - 3) ** 2 + (2 - 3) ** 2 + (6 - 3) ** 2) / 2)  # unbiased, as torch.std
    torch.testing.assert_close(n, (adv - 3.0) / (std + 1e-5))


def test_timeouts_bootstrap_or_are_terminal():
    from types import SimpleNamespace

    import numpy as np

    from lerobot_crowdnav.rl.config import PPOConfig
    from lerobot_crowdnav.rl.loop import advantages

    # One env, two steps: a timeout at t = 0 (final observation's value 5), then a step.
    ro = SimpleNamespace(scaled_rewards=np.array([[1.0], [2.0]]), terminated=np.array([[False], [False]]),
                         done=np.array([[True], [False]]))
    v, nv = np.array([[0.5], [0.25]]), np.array([[5.0], [1.0]])
    g, lam = 0.9, 0.5
    adv, _ = advantages(ro, v, nv, PPOConfig(gamma=g, gae_lambda=lam))
    np.testing.assert_allclose(adv[:, 0], [1.0 + g * 5.0 - 0.5, 2.0 + g * 1.0 - 0.25])
    adv, ret = advantages(ro, v, nv, PPOConfig(gamma=g, gae_lambda=lam, bootstrap_timeouts=False))
    np.testing.assert_allclose(adv[:, 0], [1.0 - 0.5, 2.0 + g * 1.0 - 0.25])
    np.testing.assert_allclose(ret, adv + v)


def test_ppo_option_validation():
    from lerobot_crowdnav.rl.config import PPOConfig

    for bad in (PPOConfig(norm_adv="batch"), PPOConfig(adam_eps=0.0)):
        with pytest.raises(ValueError):
            bad.validate()
    cfg = PPOConfig()
    assert (cfg.adam_eps, cfg.clip_vloss, cfg.norm_adv, cfg.bootstrap_timeouts) == (1e-8, False, "minibatch", True)


# -- the agent and the training CLI (the shared PPO run of rl/trainer.py) -------------------------
TINY = ["--num_envs=4", "--ppo.n_steps=30", "--ppo.batch_size=60", "--val.n_episodes=2", "--save_freq=120",
        "--seed=3", "--env.preset=crowdnavpp", "--env.task=CrowdNav-v0"]


def train(out: Path, *extra: str) -> list[dict]:
    import json

    from lerobot_crowdnav.rl.train_ppo import main

    main([f"--output_dir={out}", *TINY, *extra])
    return [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]


def test_agent_scores_a_rollout_as_it_acted():
    """Collected with exploration, the sequences replayed from the rollout's initial memory with
    its restarts give the rollout's own memory trajectory: the first minibatch's ratio is 1."""
    import numpy as np
    from accelerate import Accelerator

    from lerobot_crowdnav.rl.crowdnavpp import CrowdNavPPPPOConfig, make_agent
    from lerobot_crowdnav.rl.loop import Collector, update
    from lerobot_crowdnav.sim.config import CrowdSimConfig
    from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

    sim = CrowdSimConfig(preset="crowdnavpp", compute_intrusion=False).resolve()
    agent = make_agent(sim, seed=0).eval()
    collector = Collector(CrowdNavVectorEnv(4, config=sim), agent, None, torch.Generator().manual_seed(0))
    collector.reset(500_000_000)
    ro = collector.collect(agent, 30)
    assert ro.memory0.shape == (4, 128) and ro.stored["obs"].shape == (30, 4, D) and ro.starts[0].all()
    assert np.abs(ro.stored["action"].numpy()).max() > 1.0  # unclipped samples are stored (std 1 m/s)
    with torch.no_grad():
        scores = agent(ro.stored, ro.memory0, torch.as_tensor(ro.starts))
    assert scores.logp.shape == (30, 4, 1) and scores.value.shape == (30, 4) and scores.entropy.shape == (30, 4)
    # the entropy of a 2-D Gaussian with std 1
    torch.testing.assert_close(scores.entropy, torch.full((30, 4), math.log(2 * math.pi * math.e)))
    # the replay's means are the acting means: what is left of each stored action is the noise drawn
    generator = torch.Generator().manual_seed(0)
    noise = torch.stack([torch.randn(4, 2, generator=generator) for _ in range(30)])
    with torch.no_grad():
        mean, _, _ = agent.net.unroll(ro.stored["obs"], ro.memory0, torch.as_tensor(ro.starts))
    torch.testing.assert_close(ro.stored["action"] - mean, noise)
    torch.testing.assert_close(scores.logp[..., 0], (-0.5 * noise**2 - 0.5 * math.log(2 * math.pi)).sum(-1))
    assert ro.starts[1:].any()  # an episode restarted inside the rollout: the replay restarted it too
    cfg = CrowdNavPPPPOConfig(batch_size=60)
    opt = {name: torch.optim.Adam(p, lr=cfg.actor_lr, eps=cfg.adam_eps) for name, p in agent.param_groups().items()}
    assert list(opt) == ["actor"] and sum(p.numel() for p in agent.param_groups()["actor"]) == 2_502_021
    stats = update(agent, agent, ro, cfg, opt, np.random.default_rng(0), Accelerator(cpu=True), train_actor=True)
    assert stats["update_epochs"] == 5 and math.isfinite(stats["loss/value_loss"])


def test_tiny_training_run_writes_a_checkpoint_that_loads_and_evaluates(tmp_path):
    import json

    from lerobot_crowdnav.measure.episodes import LearnedPolicy
    from lerobot_crowdnav.evaluation.eval import main as eval_main

    out = tmp_path / "run"
    records = train(out, "--env_steps=240")
    assert [r["iteration"] for r in records] == [0, 1, 2]
    for key in ("loss/policy_loss", "loss/value_loss", "entropy", "approx_kl", "explained_variance",
                "perf/env_steps_per_s", "val/success_rate"):
        assert key in records[2], key
    path = out / "checkpoints" / "last" / "pretrained_model"
    assert (out / "checkpoints" / "last").resolve().name == "000000240"
    settings = json.loads((path / "train_ppo_config.json").read_text())
    assert settings["ppo"]["adam_eps"] == 1e-5 and settings["ppo"]["clip_vloss"] and settings["policy"]["type"] == "crowdnavpp"
    assert json.loads((path / "config.json").read_text())["type"] == "crowdnavpp"
    fresh = CrowdNavPPPolicy.from_pretrained(out / "checkpoints" / "best" / "pretrained_model")  # iteration 0 or later
    trained = CrowdNavPPPolicy.from_pretrained(path)
    assert trained.parameter_counts()["trainable"] == 2_502_021 and fresh is not None
    actor = LearnedPolicy(path, "cpu", D)
    assert actor.recurrent
    from lerobot_crowdnav.data.hub import policy_card

    card = str(policy_card(path, "local/crowdnavpp"))
    assert "2,502,021 trainable" in card and "2,502,535" in card and "paper: 2.503 M" in card
    assert "PPO from scratch for 240 environment steps (this checkpoint; the run's budget: 240)" in card
    eval_main([f"--policy.path={path}", "--eval.n_episodes=2", "--eval.split=val", "--env.preset=crowdnavpp",
               f"--output_dir={tmp_path / 'eval'}"])
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["n_episodes"] == 2
    # The run's last validation is this evaluation: same weights, seeds and deterministic actions,
    # the intrusion test included (the training envs run without it).
    assert metrics["itr"] > 0, "these two episodes must intrude for the comparison to mean anything"
    assert records[2]["val/intrusion_rate"] == pytest.approx(metrics["itr"])
    assert records[2]["val/success_rate"] == metrics["sr"]
    # lerobot's own evaluation loads it too (reset() per episode, memory carried by select_action).
    import subprocess
    import sys

    ev = subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={path}", "--env.type=crowdnav",
         "--env.task=CrowdNav-v0", "--eval.n_episodes=2", "--eval.batch_size=2", "--policy.device=cpu",
         f"--output_dir={tmp_path / 'lerobot_eval'}", "--seed=2000000000"], capture_output=True, text=True, timeout=600)
    assert ev.returncode == 0, ev.stderr[-3000:]
    info = json.loads((tmp_path / "lerobot_eval" / "eval_info.json").read_text())
    assert info["per_group"]["crowdnav"]["n_episodes"] == 2


def test_resume_is_bitwise(tmp_path):
    straight = train(tmp_path / "a", "--env_steps=360")
    first = train(tmp_path / "b", "--env_steps=120")
    assert first[-1]["env_steps"] == 120
    resumed = train(tmp_path / "b", "--env_steps=360", "--resume=true")
    assert [r["iteration"] for r in resumed] == [0, 1, 2, 3]
    for i in (2, 3):
        assert resumed[i]["rollout_digest"] == straight[i]["rollout_digest"]
        for key in ("loss/policy_loss", "loss/value_loss", "approx_kl", "train/episodes"):
            assert resumed[i][key] == straight[i][key], (i, key)
    weights = [(run / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").read_bytes()
               for run in (tmp_path / "a", tmp_path / "b")]
    assert weights[0] == weights[1]  # the last update too
    with pytest.raises(SystemExit, match="different settings"):
        train(tmp_path / "b", "--env_steps=480", "--resume=true", "--ppo.clip_vloss=false")


def test_bad_policy_type_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="policy.type"):
        train(tmp_path / "x", "--policy.type=pdpo")


@pytest.mark.parametrize("name, task, preset", [("crowdnavpp_bounded", "BoundedCrowdNav-v0", "paper"),
                                                ("crowdnavpp_original", "CrowdNav-v0", "crowdnavpp")])
def test_configs_parse_with_the_reference_ppo(name, task, preset):
    import draccus

    from lerobot_crowdnav.rl import families
    from lerobot_crowdnav.rl.crowdnavpp import CrowdNavPPPPOConfig
    from lerobot_crowdnav.rl.train_ppo import config_class, policy_type

    root = Path(__file__).resolve().parents[1]
    path = str(root / "configs" / "rl" / f"{name}.yaml")
    cfg = draccus.parse(config_class(families.get(policy_type([f"--config_path={path}"]))), config_path=path, args=[])
    cfg.validate()
    sim = cfg.env.resolve()
    assert (sim.task, sim.preset, sim.randomize_attributes) == (task, preset, True)
    assert cfg.ppo == CrowdNavPPPPOConfig() and (cfg.num_envs, cfg.env_steps, cfg.seed) == (16, 10_000_000, 425)
    p = cfg.ppo  # the reference's arguments.py / ppo.py, written out (not the class's own defaults)
    assert (p.n_steps, p.batch_size, p.update_epochs, p.actor_lr, p.adam_eps, p.clip_ploss_coef, p.vf_coef,
            p.max_grad_norm, p.gamma, p.gae_lambda, p.target_kl) == (30, 240, 5, 4e-5, 1e-5, 0.2, 0.5, 0.5, 0.99, 0.95, 0)
    assert (p.norm_adv, p.bootstrap_timeouts, p.clip_vloss, p.reward_scale_running, p.n_critic_warmup_itr,
            p.weight_decay) == ("rollout", False, True, False, 0, 0)
    assert not cfg.env.compute_intrusion
    assert cfg.ppo.batch_size // cfg.ppo.n_steps == cfg.num_envs // 2  # 2 minibatches of whole sequences
