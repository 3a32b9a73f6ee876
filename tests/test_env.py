"""Simulator and gymnasium envs: determinism, observation layout, reward branches, termination,
walls, episode accounting and bad input."""

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import lerobot_crowdnav  # noqa: F401  (registers the envs)
from lerobot_crowdnav.sim.config import SEED_SPLITS, CrowdSimConfig, split_seeds
from lerobot_crowdnav.sim.engine import (
    EVENT_NAMES,
    HUMAN_COLLISION,
    RUNNING,
    SUCCESS,
    TIMEOUT,
    WALL_COLLISION,
    CrowdSim,
)
from lerobot_crowdnav.sim.envs import CrowdNavEnv, CrowdNavVectorEnv, structured

FAR = 1000.0


def rollout(sim, steps, policy="orca"):
    """Observations of ``steps`` steps of every slot with a state-dependent policy."""
    obs = [sim.obs.copy()]
    for _ in range(steps):
        a = sim.orca_actions() if policy == "orca" else sim.straight_actions()
        sim.step(a)
        obs.append(sim.obs.copy())
    return np.stack(obs, 1)  # (B, T+1, obs_dim)


@pytest.mark.parametrize("preset,orca_robot", [("paper", "look_ahead"), ("paper", "current_state"),
                                               ("crowdnavpp", "current_state"), ("crowdnavpp", "look_ahead")])
def test_episode_bitwise_identical_whatever_batch_and_slot(preset, orca_robot):
    cfg = CrowdSimConfig(preset=preset, orca_robot=orca_robot)
    seed = 777
    single = CrowdSim(cfg, 1)
    single.reset([seed])
    ref = rollout(single, 60)[0]
    # Serial path (B < 16) and the parallel one (B >= 16), the seed in different slots.
    for batch, slot in [(5, 3), (64, 41)]:
        sim = CrowdSim(cfg, batch)
        seeds = np.arange(batch) + 10
        seeds[slot] = seed
        sim.reset(seeds)
        got = rollout(sim, 60)[slot]
        assert np.array_equal(got, ref), f"batch {batch} slot {slot} diverged"
    # And a different seed gives a different episode.
    single.reset([seed + 1])
    assert not np.array_equal(rollout(single, 5)[0], ref[:6])


def test_seed_splits_are_disjoint_and_sized():
    ranges = {k: set(range(*v)) if v[1] - v[0] < 10_000 else None for k, v in SEED_SPLITS.items()}
    ranges["holdout"] = set(range(*SEED_SPLITS["holdout"]))
    assert len(ranges["val"]) == 1000 and len(ranges["test"]) == 500 and len(ranges["holdout"]) == 10_000
    assert not ranges["val"] & ranges["test"] and not (ranges["val"] | ranges["test"]) & ranges["holdout"]
    train_lo, train_hi = SEED_SPLITS["train"]
    for split in ("val", "test", "holdout"):
        assert all(not train_lo <= s < train_hi for s in ranges[split])
    assert split_seeds("test", 3) == [SEED_SPLITS["test"][0] + i for i in range(3)]
    with pytest.raises(ValueError):
        split_seeds("test", 501)


def test_episode_generation_matches_spec():
    sim = CrowdSim(CrowdSimConfig(), 256)
    sim.reset(np.arange(256))
    cfg = sim.config
    start, goal = sim.robot_pos, sim.robot_goal
    assert np.all(np.abs(start) <= 6) and np.all(np.abs(goal) <= 6)
    assert np.all(np.linalg.norm(start - goal, axis=1) >= 8)
    np.testing.assert_array_equal(sim.human_goal, -sim.human_pos)  # antipodal goals
    assert np.all(sim.human_vel == 0) and np.all(sim.robot_vel == 0)
    # Start = R (cos a, sin a) + noise in [0, 2)^2 (positively biased, not centred).
    for b in range(8):
        for p in sim.human_pos[b]:
            lo, hi = p - 2.0, p
            # Some angle puts R(cos, sin) inside the box [p - 2, p]: the circle meets the box.
            nearest = np.linalg.norm(np.clip(0.0, lo, hi))
            farthest = max(math.hypot(x, y) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]))
            assert nearest <= cfg.circle_radius <= farthest
    assert np.all((sim.human_radius >= 0.3) & (sim.human_radius <= 0.5))
    assert np.all((sim.human_vpref >= 0.5) & (sim.human_vpref <= 1.5))
    # Humans start clear of every earlier agent's position and goal (+ discomfort distance).
    for b in range(16):
        for i in range(20):
            for j in range(i):
                gap = sim.human_radius[b, i] + sim.human_radius[b, j] + 0.25
                assert np.linalg.norm(sim.human_pos[b, i] - sim.human_pos[b, j]) >= gap
                assert np.linalg.norm(sim.human_pos[b, i] - sim.human_goal[b, j]) >= gap
    fixed = CrowdSim(CrowdSimConfig(preset="crowdnavpp", randomize_attributes=False), 4)
    fixed.reset(np.arange(4))
    assert np.all(fixed.human_radius == 0.3) and np.all(fixed.human_vpref == 1.0)


