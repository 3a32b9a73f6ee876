"""CrowdNav++'s two ORCA robots and the neighbour-distance quirk (docs/simulator.md, "The ORCA
robot"): the robot's memory (Plan A extrapolation, never-seen dummies), the look-ahead robot's
6 x N agents against an independent roll-out, intrusion, the quirk, determinism."""

import math

import numpy as np
import pytest

from lerobot_crowdnav.sim.config import CrowdSimConfig, split_seeds
from lerobot_crowdnav.sim.engine import DUMMY_POS, DUMMY_RADIUS, RUNNING, CrowdSim, _humans_orca, _make_scratch
from lerobot_crowdnav.sim.orca import compute_new_velocity, make_obstacles

NO_OBST = make_obstacles([])


def orca_episode_steps(sim, steps):
    for _ in range(steps):
        sim.step(sim.orca_actions())
        yield


def robot_velocity(sim, positions, velocities, radii, neighbor_dist):
    """The ORCA robot's velocity for an explicitly assembled scene (agent 0 = the robot)."""
    cfg = sim.config
    pad = cfg.orca_radius_pad + cfg.orca_safety_space
    pos = np.vstack([sim.robot_pos[0], positions])
    vel = np.vstack([sim.robot_vel[0], velocities])
    rad = np.concatenate([[cfg.robot_radius + pad], np.asarray(radii) + pad])
    a = len(pos)
    dx, dy = sim.robot_goal[0] - sim.robot_pos[0]
    dist = math.sqrt(dx * dx + dy * dy)
    pref = (dx / dist, dy / dist) if dist > 1 else (dx, dy)
    lines, proj = np.empty((a, 4)), np.empty((a, 4))
    return np.array(compute_new_velocity(
        0, pos, vel, rad, np.arange(1, a), a - 1, cfg.robot_v_pref, pref[0], pref[1], neighbor_dist,
        a - 1, cfg.orca_time_horizon, cfg.orca_time_horizon_obst, cfg.dt, *NO_OBST, lines, proj,
        np.empty(a, np.int64), np.empty(a), np.empty(1, np.int64), np.empty(1)))


def test_human_out_of_sight_is_extrapolated_step_by_step_and_never_seen_is_a_dummy():
    """The robot's memory against an independent model of CrowdNav++'s ``last_human_states``."""
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", orca_robot="current_state"), 1)
    sim.reset([2_000_000_003])
    n, dt = sim.config.num_humans, sim.config.dt
    mem_pos, mem_vel, mem_r = np.full((n, 2), DUMMY_POS), np.zeros((n, 2)), np.full(n, DUMMY_RADIUS)
    extrapolated = 0
    for t in range(150):
        if t:
            res = sim.step(sim.orca_actions())
            if res.event[0] != RUNNING:
                break
        vis = sim.visible[0]
        mem_pos[~vis] += mem_vel[~vis] * dt
        mem_pos[vis], mem_vel[vis], mem_r[vis] = sim.human_pos[0, vis], sim.human_vel[0, vis], sim.human_radius[0, vis]
        assert np.array_equal(sim.seen_pos[0], mem_pos) and np.array_equal(sim.seen_vel[0], mem_vel)
        assert np.array_equal(sim.seen_radius[0], mem_r)
        extrapolated += int(np.sum(~vis & np.any(mem_vel != 0, axis=1)))
        if t == 0:
            assert (~vis).any()  # slots never seen: dummies at (15, 15), v = 0, r = 0.3
    assert extrapolated >= 10, "no human was out of sight with a remembered velocity"


def test_current_state_robot_sees_its_memory_including_dummies():
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", orca_robot="current_state", preset="crowdnavpp",
                                  persistent_orca_sims=False), 1)
    sim.reset([2_000_000_011])
    for _ in orca_episode_steps(sim, 40):
        got = sim.orca_actions()[0]
        want = robot_velocity(sim, sim.seen_pos[0], sim.seen_vel[0], sim.seen_radius[0],
                              sim.neighbor_dist[0])
        assert np.array_equal(got, want)


def independent_rollout(sim):
    """The humans' ORCA roll-out recomputed from the current state, outside the simulator."""
    p, L, n = sim.params, sim.config.prediction_steps, sim.config.num_humans
    s = _make_scratch(n, L, 0)
    pos, vel = [sim.human_pos[0].copy()], [sim.human_vel[0].copy()]
    for _ in range(L):
        new = np.empty((n, 2))
        _humans_orca(pos[-1], vel[-1], sim.human_goal[0], sim.human_radius[0], sim.human_vpref[0],
                     sim.sim_radius[0], sim.sim_neighbor_dist[0], np.arange(n), p, sim.neighbor_dist[0],
                     NO_OBST, s, new)
        vel.append(new)
        pos.append(pos[-1] + new * sim.config.dt)
    return np.stack(pos), np.stack(vel)  # (L+1, N, 2) each


