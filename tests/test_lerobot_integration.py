"""The crowd env inside lerobot 0.6.1: plugin discovery, CLI, draccus parsing, make_env and eval_policy."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import draccus
import numpy as np
import pytest
import torch

from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env, make_env_pre_post_processors
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.scripts.lerobot_eval import eval_policy
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_crowdnav.sim.config import SEED_SPLITS, CrowdSimConfig
from lerobot_crowdnav.sim.engine import EVENT_NAMES
from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv
from lerobot_crowdnav.sim.lerobot_env import CrowdNavEnvConfig

TEST_SEED0 = SEED_SPLITS["test"][0]
LEROBOT_EVAL = Path(sys.executable).parent / "lerobot-eval"


def _run(cmd: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "HF_HUB_OFFLINE": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)


# -- plugin discovery ------------------------------------------------------------------------


def test_plugin_discovery_registers_crowdnav_env_type():
    """lerobot's own discovery of `lerobot_env_*` distributions registers `crowdnav`, in a clean
    interpreter that never imported lerobot_crowdnav.sim.lerobot_env itself."""
    script = textwrap.dedent("""
        import sys
        from lerobot.envs.configs import EnvConfig
        from lerobot.utils.import_utils import register_third_party_plugins
        assert "lerobot_crowdnav.sim.lerobot_env" not in sys.modules, "imported too early"
        assert "crowdnav" not in EnvConfig.get_known_choices(), "registered without the plugin"
        register_third_party_plugins()
        assert "crowdnav" in EnvConfig.get_known_choices(), sorted(EnvConfig.get_known_choices())
        cls = EnvConfig.get_choice_class("crowdnav")
        assert cls.__module__ == "lerobot_crowdnav.sim.lerobot_env", cls.__module__
        assert cls.__name__ == "CrowdNavEnvConfig", cls.__name__
        assert "lerobot_env_crowdnav" in sys.modules
        print("OK crowdnav", cls().type)
    """)
    res = _run([sys.executable, "-c", script])
    assert res.returncode == 0, res.stdout + res.stderr
    assert "OK crowdnav crowdnav" in res.stdout


def test_lerobot_eval_help_lists_crowdnav():
    assert LEROBOT_EVAL.exists(), f"console script missing: {LEROBOT_EVAL}"
    res = _run([str(LEROBOT_EVAL), "--help"])
    assert res.returncode == 0, res.stdout + res.stderr
    choices = [line for line in res.stdout.splitlines() if "--env.type {" in line]
    assert choices, res.stdout
    assert all("crowdnav" in line.split("{", 1)[1].split("}", 1)[0].split(",") for line in choices)
    # draccus shows a choice's own fields once the type is chosen.
    res = _run([str(LEROBOT_EVAL), "--env.type=crowdnav", "--help"])
    assert res.returncode == 0, res.stdout + res.stderr
    for flag in ("--env.randomize_attributes", "--env.task", "--env.preset", "--env.num_humans"):
        assert flag in res.stdout, flag
    assert "CrowdNavEnvConfig ['env']" in res.stdout


# -- draccus parsing -------------------------------------------------------------------------


@dataclasses.dataclass
class _EnvOnly:
    env: EnvConfig


ARGS = ["--env.type=crowdnav", "--env.task=BoundedCrowdNav-v0", "--env.randomize_attributes=false"]


def _check_parsed(env):
    assert type(env) is CrowdNavEnvConfig
    assert isinstance(env, CrowdSimConfig) and isinstance(env, EnvConfig)
    assert env.type == "crowdnav"
    assert env.task == "BoundedCrowdNav-v0"
    assert env.randomize_attributes is False
    assert env.preset == "paper"
    assert env.fps == 4
    assert env.features[ACTION].shape == (2,)
    assert env.features["agent_pos"].shape == (269,)
    assert env.features_map == {ACTION: ACTION, "agent_pos": OBS_STATE}
    sim = env.gym_kwargs["config"]
    assert type(sim) is CrowdSimConfig
    assert sim.randomize_attributes is False and sim.bounded
    assert sim.robot_radius == 0.2  # paper preset filled in


def test_draccus_parses_crowdnav_env_config():
    cfg = draccus.parse(config_class=_EnvOnly, args=ARGS)
    _check_parsed(cfg.env)
    cfg = draccus.parse(config_class=_EnvOnly, args=["--env.type=crowdnav", "--env.task=CrowdNav-v0",
                                                      "--env.preset=crowdnavpp", "--env.num_humans=5"])
    assert cfg.env.task == "CrowdNav-v0" and cfg.env.num_humans == 5
    assert cfg.env.randomize_attributes is None  # left to the preset
    assert cfg.env.features["agent_pos"].shape == (7 + 2 + 5 * 12 + 5,)
    assert cfg.env.resolve().robot_radius == 0.3


def test_eval_pipeline_config_parses_crowdnav(tmp_path):
    from lerobot.configs.eval import EvalPipelineConfig

    cfg = draccus.parse(config_class=EvalPipelineConfig,
                        args=[*ARGS, "--eval.n_episodes=2", "--eval.batch_size=2", f"--output_dir={tmp_path}"])
    _check_parsed(cfg.env)
    assert cfg.eval.n_episodes == 2 and cfg.eval.batch_size == 2
    assert cfg.job_name == "crowdnav_scratch"


def test_train_pipeline_config_parses_crowdnav(tmp_path):
    """lerobot-train's config takes the env for its in-training evaluation the same way."""
    from lerobot.configs.train import TrainPipelineConfig

    cfg = draccus.parse(config_class=TrainPipelineConfig,
                        args=[*ARGS, "--dataset.repo_id=local/crowdnav", "--policy.type=diffusion",
                              "--env_eval_freq=500", f"--output_dir={tmp_path / 'train'}"])
    _check_parsed(cfg.env)
    assert cfg.env_eval_freq == 500