def hand_built(task="BoundedCrowdNav-v0", **kw):
    """One env with every human parked far away, walking away from the robot."""
    sim = CrowdSim(CrowdSimConfig(task=task, **kw), 1)
    sim.reset([5])
    n = sim.config.num_humans
    sim.human_pos[0] = FAR + 3.0 * np.arange(2 * n).reshape(n, 2)
    sim.human_goal[0] = sim.human_pos[0] + FAR
    sim.human_vel[0] = 0.0
    sim.robot_pos[0] = [0.0, 0.0]
    sim.robot_goal[0] = [0.0, 5.0]
    sim.robot_vel[0] = 0.0
    sim.potential[0] = -5.0
    return sim


def test_observation_layout_sorting_sentinel_mask_and_stale_velocity():
    sim = hand_built()
    cfg = sim.config
    # Three visible humans at increasing distance (listed out of order), one just out of range.
    sim.human_pos[0, 3] = [3.0, 0.0]
    sim.human_pos[0, 7] = [0.0, 1.5]
    sim.human_pos[0, 9] = [-2.0, -2.0]
    r_out = cfg.sensing_range + cfg.robot_radius + sim.human_radius[0, 11] + 0.01
    sim.human_pos[0, 11] = [r_out, 0.0]
    sim.human_vel[0, 7] = [0.4, -0.2]
    obs = sim.observe()[0].copy()
    view = structured(obs)
    assert obs.shape == (269,)
    np.testing.assert_allclose(view.robot, [0, 0, 0.2, 0, 5, 1.0, np.pi / 2], rtol=1e-6)
    np.testing.assert_array_equal(view.mask, [1, 1, 1] + [0] * 17)
    np.testing.assert_allclose(view.humans[0, 0], [0.0, 1.5])
    np.testing.assert_allclose(view.humans[1, 0], [-2.0, -2.0], rtol=1e-6)
    np.testing.assert_allclose(view.humans[2, 0], [3.0, 0.0])
    assert np.all(view.humans[3:] == 15.0)
    # First observation: the last observed velocity is still zero, so predictions stand still.
    np.testing.assert_allclose(view.humans[0], np.tile([0.0, 1.5], (6, 1)))
    # Next observation: the prediction uses the velocity seen at the previous one (stale), not
    # the current velocity.
    sim.human_vel[0, 7] = [-1.0, 0.0]
    view = structured(sim.observe()[0].copy())
    expected = np.array([[0.4 * 0.25 * k, 1.5 - 0.2 * 0.25 * k] for k in range(6)])
    np.testing.assert_allclose(view.humans[0], expected, atol=1e-6)


def step_once(sim, action=(0.0, 0.0)):
    res = sim.step(np.array([action], float))
    return float(res.reward[0]), int(res.event[0]), res


def test_reward_potential_branch():
    sim = hand_built()
    reward, event, _ = step_once(sim, (0.0, 1.0))  # moves after the reward is computed
    assert event == RUNNING and reward == pytest.approx(0.0)  # potential was -5, still at 5 m
    reward, _, _ = step_once(sim)
    assert reward == pytest.approx(2 * (-(5 - 0.25) + 5))


def test_reward_discomfort_branch():
    sim = hand_built()
    sim.human_pos[0, 0] = [0.0, -(0.2 + sim.human_radius[0, 0] + 0.1)]  # surface distance 0.1
    sim.observe()
    reward, event, res = step_once(sim)
    assert event == RUNNING
    assert res.min_distance[0] == pytest.approx(0.1)
    assert reward == pytest.approx((0.1 - 0.25) * 10 * 0.25)


