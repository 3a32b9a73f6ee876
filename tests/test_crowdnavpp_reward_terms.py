"""scripts/crowdnavpp_reward_terms.py: a policy's episode reward split into its terms. The split
must add up to the env's own episode returns, its prediction penalty must be the env's, and a bad
policy argument is a one-line error."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

ROOT = Path(__file__).parents[1]
spec = importlib.util.spec_from_file_location("crowdnavpp_reward_terms", ROOT / "scripts/crowdnavpp_reward_terms.py")
terms_mod = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # dataclasses look it up
spec.loader.exec_module(terms_mod)


def test_terms_add_up_to_the_envs_own_returns(tmp_path):
    n, envs, seed = 12, 4, 1_000_000_000
    out = tmp_path / "terms.json"
    terms_mod.main(["--policy=straight", f"--episodes={n}", f"--num_envs={envs}", f"--output_json={out}"])
    result = json.loads(out.read_text())
    # The same episodes, read from the env's own episode records.
    env = CrowdNavVectorEnv(envs, task="CrowdNav-v0", preset="crowdnavpp", robot_policy="straight")
    env.reset(seed=list(range(seed, seed + envs)))
    returns, penalties, lengths, events = [], [], [], []
    while len(returns) < n:
        _, _, term, trunc, info = env.step(None)
        for b in np.flatnonzero(term | trunc):
            fi = info["final_info"]
            returns.append(fi["return"][b]), penalties.append(fi["prediction_penalty"][b])
            lengths.append(fi["length"][b]), events.append(int(fi["event"][b]))
    returns, penalties = np.array(returns[:n]), np.array(penalties[:n])
    overall = result["all"]
    assert overall["episodes"] == n and overall["share"] == 1.0
    assert overall["episode_return"] == pytest.approx(returns.mean())
    assert sum(overall[k] for k in terms_mod.TERMS) == pytest.approx(returns.mean())
    assert overall["prediction_penalty"] == pytest.approx(penalties.mean()) and overall["prediction_penalty"] < 0
    assert overall["without_penalty"] == pytest.approx((returns - penalties).mean())
    assert overall["steps"] == pytest.approx(np.mean(lengths[:n]))
    collided = result["human_collision"]
    assert collided["terminal"] == pytest.approx(-20.0) and collided["share"] > 0.5  # straight into a crowd
    assert sum(result[o]["share"] for o in terms_mod.OUTCOMES if result.get(o)) == pytest.approx(1.0)
    assert "mean_speed_percentiles" not in result  # a built-in robot has no Gaussian


def test_bad_policy_is_a_one_line_error(tmp_path):
    with pytest.raises(SystemExit, match="not a pretrained_model directory"):
        terms_mod.main([f"--policy={tmp_path / 'nothing'}"])
    with pytest.raises(SystemExit, match="must be >= 1"):
        terms_mod.main(["--episodes=0"])
