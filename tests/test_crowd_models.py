"""Crowd models past the paper's (docs/simulator.md, "Crowd models"): humans that see the robot
(``robot_visible``) and social-force humans (``human_policy="social_force"``).

A head-on scene where the robot holds course and a reactive human yields; the social force
against an independent implementation of CrowdNav++'s formula on assembled scenes; the reactive
ORCA humans against an explicitly assembled RVO2 scene; the look-ahead model (the roll-out)
unchanged by visibility; determinism whatever the batch and slot; and the defaults bitwise
unchanged (digests recorded before the crowd models existed)."""

import dataclasses
import hashlib
import math

import numpy as np
import pytest

import lerobot_crowdnav  # noqa: F401  (registers the envs)
from lerobot_crowdnav.sim.config import CrowdSimConfig
from lerobot_crowdnav.sim.engine import HUMAN_COLLISION, CrowdSim
from lerobot_crowdnav.sim.orca import compute_new_velocity, make_obstacles

CROWDS = {"reactive ORCA": dict(robot_visible=True), "social force": dict(human_policy="social_force"),
          "reactive social force": dict(robot_visible=True, human_policy="social_force")}


def head_on(robot_visible, human_policy="orca", lateral=0.0, steps=30):
    """Robot from (0, -4) to (0, 4.5) at 1 m/s, straight (it holds course whatever happens); one
    human from (lateral, 4) toward (lateral, -6) at 1 m/s. Returns (closest surface distance,
    largest sideways displacement of the human, collided)."""
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", num_humans=1, randomize_attributes=False,
                                  goal_change_prob=0.0, robot_visible=robot_visible,
                                  human_policy=human_policy), 1)
    sim.reset([0])
    sim.robot_pos[0], sim.robot_goal[0], sim.robot_vel[0] = (0.0, -4.0), (0.0, 4.5), (0.0, 1.0)
    sim.human_pos[0, 0], sim.human_goal[0, 0], sim.human_vel[0, 0] = (lateral, 4.0), (lateral, -6.0), (0.0, -1.0)
    sim.observe()
    dmin, sideways, collided = math.inf, 0.0, False
    for _ in range(steps):  # the human reaches its goal (a respawn) after about 39 steps
        res = sim.step(np.array([[0.0, 1.0]]))
        assert sim.robot_pos[0, 0] == 0.0  # the robot holds its course
        dmin = min(dmin, res.min_distance[0])
        sideways = max(sideways, abs(sim.human_pos[0, 0, 0] - lateral))
        collided |= res.event[0] == HUMAN_COLLISION
    return dmin, sideways, collided


def test_reactive_orca_human_yields_to_a_robot_holding_course():
    # Today's humans never yield: the human walks straight through the robot's path into it.
    dmin, sideways, collided = head_on(robot_visible=False)
    assert collided and dmin < 0 and sideways == 0.0
    # A human that sees the robot steps aside and passes it without contact.
    dmin, sideways, collided = head_on(robot_visible=True)
    assert not collided and dmin > 0.1 and sideways > 0.3


def test_social_force_human_is_pushed_aside_by_a_visible_robot():
    """Social-force repulsion acts along the line of centres and only within about B = 1 m: a
    slightly offset head-on human is pushed sideways only when it sees the robot, but too late to
    avoid a robot that holds course (CrowdNav++'s social force does not anticipate)."""
    blind_dmin, blind_sideways, blind_collided = head_on(False, "social_force", lateral=0.2)
    assert blind_collided and blind_sideways == 0.0
    dmin, sideways, collided = head_on(True, "social_force", lateral=0.2)
    assert sideways > 0.3 and blind_dmin + 0.1 < dmin < 0 and collided  # less deep, still a collision
    # Half a metre off the line, the push is enough: the visible robot passes, with room.
    blind_dmin, _, _ = head_on(False, "social_force", lateral=0.5)
    dmin, _, collided = head_on(True, "social_force", lateral=0.5)
    assert not collided and dmin > blind_dmin + 0.1


# -- social force against CrowdNav++'s formula ------------------------------------------------