@pytest.mark.parametrize("preset", ["paper", "crowdnavpp"])
def test_look_ahead_robot_sees_visible_humans_at_the_rollout_positions(preset):
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", preset=preset, orca_robot="look_ahead",
                                  persistent_orca_sims=False), 1)
    sim.reset([2_000_000_021])
    checked = 0
    for _ in range(60):
        pos, vel = independent_rollout(sim)
        got = sim.orca_actions()[0]
        assert np.array_equal(sim.future_pos[0], pos) and np.array_equal(sim.future_vel[0], vel)
        vis = sim.visible[0]
        agents_pos = np.where(vis[None, :, None], pos, DUMMY_POS).reshape(-1, 2)
        agents_vel = np.where(vis[None, :, None], vel, 0.0).reshape(-1, 2)
        radii = np.tile(sim.seen_radius[0], len(pos))
        want = robot_velocity(sim, agents_pos, agents_vel, radii, sim.neighbor_dist[0])
        assert np.array_equal(got, want)
        res = sim.step(got[None])
        if res.event[0] != RUNNING:
            break
        # Roll-out step 1 is the humans' actual move (respawned humans excepted).
        moved = ~np.all(sim.human_vel[0] == 0, axis=1)
        assert np.array_equal(sim.human_pos[0, moved], pos[1, moved])
        checked += int(vis.any())
    assert checked >= 10


def test_rollout_cache_changes_nothing():
    """Stepping after orca_actions (roll-out reused) equals stepping with the same actions and a
    fresh roll-out, with the intrusion test on or off."""
    cfg = CrowdSimConfig(orca_robot="look_ahead")
    # a: roll-out cached by orca_actions; b: the same, recomputed inside step; c: intrusion test off
    off = CrowdSimConfig(orca_robot="look_ahead", compute_intrusion=False)
    a, b, c = CrowdSim(cfg, 4), CrowdSim(cfg, 4), CrowdSim(off, 4)
    for sim in (a, b, c):
        sim.reset(np.arange(4) + 50)
    intrusions = 0
    for _ in range(50):
        act = a.orca_actions()
        b.rollout_depth[:] = 0
        c.rollout_depth[:] = 0
        ra, rb, rc = a.step(act), b.step(act), c.step(act)
        for other, r in ((b, rb), (c, rc)):
            assert np.array_equal(a.obs, other.obs) and np.array_equal(ra.reward, r.reward)
            assert np.array_equal(ra.event, r.event)
        assert np.array_equal(ra.intrusion, rb.intrusion)
        assert np.array_equal(ra.intrusion_distance, rb.intrusion_distance)  # all L cached steps used
        assert not rc.intrusion.any()
        intrusions += int(ra.intrusion.sum())
    assert intrusions > 0


def intrusion_rate(preset, orca_robot, n=64):
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", preset=preset, orca_robot=orca_robot), n)
    sim.reset(split_seeds("test", n))
    alive = np.ones(n, bool)
    steps, intrusions = np.zeros(n), np.zeros(n)
    while alive.any():
        res = sim.step(sim.orca_actions())
        steps += alive
        intrusions += alive & res.intrusion
        alive &= res.event == RUNNING
    return float(np.mean(intrusions / steps))


@pytest.mark.parametrize("preset", ["paper", "crowdnavpp"])
def test_look_ahead_robot_intrudes_far_less_than_current_state_robot(preset):
    look, current = intrusion_rate(preset, "look_ahead"), intrusion_rate(preset, "current_state")
    assert look < 0.4 * current, (look, current)


def respawned(sim):
    """Humans created this step: zero velocity and the antipodal goal of a fresh spawn."""
    return np.all(sim.human_vel == 0, axis=-1) & np.all(sim.human_goal == -sim.human_pos, axis=-1)


