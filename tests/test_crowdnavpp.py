"""CrowdNav++ (--policy.type=crowdnavpp): the reference's parameter count, the observation
mapping, masking, recurrence with resets, lerobot save/load and plugin discovery."""

from __future__ import annotations

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