@pytest.mark.parametrize("arg, message", [
    ("--env.task=Nope-v0", "unknown task 'Nope-v0'"),
    ("--env.preset=nope", "unknown preset 'nope'"),
    ("--env.num_humans=0", "num_humans must be >= 1"),
])
def test_draccus_rejects_bad_crowdnav_config(arg, message):
    with pytest.raises(draccus.utils.ParsingError) as exc:
        draccus.parse(config_class=_EnvOnly, args=["--env.type=crowdnav", arg])
    cause = exc.value.__cause__
    assert isinstance(cause, ValueError), repr(cause)
    assert message in str(cause)
    # Built directly, the same config fails with the plain ValueError.
    key, value = arg.removeprefix("--env.").split("=")
    with pytest.raises(ValueError, match=re.escape(message)):
        CrowdNavEnvConfig(**{key: int(value) if value.isdigit() else value})


# -- make_env and observations ---------------------------------------------------------------


def test_make_env_returns_native_vector_env_with_dict_obs():
    cfg = CrowdNavEnvConfig(task="CrowdNav-v0")
    envs = make_env(cfg, n_envs=3)
    assert list(envs) == ["crowdnav"] and list(envs["crowdnav"]) == [0]
    env = envs["crowdnav"][0]
    assert type(env) is CrowdNavVectorEnv and env.freeze_ended
    assert env.num_envs == 3 and env.obs_mode == "dict" and env.render_mode == "rgb_array"
    assert env.config.task == "CrowdNav-v0" and not env.config.bounded
    assert env.call("_max_episode_steps") == (env.config.max_steps,) * 3
    assert env.call("task_description")[0] == "reach the goal among 20 humans"

    obs, info = env.reset(seed=TEST_SEED0)
    assert set(obs) == {"agent_pos"}
    assert obs["agent_pos"].shape == (3, 269) and obs["agent_pos"].dtype == np.float32
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(info["seed"], np.arange(TEST_SEED0, TEST_SEED0 + 3))

    flat = CrowdNavVectorEnv(3, config=cfg.resolve())
    flat_obs, _ = flat.reset(seed=TEST_SEED0)
    np.testing.assert_array_equal(obs["agent_pos"], flat_obs)

    batch = preprocess_observation(obs)
    assert set(batch) == {OBS_STATE}
    state = batch[OBS_STATE]
    assert isinstance(state, torch.Tensor)
    assert state.shape == (3, 269) and state.dtype == torch.float32
    np.testing.assert_array_equal(state.numpy(), flat_obs)

    # A step keeps the dict form, and final_obs too.
    obs2, reward, terminated, truncated, info = env.step(np.zeros((3, 2), np.float32))
    assert obs2["agent_pos"].shape == (3, 269) and reward.shape == (3,)
    env.close()


# -- lerobot's eval_policy with a go-to-goal policy ------------------------------------------


@dataclasses.dataclass
class _GoToGoalConfig(PreTrainedConfig):
    device: str | None = "cpu"

    @property
    def observation_delta_indices(self):
        return None

    @property
    def action_delta_indices(self):
        return None

    @property
    def reward_delta_indices(self):
        return None

    def get_optimizer_preset(self):
        raise NotImplementedError

    def get_scheduler_preset(self):
        return None

    def validate_features(self) -> None:
        pass


class _GoToGoalPolicy(PreTrainedPolicy):
    """Full speed toward the goal from `observation.state` (px, py at 0, 1; gx, gy at 3, 4; v_pref at 5)."""

    config_class = _GoToGoalConfig
    name = "test_go_to_goal"

    def __init__(self, config):
        super().__init__(config)
        self.n_resets = 0
        self.n_calls = 0

    def get_optim_params(self) -> dict:
        return {}

    def reset(self):
        self.n_resets += 1

    def forward(self, batch):
        raise NotImplementedError

    def predict_action_chunk(self, batch, **kwargs):
        return self.select_action(batch)[:, None]

    def select_action(self, batch, **kwargs):
        self.n_calls += 1
        state = batch[OBS_STATE].double()
        assert state.ndim == 2 and state.shape[1] == 269
        d = state[:, 3:5] - state[:, 0:2]
        return (d / d.norm(dim=1, keepdim=True).clamp_min(1e-12) * state[:, 5:6]).float()