def test_reward_collision_goal_timeout_and_wall_branches():
    sim = hand_built()
    sim.human_pos[0, 0] = [0.1, 0.0]
    reward, event, _ = step_once(sim)
    assert (event, reward) == (HUMAN_COLLISION, -20.0)

    sim = hand_built()
    sim.robot_pos[0] = [0.0, 4.85]  # 0.15 < radius 0.2 from the goal
    reward, event, _ = step_once(sim)
    assert (event, reward) == (SUCCESS, 10.0)

    sim = hand_built()
    sim.step_count[0] = 196  # t = 49 s >= time_limit - 1
    reward, event, _ = step_once(sim)
    assert (event, reward) == (TIMEOUT, 0.0)

    sim = hand_built()
    sim.robot_pos[0] = [5.8, 0.0]  # |x| + r = 6.0: touching the wall
    reward, event, _ = step_once(sim)
    assert (event, reward) == (WALL_COLLISION, -20.0)
    sim = hand_built(task="CrowdNav-v0")
    sim.robot_pos[0] = [5.8, 0.0]
    _, event, res = step_once(sim)
    assert event == RUNNING and not res.out_of_bounds[0]
    sim.robot_pos[0] = [6.5, 0.0]
    _, event, res = step_once(sim)
    assert event == RUNNING and res.out_of_bounds[0]


@pytest.mark.parametrize("k, penalty", [(1, -5.0), (2, -2.5), (3, -1.25), (4, -0.625), (5, -0.3125)])
def test_prediction_penalty_takes_the_worst_step(k, penalty):
    sim = hand_built()
    # A visible human 4 m away whose observed velocity brings its prediction k steps ahead onto
    # the robot; a second one whose prediction hits later adds nothing (only the worst counts).
    sim.human_pos[0, 0] = [4.0, 0.0]
    sim.human_vel[0, 0] = [-4.0 / (k * 0.25), 0.0]
    sim.human_pos[0, 1] = [0.0, -4.0]
    sim.human_vel[0, 1] = [0.0, 4.0 / (5 * 0.25)]
    sim.observe()
    sim.observe()  # the velocity becomes "last observed"
    reward, event, res = step_once(sim)
    assert event == RUNNING
    assert reward == pytest.approx(penalty)
    assert res.prediction_penalty[0] == pytest.approx(penalty)  # the reward's penalty part, apart


def test_termination_at_step_197_and_time_limit():
    env = CrowdNavVectorEnv(1, task="CrowdNav-v0", compute_intrusion=False)
    env.reset(seed=3)
    sim = env.sim
    n = sim.config.num_humans
    sim.human_pos[0] = FAR + 3.0 * np.arange(2 * n).reshape(n, 2)
    sim.human_goal[0] = sim.human_pos[0] + FAR
    sim.observe()
    steps = 0
    while True:
        _, _, terminated, truncated, info = env.step(np.zeros((1, 2)))
        steps += 1
        if terminated[0] or truncated[0]:
            break
    assert steps == 197 == sim.config.max_steps
    assert truncated[0] and not terminated[0]
    assert info["final_info"]["length"][0] == 197


def test_robot_driven_into_wall_collides_when_disc_touches():
    sim = hand_built()
    sim.robot_goal[0] = [0.0, 5.0]
    events = []
    for _ in range(40):
        x = sim.robot_pos[0, 0]
        _, event, _ = step_once(sim, (1.0, 0.0))
        events.append((x, event))
        if event != RUNNING:
            break
    x_last, event = events[-1]
    assert event == WALL_COLLISION
    assert x_last + 0.2 >= 6.0 and events[-2][0] + 0.2 < 6.0


def test_episode_record_path_length_excludes_jump_to_next_episode_and_goal_is_the_episodes():
    env = CrowdNavVectorEnv(4, task="CrowdNav-v0", robot_policy="straight", compute_intrusion=False)
    obs, _ = env.reset(seed=100)
    positions = [[p] for p in obs[:, :2].astype(np.float64)]
    goals = obs[:, 3:5].copy()
    done_records = []
    while len(done_records) < 4:
        obs, _, term, trunc, info = env.step(None)
        for b in range(4):
            if term[b] or trunc[b]:
                if len(done_records) < 4 and b not in [r[0] for r in done_records]:
                    path = np.sum(np.linalg.norm(np.diff(np.array(positions[b]), axis=0), axis=1))
                    done_records.append((b, path, info["final_info"]["path_length"][b],
                                         np.linalg.norm(obs[b, :2] - positions[b][-1])))
                np.testing.assert_allclose(info["final_info"]["goal"][b], goals[b], atol=1e-5)  # float32 obs
                positions[b], goals[b] = [obs[b, :2].astype(np.float64)], obs[b, 3:5]
            else:
                positions[b].append(obs[b, :2].astype(np.float64))
    for _, from_positions, reported, jump in done_records:
        assert reported == pytest.approx(from_positions, abs=1e-4)  # float32 observations
        assert jump > 0.5  # the next episode's start is elsewhere, and it was not added