@pytest.mark.parametrize("quirk", [True, False])
def test_neighbor_distance_quirk_redraws_on_reset_and_respawn_only_when_on(quirk):
    cfg = CrowdSimConfig(task="CrowdNav-v0", preset="crowdnavpp", randomize_neighbor_dist=quirk)
    sim = CrowdSim(cfg, 16)
    sim.reset(np.arange(16) + 300)
    first = sim.neighbor_dist.copy()
    if quirk:
        assert np.all((first >= 5) & (first < 10)) and len(np.unique(first)) == 16
    else:
        assert np.all(first == 10.0)
    changes = respawns = 0
    for _ in range(150):
        before = sim.neighbor_dist.copy()
        res = sim.step(sim.orca_actions())
        new = respawned(sim).any(axis=1) & (res.event == RUNNING)
        changed = sim.neighbor_dist != before
        if quirk:
            assert np.array_equal(changed[res.event == RUNNING], new[res.event == RUNNING])
        else:
            assert not changed.any()
        changes += int(changed.sum())
        respawns += int(new.sum())
        sim.reset(sim.seeds[res.event != RUNNING] + 1000, np.flatnonzero(res.event != RUNNING))
    assert respawns > 0 and (changes > 0) == quirk


def test_quirk_preset_rules_and_wall_awareness_defaults():
    resolved = lambda **kw: CrowdSimConfig(**kw).resolve()  # noqa: E731
    for quirk in ("randomize_neighbor_dist", "persistent_orca_sims"):
        assert getattr(resolved(preset="crowdnavpp"), quirk) is True
        assert getattr(resolved(preset="crowdnavpp", randomize_attributes=False), quirk) is False
        assert getattr(resolved(preset="paper"), quirk) is False
    assert resolved(preset="paper").orca_robot == "look_ahead"
    assert resolved(preset="crowdnavpp").orca_robot == "current_state"
    assert not resolved().orca_robot_wall_aware
    with pytest.raises(ValueError, match="orca_robot"):
        resolved(orca_robot="psychic")
    # The quirk changes the crowd: same seed, other human trajectories.
    on, off = (CrowdSim(CrowdSimConfig(preset="crowdnavpp", randomize_neighbor_dist=q), 1) for q in (True, False))
    for sim in (on, off):
        sim.reset([5])
        for _ in range(40):
            sim.step(np.zeros((1, 2)))
    assert not np.allclose(on.human_pos, off.human_pos)


def test_wall_unaware_robot_hits_walls_wall_aware_does_not_after_start():
    def wall_hits(aware):
        sim = CrowdSim(CrowdSimConfig(orca_robot_wall_aware=aware, compute_intrusion=False), 64)
        sim.reset(split_seeds("test", 64))
        hits, alive, t = 0, np.ones(64, bool), 0
        while alive.any():
            res = sim.step(sim.orca_actions())
            t += 1
            hits += int(np.sum(alive & (res.event == 3) & (t > 1)))
            alive &= res.event == RUNNING
        return hits

    assert wall_hits(True) == 0
    assert wall_hits(False) >= 5


def test_look_ahead_robot_ignores_a_human_invisible_at_the_last_observation():
    """As CrowdSimPred: its ORCA robot takes the humans' roll-out from
    ``calc_human_future_traj('truth')``, which overwrites every human not visible at the last
    observation with (15, 15), v = 0. A human just out of sensing range, head-on at 1 m/s, leaves
    the robot's velocity as if it were absent; in range, it turns the robot."""
    def velocity(sensing_range, human_y):
        sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", preset="crowdnavpp", orca_robot="look_ahead",
                                      randomize_attributes=False, sensing_range=sensing_range), 1)
        sim.reset([5])
        n = sim.config.num_humans
        sim.human_pos[0] = 1000.0 + 3.0 * np.arange(2 * n).reshape(n, 2)  # parked far away
        sim.human_goal[0] = sim.human_pos[0] + 1000.0
        sim.human_vel[0] = 0.0
        sim.robot_pos[0], sim.robot_goal[0], sim.robot_vel[0] = [0.0, 0.0], [0.0, 20.0], [0.0, 1.0]
        sim.human_pos[0, 0], sim.human_goal[0, 0], sim.human_vel[0, 0] = [0.1, human_y], [0.1, -20.0], [0.0, -1.0]
        sim.observe()
        sim.observe()  # the human's velocity becomes "last observed"
        return sim.orca_actions()[0], bool(sim.visible[0, 0])

    alone, _ = velocity(5.0, 1000.0)
    unseen, visible = velocity(5.0, 6.5)  # surface distance 5.9 m
    assert not visible and np.array_equal(unseen, alone)
    seen, visible = velocity(10.0, 6.5)
    assert visible and np.linalg.norm(seen - alone) > 0.05


def frozen_scene(seed, **cfg):
    """What CrowdNav++'s robot builds its simulator from at its first call, in another episode:
    the memory's radii and the env's neighbour distance right after that episode's reset."""
    sim = CrowdSim(CrowdSimConfig(**cfg), 1)
    sim.reset([seed])
    return sim.seen_radius[0].copy(), float(sim.neighbor_dist[0])