def _straight_reference(config: CrowdSimConfig, seeds: list[int]) -> list[dict]:
    """Episode records of the built-in straight policy, one slot per seed, no autoreset."""
    env = CrowdNavVectorEnv(len(seeds), robot_policy="straight", autoreset=False, config=config)
    env.reset(seed=seeds)
    records: dict[int, dict] = {}
    for _ in range(config.max_steps):
        _, _, _, _, info = env.step(None)
        if "final_info" in info:
            fi = info["final_info"]
            for b in np.flatnonzero(info["_final_info"]):
                records.setdefault(int(b), {"success": bool(fi["is_success"][b]), "return": float(fi["return"][b]),
                                            "event": EVENT_NAMES[int(fi["event"][b])]})
        if len(records) == len(seeds):
            break
    return [records[b] for b in range(len(seeds))]


def test_lerobot_eval_policy_runs_on_crowdnav():
    cfg = draccus.parse(config_class=_EnvOnly, args=["--env.type=crowdnav", "--env.task=BoundedCrowdNav-v0"]).env
    env = make_env(cfg, n_envs=3)["crowdnav"][0]
    policy = _GoToGoalPolicy(_GoToGoalConfig())
    env_pre, env_post = make_env_pre_post_processors(cfg, policy.config)
    pre = PolicyProcessorPipeline(steps=[])
    post = PolicyProcessorPipeline(steps=[], to_transition=policy_action_to_transition,
                                   to_output=transition_to_policy_action)
    start = TEST_SEED0 + 2  # test seeds 2..7: a wall collision at the first step, collisions, successes
    n_episodes = 6
    info = eval_policy(env, policy, env_pre, env_post, pre, post, n_episodes=n_episodes,
                       max_episodes_rendered=0, start_seed=start)
    env.close()

    assert policy.n_resets == 2  # one rollout per batch of 3
    assert policy.n_calls > 2
    per_ep = info["per_episode"]
    assert [e["seed"] for e in per_ep] == list(range(start, start + n_episodes))
    assert [e["episode_ix"] for e in per_ep] == list(range(n_episodes))

    ref = _straight_reference(cfg.resolve(), list(range(start, start + n_episodes)))
    assert [r["event"] for r in ref] == ["wall_collision"] + ["human_collision"] * 3 + ["success"] * 2
    assert [bool(e["success"]) for e in per_ep] == [r["success"] for r in ref]
    for e, r in zip(per_ep, ref, strict=True):
        assert e["sum_reward"] == pytest.approx(r["return"], abs=1e-4)
    agg = info["aggregated"]
    assert agg["pc_success"] == pytest.approx(100 * np.mean([r["success"] for r in ref]))
    assert agg["pc_success"] == pytest.approx(100 / 3)
    assert agg["avg_sum_reward"] == pytest.approx(np.mean([r["return"] for r in ref]), abs=1e-4)
    assert "video_paths" not in info


def test_lerobot_eval_sums_stop_at_the_episode_end():
    """lerobot's mask keeps the step after each episode's end. Test seeds 0 and 1 side by side: the
    slot that ends first autoresets into seed 2, which starts against a wall (-20 at its first
    step); the env reports nothing more for an ended slot, so each sum is its episode's return."""
    cfg = CrowdNavEnvConfig(task="BoundedCrowdNav-v0")
    env = make_env(cfg, n_envs=2)["crowdnav"][0]
    policy = _GoToGoalPolicy(_GoToGoalConfig())
    env_pre, env_post = make_env_pre_post_processors(cfg, policy.config)
    post = PolicyProcessorPipeline(steps=[], to_transition=policy_action_to_transition,
                                   to_output=transition_to_policy_action)
    info = eval_policy(env, policy, env_pre, env_post, PolicyProcessorPipeline(steps=[]), post, n_episodes=2,
                       max_episodes_rendered=0, start_seed=TEST_SEED0)
    ref = _straight_reference(cfg.resolve(), [TEST_SEED0, TEST_SEED0 + 1, TEST_SEED0 + 2])
    assert ref[2]["event"] == "wall_collision" and ref[2]["return"] <= -20  # what the first to end runs into
    assert [e["sum_reward"] for e in info["per_episode"]] == pytest.approx([r["return"] for r in ref[:2]], abs=1e-4)
    # the env's own records are untouched: a fresh rollout starts unfrozen
    obs, _ = env.reset(seed=[TEST_SEED0 + 2, TEST_SEED0 + 3])
    _, reward, terminated, _, _ = env.step(np.zeros((2, 2), np.float32))
    assert terminated[0] and reward[0] <= -20
    env.close()


def test_dataset_stack_prints_no_library_traceback():
    """torchcodec (which needs FFmpeg) is kept out of the install: lerobot's video-backend probe,
    run whenever it builds a dataset, must not print a traceback."""
    code = ("from lerobot.utils.import_utils import get_safe_default_video_backend; "
            "import lerobot.datasets.lerobot_dataset; print(get_safe_default_video_backend())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr + out.stdout
    assert out.stdout.strip().splitlines()[-1] == "pyav"