def test_prediction_penalty_is_reported_per_step_and_summed_per_episode():
    """The step info's penalty is exactly what the reward loses against a twin env whose penalty
    never fires (same seeds and actions, so the same episodes); an episode's record sums it; a
    state saved before the sum existed resumes with it at zero."""
    def make(**kw):
        return CrowdNavVectorEnv(4, task="CrowdNav-v0", preset="crowdnavpp", robot_policy="straight", **kw)
    env, twin = make(), make(prediction_radius=-0.3)  # robot radius 0.3: centres closer than 0
    env.reset(seed=7)
    twin.reset(seed=7)
    summed, ended = np.zeros(4), []
    while len(ended) < 6:
        _, reward, term, trunc, info = env.step(None)
        _, twin_reward, _, _, twin_info = twin.step(None)
        np.testing.assert_allclose(info["prediction_penalty"], reward - twin_reward, atol=1e-12)
        assert not twin_info["prediction_penalty"].any()
        summed += info["prediction_penalty"]
        for b in np.flatnonzero(term | trunc):
            ended.append((summed[b], info["final_info"]["prediction_penalty"][b]))
            summed[b] = 0.0
    np.testing.assert_allclose([e[1] for e in ended], [e[0] for e in ended])
    assert min(e[1] for e in ended) < 0  # walking straight into a crowd gets penalized
    state = env.state_dict()
    assert state["_ep_pred"].any() or not summed.any()
    del state["_ep_pred"]
    env.load_state_dict(state)
    assert not env._ep_pred.any()


def test_bad_actions_raise_clear_errors_and_overspeed_is_clipped():
    env = CrowdNavEnv()
    env.reset(seed=1)
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.inf, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    vec = CrowdNavVectorEnv(3)
    vec.reset(seed=1)
    with pytest.raises(ValueError, match=r"shape \(3, 2\)"):
        vec.step(np.zeros((2, 2)))
    obs, *_ = env.step(np.array([3.0, 4.0]))
    np.testing.assert_allclose(obs[7:9], [0.6, 0.8], rtol=1e-6)
    with pytest.raises(ValueError, match="unknown task"):
        CrowdSimConfig(task="Nope-v0").resolve()
    with pytest.raises(ValueError, match="unknown preset"):
        CrowdSimConfig(preset="nope").resolve()
    with pytest.raises(ValueError, match="dt"):
        CrowdSimConfig(dt=-1.0).resolve()