def crowdnavpp_social_force(pos, vel, goal, radius, v_pref, robot_pos, robot_radius, robot_visible, A, B, KI, dt):
    """CrowdNav++'s ``SOCIAL_FORCE.predict`` for every human, written independently with numpy:
    pull ``KI (v_des - v)`` toward ``v_des = v_pref (g - p) / |g - p|``, push
    ``sum_j A exp((r + r_j - d_j) / B) (p - p_j) / d_j`` from every other human and, when visible,
    the robot; ``v' = v + (pull + push) dt`` clipped to norm v_pref."""
    n = len(pos)
    out = np.empty((n, 2))
    for i in range(n):
        to_goal = goal[i] - pos[i]
        pull = KI * (to_goal / np.linalg.norm(to_goal) * v_pref[i] - vel[i])
        others = [j for j in range(n) if j != i]
        o_pos, o_r = pos[others], radius[others]
        if robot_visible:
            o_pos, o_r = np.vstack([o_pos, robot_pos]), np.append(o_r, robot_radius)
        away = pos[i] - o_pos
        d = np.linalg.norm(away, axis=1)
        push = np.sum((A * np.exp((radius[i] + o_r - d) / B))[:, None] * away / d[:, None], axis=0)
        new = vel[i] + (pull + push) * dt
        speed = np.linalg.norm(new)
        out[i] = new / speed * v_pref[i] if speed > v_pref[i] else new
    return out