@pytest.mark.parametrize("orca_robot", ["current_state", "look_ahead"])
def test_persistent_robot_keeps_the_radii_and_neighbor_distance_of_its_first_call(orca_robot):
    """The robot against an independent model of ``ORCA.predict``'s persistent simulator: built
    once (radii, neighbour distance), then only positions and velocities change; here it was
    built at episode seed + 1's first observation."""
    cfg = dict(task="CrowdNav-v0", preset="crowdnavpp", orca_robot=orca_robot)
    seed = 2_000_000_031
    radii, nd = frozen_scene(seed + 1, **cfg)
    sim = CrowdSim(CrowdSimConfig(**cfg), 1)
    sim.reset([seed])
    stale = 0
    for _ in range(80):
        got = sim.orca_actions()[0]
        if orca_robot == "current_state":
            want = robot_velocity(sim, sim.seen_pos[0], sim.seen_vel[0], radii, nd)
        else:
            vis = sim.visible[0]
            pos = np.where(vis[None, :, None], sim.future_pos[0], DUMMY_POS).reshape(-1, 2)
            vel = np.where(vis[None, :, None], sim.future_vel[0], 0.0).reshape(-1, 2)
            want = robot_velocity(sim, pos, vel, np.tile(radii, len(sim.future_pos[0])), nd)
        assert np.array_equal(got, want)
        stale += int(np.any(radii != sim.seen_radius[0]))
        if sim.step(got[None]).event[0] != RUNNING:
            break
    assert stale >= 10 and nd != sim.neighbor_dist[0]


def test_persistent_humans_keep_the_radii_and_neighbor_distance_of_their_creation():
    """Each human against an independent model of its own persistent simulator: built at its
    first call after its creation (reset or respawn) with every human's radius and the env's
    neighbour distance then; a neighbour respawned since keeps its old radius."""
    sim = CrowdSim(CrowdSimConfig(task="CrowdNav-v0", preset="crowdnavpp", compute_intrusion=False), 1)
    sim.reset([2_000_000_007])
    cfg, n = sim.config, sim.config.num_humans
    pad = cfg.orca_radius_pad + cfg.orca_safety_space
    built, stale = {}, 0
    for _ in range(190):
        want = np.empty((n, 2))
        for i in range(n):
            radii, nd = built.setdefault(i, (sim.human_radius[0].copy(), float(sim.neighbor_dist[0])))
            stale += int(np.any(radii != sim.human_radius[0]) or nd != sim.neighbor_dist[0])
            dx, dy = sim.human_goal[0, i] - sim.human_pos[0, i]
            dist = math.sqrt(dx * dx + dy * dy)
            pref = (dx / dist, dy / dist) if dist > 1 else (dx, dy)
            want[i] = compute_new_velocity(
                i, sim.human_pos[0], sim.human_vel[0], radii + pad, np.arange(n), n, sim.human_vpref[0, i],
                pref[0], pref[1], nd, n, cfg.orca_time_horizon, cfg.orca_time_horizon_obst, cfg.dt,
                *NO_OBST, np.empty((n, 4)), np.empty((n, 4)), np.empty(n, np.int64), np.empty(n),
                np.empty(1, np.int64), np.empty(1))
        sim.step(np.zeros((1, 2)))
        new = respawned(sim)[0]
        assert np.array_equal(sim.human_vel[0, ~new], want[~new])
        for i in np.flatnonzero(new):
            del built[i]
    assert stale >= 50


def test_simulators_are_resumable_and_older_states_load_where_unused():
    cfg = dict(task="CrowdNav-v0", preset="crowdnavpp", orca_robot="look_ahead")
    a, b = CrowdSim(CrowdSimConfig(**cfg), 2), CrowdSim(CrowdSimConfig(**cfg), 2)
    a.reset([3, 4])
    for _ in range(30):
        a.step(a.orca_actions())
    b.load_state_dict(a.state_dict())
    for _ in range(40):
        assert np.array_equal(a.step(a.orca_actions()).reward, b.step(b.orca_actions()).reward)
    assert np.array_equal(a.obs, b.obs)
    older = {k: v for k, v in a.state_dict().items() if not k.startswith("sim_")}
    with pytest.raises(KeyError):
        b.load_state_dict(older)
    CrowdSim(CrowdSimConfig(persistent_orca_sims=False, **cfg), 2).load_state_dict(older)