@pytest.mark.parametrize("task", ["CrowdNav-v0", "BoundedCrowdNav-v0"])
def test_gymnasium_registration_check_env_and_native_vector_env(task):
    env = gym.make(f"lerobot_crowdnav/{task}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=False)
    messages = [str(w.message) for w in caught]
    assert messages and all("infinit" in m for m in messages), messages  # only the unbounded observations
    assert env.unwrapped.config.bounded == (task == "BoundedCrowdNav-v0")
    vec = gym.make_vec(f"lerobot_crowdnav/{task}", num_envs=6, vectorization_mode="vector_entry_point")
    assert isinstance(vec, CrowdNavVectorEnv)
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (6, 269) and obs.dtype == np.float32
    ended = 0
    for _ in range(250):
        obs, reward, term, trunc, info = vec.step(vec.expert_actions("orca"))
        if "final_info" in info:
            m = info["_final_info"]
            ended += m.sum()
            # Autoreset: the returned observation starts a new episode (robot at rest).
            assert np.all(obs[m, 7:9] == 0)
            assert np.all(info["final_info"]["is_success"][m] == (info["final_info"]["event"][m] == SUCCESS))
    assert ended >= 6
    obs, _ = env.reset(seed=0)
    while True:  # the single env's episode record: plain Python values, the goal a 2-list
        obs, _, term, trunc, info = env.step(env.unwrapped.expert_action("straight"))
        if term or trunc:
            break
    assert EVENT_NAMES[info["episode"]["event"]] == info["event"] and isinstance(info["episode"]["length"], int)
    assert info["episode"]["goal"] == pytest.approx(obs[3:5].tolist(), abs=1e-5)


def test_render_rgb_array():
    env = gym.make("lerobot_crowdnav/CrowdNav-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (512, 512, 3) and frame.dtype == np.uint8
    assert frame.std() > 5  # something is drawn


def test_an_episode_gif_holds_every_drawn_frame_exactly(tmp_path):
    """The GIF shares one palette of the frames' own colours (lossless), and frames with more
    colours than a palette holds still write, quantized by Pillow."""
    from PIL import Image, ImageSequence

    from lerobot_crowdnav.sim.render import render_frame, save_video

    env = CrowdNavEnv(task="BoundedCrowdNav-v0")
    env.reset(seed=3)
    frames = [render_frame(env.sim, 0)]
    for _ in range(12):
        env.step(env.expert_action("orca"))
        frames.append(render_frame(env.sim, 0))
    with Image.open(save_video(frames, tmp_path / "episode.gif")) as gif:
        decoded = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(gif)]
    assert len(decoded) == len(frames) and all(np.array_equal(a, b) for a, b in zip(decoded, frames))
    noise = [np.random.default_rng(s).integers(0, 256, (64, 64, 3), dtype=np.uint8) for s in range(3)]
    with Image.open(save_video(noise, tmp_path / "noise.gif")) as gif:
        assert gif.n_frames == 3


def test_vector_render_call_draws_only_requested_slots(monkeypatch):
    env = CrowdNavVectorEnv(8, render_mode="rgb_array")
    env.reset(seed=0)
    drawn = []
    original = env.render_slot
    monkeypatch.setattr(env, "render_slot", lambda b: drawn.append(b) or original(b))
    frames = env.call("render")
    assert len(frames) == 8 and drawn == []
    stacked = np.stack(frames[:2])  # what lerobot's rollout does
    assert stacked.shape == (2, 512, 512, 3) and drawn == [0, 1]
    assert frames[-1].shape == (512, 512, 3) and drawn[-1] == 7


def test_gym_make_imports_the_package_itself_with_module_syntax():
    """gymnasium 1.x has no plugin entry points; ``module:id`` makes it import the package."""
    import subprocess
    import sys

    code = ("import gymnasium as gym; "
            "env = gym.make('lerobot_crowdnav:lerobot_crowdnav/CrowdNav-v0'); "
            "print(env.reset(seed=0)[0].shape)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(269,)"


def test_a_respawn_keeps_clear_of_the_human_it_replaces_by_that_ones_radius():
    """CrowdNav++ checks a respawned human's start against the human it replaces, still in its list
    with its own radius: a start clear by twice the new radius but not by new + old is refused."""
    from lerobot_crowdnav.sim.engine import _spawn_human, make_params, seed_rng

    cfg = CrowdSimConfig(task="CrowdNav-v0").resolve()  # paper preset: radii drawn from [0.3, 0.5]
    p, n = make_params(cfg), cfg.num_humans

    def spawn(seed, old_at, r_old):
        rng = np.zeros(4, np.uint64)
        seed_rng(rng, seed)
        far = 1000.0 + 10.0 * np.arange(2 * n, dtype=np.float64).reshape(n, 2)  # nobody else near
        hp, hg, hr = far.copy(), far.copy(), np.full(n, 0.3)
        hp[0] = hg[0] = old_at  # the human being replaced, at its goal
        hr[0] = r_old
        robot = np.array([-1000.0, -1000.0])
        _spawn_human(0, n, rng, robot, robot.copy(), hp, np.zeros((n, 2)), hg, hr, np.ones(n), np.array([10.0]), p)
        return hp[0].copy(), float(hr[0])

    seed = next(s for s in range(100) if spawn(s, (2000.0, 2000.0), 0.3)[1] < 0.4)
    first, r_new = spawn(seed, (2000.0, 2000.0), 0.3)  # the first candidate, nobody near it
    r_old, discomfort = 0.5, cfg.discomfort_dist
    d = (2 * r_new + discomfort + r_new + r_old + discomfort) / 2  # between the two clearances
    old_at = first + np.array([d, 0.0])
    start, _ = spawn(seed, old_at, r_old)
    assert not np.array_equal(start, first)
    assert np.linalg.norm(start - old_at) >= r_new + r_old + discomfort