def assembled_scene(seed, n, box):
    """Humans at random in a ``box``-metre square (close encounters and overlaps included), with
    random velocities, radii, speeds and far goals; the robot among them."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-box / 2, box / 2, (n, 2))
    angle = rng.uniform(0, 2 * np.pi, n)
    goal = pos + 9.0 * np.stack([np.cos(angle), np.sin(angle)], 1)  # far: no respawn this step
    return dict(pos=pos, vel=rng.uniform(-1, 1, (n, 2)), goal=goal, radius=rng.uniform(0.3, 0.5, n),
                v_pref=rng.uniform(0.5, 1.5, n), robot_pos=rng.uniform(-1, 1, 2), robot_vel=rng.uniform(-1, 1, 2))


@pytest.mark.parametrize("robot_visible", [False, True])
@pytest.mark.parametrize("seed,n,box,params", [(0, 20, 8.0, {}), (1, 20, 4.0, {}), (2, 6, 3.0, {}),
                                               (3, 12, 5.0, dict(sf_a=1.5, sf_b=0.7, sf_ki=2.0))])
def test_social_force_matches_crowdnavpp_formula_on_assembled_scenes(robot_visible, seed, n, box, params):
    cfg = CrowdSimConfig(task="CrowdNav-v0", num_humans=n, human_policy="social_force",
                         robot_visible=robot_visible, goal_change_prob=0.0, compute_intrusion=False, **params)
    sim = CrowdSim(cfg, 1)
    sim.reset([5])
    c = sim.config
    scene = assembled_scene(seed, n, box)
    sim.human_pos[0], sim.human_vel[0], sim.human_goal[0] = scene["pos"], scene["vel"], scene["goal"]
    sim.human_radius[0], sim.human_vpref[0] = scene["radius"], scene["v_pref"]
    sim.robot_pos[0], sim.robot_vel[0] = scene["robot_pos"], scene["robot_vel"]
    sim.observe()
    want = crowdnavpp_social_force(scene["pos"], scene["vel"], scene["goal"], scene["radius"], scene["v_pref"],
                                   scene["robot_pos"], c.robot_radius, robot_visible, c.sf_a, c.sf_b, c.sf_ki, c.dt)
    sim.step(np.zeros((1, 2)))
    np.testing.assert_allclose(sim.human_vel[0], want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sim.human_pos[0], scene["pos"] + want * c.dt, rtol=1e-12, atol=1e-12)
    if seed < 3:  # the crowded scenes exercise the speed clip, and not every human is clipped
        speed = np.linalg.norm(want, axis=1)
        assert np.any(np.isclose(speed, scene["v_pref"])) and np.any(speed < scene["v_pref"] - 1e-6)
    # The robot's term matters exactly when it is visible.
    other = crowdnavpp_social_force(scene["pos"], scene["vel"], scene["goal"], scene["radius"], scene["v_pref"],
                                    scene["robot_pos"], c.robot_radius, not robot_visible, c.sf_a, c.sf_b, c.sf_ki,
                                    c.dt)
    assert not np.allclose(sim.human_vel[0], other, rtol=1e-9, atol=1e-9)


# -- reactive ORCA humans against an assembled RVO2 scene --------------------------------------


def test_reactive_orca_humans_see_the_robot_as_an_agent_with_its_radius_and_velocity():
    """Every human's new velocity is RVO2's for the scene of the other humans plus the robot (at
    its position, with its last executed velocity and radius r + 0.16), assembled here by hand."""
    cfg = CrowdSimConfig(task="CrowdNav-v0", robot_visible=True, compute_intrusion=False)
    sim = CrowdSim(cfg, 1)
    sim.reset([2_000_000_004])
    c, n = sim.config, sim.config.num_humans
    pad = c.orca_radius_pad + c.orca_safety_space
    rng = np.random.default_rng(0)
    checked_near = 0
    for _ in range(60):
        action = rng.uniform(-1, 1, (1, 2))
        pos = np.vstack([sim.human_pos[0], sim.robot_pos[0]])
        vel = np.vstack([sim.human_vel[0], sim.robot_vel[0]])
        radii = np.append(sim.human_radius[0], c.robot_radius) + pad
        goal, vpref = sim.human_goal[0].copy(), sim.human_vpref[0].copy()
        want = np.empty((n, 2))
        for i in range(n):
            dx, dy = goal[i] - pos[i]
            dist = math.sqrt(dx * dx + dy * dy)
            pref = (dx / dist, dy / dist) if dist > 1 else (dx, dy)
            want[i] = compute_new_velocity(
                i, pos, vel, radii, np.arange(n + 1), n + 1, vpref[i], pref[0], pref[1], sim.neighbor_dist[0], n,
                c.orca_time_horizon, c.orca_time_horizon_obst, c.dt, *make_obstacles([]), np.empty((n + 1, 4)),
                np.empty((n + 1, 4)), np.empty(n + 1, np.int64), np.empty(n + 1), np.empty(1, np.int64), np.empty(1))
        before = sim.human_pos[0].copy()
        sim.step(action)
        moved = ~np.all(sim.human_vel[0] == 0, axis=1)  # respawned humans excepted
        assert np.array_equal(sim.human_vel[0, moved], want[moved])
        assert np.array_equal(sim.human_pos[0, moved], before[moved] + want[moved] * c.dt)
        checked_near += int(np.min(np.linalg.norm(before - pos[n], axis=1)) < 3.0)
    assert checked_near >= 5, "the robot never came near a human: the scene tests nothing"


@pytest.mark.parametrize("crowd", list(CROWDS))
def test_look_ahead_model_ignores_the_robot_and_follows_the_humans_policy(crowd):
    """The roll-out (the look-ahead robot's model, the intrusion test's true futures) leaves the
    robot out, as CrowdNav++'s ``calc_human_future_traj('truth')``: it equals the roll-out of the
    same state with the robot invisible, and its first step is the humans' actual move only when
    they do not see the robot."""
    kw = CROWDS[crowd]
    seen = CrowdSim(CrowdSimConfig(orca_robot="look_ahead", **kw), 1)
    blind = CrowdSim(CrowdSimConfig(orca_robot="look_ahead", **{**kw, "robot_visible": False}), 1)
    seen.reset([2_000_000_007])
    differs = 0
    for _ in range(50):
        blind.load_state_dict(seen.state_dict())
        action = seen.orca_actions()
        assert np.array_equal(action, blind.orca_actions())
        assert np.array_equal(seen.future_pos, blind.future_pos)
        rollout_step1 = seen.future_pos[0, 1].copy()
        seen.step(action)
        moved = ~np.all(seen.human_vel[0] == 0, axis=1)
        differs += int(not np.array_equal(seen.human_pos[0, moved], rollout_step1[moved]))
        if not kw.get("robot_visible"):
            assert np.array_equal(seen.human_pos[0, moved], rollout_step1[moved])
    assert (differs > 0) == bool(kw.get("robot_visible"))


# -- determinism, defaults, configuration -------------------------------------------------------


def rollout(sim, steps):
    obs = [sim.obs.copy()]
    for _ in range(steps):
        sim.step(sim.orca_actions())
        obs.append(sim.obs.copy())
    return np.stack(obs, 1)


@pytest.mark.parametrize("crowd", list(CROWDS))
@pytest.mark.parametrize("preset,orca_robot", [("paper", "look_ahead"), ("crowdnavpp", "current_state")])
def test_episode_bitwise_identical_whatever_batch_and_slot(crowd, preset, orca_robot):
    cfg = CrowdSimConfig(preset=preset, orca_robot=orca_robot, **CROWDS[crowd])
    seed = 777
    single = CrowdSim(cfg, 1)
    single.reset([seed])
    ref = rollout(single, 40)[0]
    for batch, slot in [(5, 3), (64, 41)]:  # serial and parallel kernels
        sim = CrowdSim(cfg, batch)
        seeds = np.arange(batch) + 10
        seeds[slot] = seed
        sim.reset(seeds)
        assert np.array_equal(rollout(sim, 40)[slot], ref), f"batch {batch} slot {slot} diverged"
    # The crowd model changes the episode (same start: the crowd is generated the same way).
    default = CrowdSim(CrowdSimConfig(preset=preset, orca_robot=orca_robot), 1)
    default.reset([seed])
    assert np.array_equal(default.obs[0], ref[0])
    assert not np.array_equal(rollout(default, 40)[0], ref)


def digest(cfg, seeds, steps):
    sim = CrowdSim(cfg, len(seeds))
    sim.reset(seeds)
    h = hashlib.sha256(sim.obs.tobytes())
    for _ in range(steps):
        res = sim.step(sim.orca_actions())
        for x in (sim.obs, res.reward, res.event, res.intrusion_distance, sim.human_pos, sim.human_vel):
            h.update(np.ascontiguousarray(x).tobytes())
    return h.hexdigest()[:16]


@pytest.mark.parametrize("fields,expected", [
    (dict(preset="paper"), "83d8b5409c79336d"),
    (dict(task="CrowdNav-v0", preset="crowdnavpp"), "db4d96de67954fe5"),
    (dict(preset="paper", robot_visible=False, human_policy="orca"), "83d8b5409c79336d"),
])
def test_default_crowd_is_bitwise_unchanged(fields, expected):
    """Digests of 80 ORCA-robot steps on three test seeds, recorded with the simulator as it was
    before the crowd models (git HEAD of the change): the default crowd did not move a bit.
    Re-recorded on 2026-11-28, when the step that ends an episode stopped being an intrusion
    (its intrusion_distance is inf now); without intrusion_distance the digests did not change."""
    assert digest(CrowdSimConfig(**fields), [2_000_000_000, 2_000_000_001, 2_000_000_002], 80) == expected


def test_defaults_resolve_and_bad_values_are_refused():
    cfg = CrowdSimConfig().resolve()
    assert (cfg.robot_visible, cfg.human_policy, cfg.sf_a, cfg.sf_b, cfg.sf_ki) == (False, "orca", 2.0, 1.0, 1.0)
    assert cfg.crowd_description == "ORCA humans, robot invisible"
    assert CrowdSimConfig(robot_visible=True, human_policy="social_force").resolve().crowd_description == \
        "social-force humans, robot visible"
    for bad, match in [(dict(human_policy="sfm"), "human_policy"), (dict(sf_b=0.0), "sf_b"),
                       (dict(sf_a=-1.0), "sf_a"), (dict(sf_ki=float("nan")), "sf_ki"),
                       (dict(robot_visible="yes"), "robot_visible")]:
        with pytest.raises(ValueError, match=match):
            CrowdSimConfig(**bad).resolve()


def test_crowd_flags_reach_gymnasium_and_lerobot():
    import draccus
    import gymnasium as gym
    from lerobot.envs.configs import EnvConfig

    from lerobot_crowdnav.sim.lerobot_env import CrowdNavEnvConfig

    env = gym.make("lerobot_crowdnav/BoundedCrowdNav-v0", robot_visible=True, human_policy="social_force")
    assert env.unwrapped.sim.config.robot_visible and env.unwrapped.sim.params.human_policy == 1
    env.reset(seed=0)
    env.step(env.unwrapped.expert_action("orca"))

    @dataclasses.dataclass
    class Args:
        env: EnvConfig

    cfg = draccus.parse(config_class=Args, args=["--env.type=crowdnav", "--env.robot_visible=true",
                                                  "--env.human_policy=social_force", "--env.sf_a=1.5"])
    assert type(cfg.env) is CrowdNavEnvConfig
    sim_cfg = cfg.env.gym_kwargs["config"]
    assert (sim_cfg.robot_visible, sim_cfg.human_policy, sim_cfg.sf_a, sim_cfg.sf_b) == (True, "social_force", 1.5, 1.0)


# -- the generalization table (lerobot-crowdnav-baselines --only='[generalization]') -------------


def test_generalization_table_runs_every_policy_under_every_crowd_and_resumes(tmp_path):
    import json

    from lerobot_crowdnav.evaluation.baselines import SHIPPED_MODELS, main as baselines_main

    if not (SHIPPED_MODELS / "pdpo_original_h5" / "model.safetensors").exists():
        pytest.skip("no shipped models in this checkout")
    args = ["--only=[generalization]", "--n_episodes=2", "--batch_size=2", "--generalization_tasks=[CrowdNav-v0]",
            "--crowds=[orca,reactive_social_force]", f"--output_dir={tmp_path}"]
    baselines_main(args)
    text = (tmp_path / "generalization.md").read_text()
    assert not (tmp_path / "baselines.md").exists()  # the baseline tables are left alone
    rows = ["ORCA look-ahead", "ORCA current-state", "straight", "PDPO (H = 5, fine-tuned)",
            "PDPO w/o action chunk (H = 1, fine-tuned)"]
    from lerobot_crowdnav.evaluation.generalization import generalization_markdown, read_csv

    table = read_csv((tmp_path / "generalization_original.csv").read_text())  # the main job's report table
    assert sorted((r["method"], r["crowd"]) for r in table) == sorted((row, c) for row in rows
                                                                      for c in ("orca", "reactive_social_force"))
    assert generalization_markdown(table, False, "policy") in text
    assert "| policy | trained (ORCA): SR (%) [95 % CI] | trained (ORCA): human CR / TR (%) | " in text
    metrics = sorted((tmp_path / "generalization").rglob("metrics.json"))
    assert len(metrics) == 2 * len(rows)
    for path in metrics:
        result = json.loads(path.read_text())
        visible = path.parts[-3] == "reactive_social_force"
        assert result["n_episodes"] == 2 and result["env"]["task"] == "CrowdNav-v0"
        assert result["env"]["robot_visible"] == visible
        assert result["env"]["human_policy"] == ("social_force" if visible else "orca")
    # The trained-crowd column is the ordinary baseline row.
    orca = json.loads((tmp_path / "generalization/original/orca/orca_look_ahead/metrics.json").read_text())
    baselines_main(["--only=[original_paper]", "--n_episodes=2", "--batch_size=2", f"--output_dir={tmp_path}"])
    plain = json.loads((tmp_path / "original_paper/orca_look_ahead/metrics.json").read_text())
    assert plain["episodes"] == orca["episodes"]
    stamps = [m.stat().st_mtime_ns for m in metrics]
    baselines_main(args)  # a rerun keeps finished rows
    assert [m.stat().st_mtime_ns for m in metrics] == stamps
    with pytest.raises(SystemExit, match="crowds"):
        baselines_main([*args, "--crowds=[calm]"])


def test_benchmark_has_a_row_per_crowd_with_its_cost_against_the_trained_crowd():
    from lerobot_crowdnav.sim.benchmark import BenchmarkConfig, run

    result = run(BenchmarkConfig(batch_sizes=[2], repeats=2, steps_per_run=40))
    rows = {(r["mode"], r["crowd"]): r for r in result["rows"] if r["api"] == "CrowdNavVectorEnv"}
    for crowd in ("reactive_orca", "social_force", "reactive_social_force"):
        for mode in ("random", "orca robot"):
            row = rows[(mode, crowd)]
            assert row["cost_vs_orca"] > 0 and len(row["runs"]) == 2
    assert rows[("random", "orca")]["cost_vs_orca"] == 1.0
    assert "| CrowdNavVectorEnv | 2 | orca robot | reactive_social_force | " in result["markdown"]
    with pytest.raises(ValueError, match="unknown crowds"):
        run(BenchmarkConfig(crowds=["calm"]))
