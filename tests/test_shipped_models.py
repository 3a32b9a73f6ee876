"""The trained models shipped in models/lerobot-crowdnav: hub-format directories with their card
and learning curve that lerobot loads and lerobot-crowdnav-eval runs (make main evaluates them on
the 500 test seeds; tests/test_report.py checks that a shipped copy reproduces its run's metrics)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from lerobot_crowdnav.evaluation.eval import main as eval_main
from lerobot_crowdnav.main.config import SHIPPED_MODELS

MODELS = sorted(p for p in SHIPPED_MODELS.iterdir() if p.is_dir()) if SHIPPED_MODELS.exists() else []


def test_the_four_pdpo_policies_and_the_bounded_crowdnavpp_baseline_are_shipped():
    """Both benchmarks, with and without the action chunk (issue 13's table), and the CrowdNav++
    (Const. Vel.) row of Bounded CrowdNav (issue 32; the original benchmark's is still training)."""
    expected = {f"pdpo_{task}_h{h}" for task in ("bounded", "original") for h in (1, 5)} | {"crowdnavpp_bounded"}
    assert expected <= {p.name for p in MODELS}


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_shipped_model_has_its_card_and_evaluates(path, tmp_path):
    card = (path / "README.md").read_text()
    for section in ("## Evaluation", "500 test episodes", "## Learning curve", "## Reproduce", "| total |"):
        assert section in card, section
    assert (path / "learning_curve.png").stat().st_size > 10_000
    run = next(path / name for name in ("finetune_config.json", "train_ppo_config.json") if (path / name).exists())
    task = json.loads(run.read_text())["env"]["task"]  # PDPO's fine-tuning run or CrowdNav++'s PPO run
    eval_main([f"--policy.path={path}", f"--env.task={task}", "--eval.n_episodes=4", "--eval.split=test",
               f"--output_dir={tmp_path}"])
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["n_episodes"] == 4 and metrics["policy"] == path.name


def test_a_policy_trained_on_a_gpu_evaluates_and_fine_tunes_on_the_cpu(tmp_path):
    """lerobot-train on a GPU saves its device in the preprocessor; evaluation, DAgger, the figures
    and fine-tuning put the inputs where they run instead (as lerobot-eval does)."""
    from lerobot_crowdnav.measure.episodes import LearnedPolicy
    from lerobot_crowdnav.rl.config import DiffusionPPOConfig
    from lerobot_crowdnav.rl.dppo import load_agent
    from lerobot_crowdnav.sim.config import CrowdSimConfig
    from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

    path = shutil.copytree(SHIPPED_MODELS / "pdpo_bounded_h1", tmp_path / "gpu_trained")
    for name in ("config.json", "policy_preprocessor.json"):
        text = (path / name).read_text()
        assert '"device": "cpu"' in text
        (path / name).write_text(text.replace('"device": "cpu"', '"device": "cuda"'))
    sim_cfg = CrowdSimConfig(task="BoundedCrowdNav-v0").resolve()
    obs, _ = CrowdNavVectorEnv(2, config=sim_cfg).reset(seed=[0, 1])
    actions = LearnedPolicy(path, "cpu", sim_cfg.obs_dim)(obs, np.ones(2, bool))
    assert actions.shape == (2, 2) and np.isfinite(actions).all()
    step = load_agent(path, DiffusionPPOConfig(), seed=0).act(torch.as_tensor(obs), None, explore=True,
                                                              generator=torch.Generator().manual_seed(0))
    assert step.action.shape == (2, 2) and torch.isfinite(step.action).all()
