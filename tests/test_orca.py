"""ORCA kernel: RVO2 semantics as properties (collision-free pairs, speed bound, feasibility,
least-violation fallback, walls, independence from the others' preferred velocities)."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from lerobot_crowdnav.sim.config import CrowdSimConfig
from lerobot_crowdnav.sim.engine import CrowdSim, WALL_COLLISION, _humans_orca, _make_scratch, make_params
from lerobot_crowdnav.sim.orca import (
    bounding_box,
    compute_new_velocity,
    linear_program2,
    linear_program3,
    make_obstacles,
)

DT = 0.25
NO_OBST = make_obstacles([])


def new_velocities(pos, vel, radii, max_speed, pref, obstacles=NO_OBST, time_horizon=5.0,
                   neighbor_dist=10.0):
    """One synchronous ORCA update of every agent (RVO2's doStep velocity phase)."""
    n = len(pos)
    k = obstacles[0].shape[0]
    lines, proj = np.empty((k + n, 4)), np.empty((k + n, 4))
    nb_idx, nb_dist = np.empty(n, np.int64), np.empty(n)
    ob_idx, ob_dist = np.empty(max(k, 1), np.int64), np.empty(max(k, 1))
    cand = np.arange(n, dtype=np.int64)
    out = np.empty((n, 2))
    for i in range(n):
        out[i] = compute_new_velocity(i, pos, vel, radii, cand, n, max_speed[i], pref[i, 0], pref[i, 1],
                                      neighbor_dist, n, time_horizon, 5.0, DT, *obstacles, lines, proj,
                                      nb_idx, nb_dist, ob_idx, ob_dist)
    return out


def simulate(pos, goals, radii, max_speed, steps, obstacles=NO_OBST):
    pos = np.array(pos, float)
    goals = np.array(goals, float)
    vel = np.zeros_like(pos)
    min_gap = math.inf
    for _ in range(steps):
        d = goals - pos
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        pref = np.where(norm > 1, d / np.maximum(norm, 1e-12), d)
        vel = new_velocities(pos, vel, radii, max_speed, pref, obstacles)
        pos = pos + vel * DT
        for i in range(len(pos)):
            for j in range(i + 1, len(pos)):
                min_gap = min(min_gap, np.linalg.norm(pos[i] - pos[j]) - radii[i] - radii[j])
    return pos, min_gap


@pytest.mark.parametrize("offset", [0.05, -0.2])
def test_head_on_pair_avoids_collision_and_passes(offset):
    # (An exactly symmetric head-on pair deadlocks face to face, in RVO2 as here: the cut-off
    # projection is then purely along the axis. Any asymmetry resolves it.)
    radii = np.array([0.46, 0.46])
    pos, min_gap = simulate([[-4, 0], [4, offset]], [[4, 0], [-4, offset]], radii, np.ones(2), 80)
    assert min_gap > -1e-6, f"agents overlapped by {-min_gap:.4f} m"
    np.testing.assert_allclose(pos, [[4, 0], [-4, offset]], atol=0.1)


def test_crossing_pair_avoids_collision():
    # (A mirror-symmetric crossing deadlocks as the head-on one does; start one agent later.)
    radii = np.array([0.46, 0.46])
    pos, min_gap = simulate([[-4, 0], [0, -4.3]], [[4, 0], [0, 4]], radii, np.ones(2), 80)
    assert min_gap > -1e-6
    np.testing.assert_allclose(pos, [[4, 0], [0, 4]], atol=0.1)


@pytest.mark.parametrize("n, steps, must_arrive", [(4, 400, True), (12, 200, False)])
def test_circle_of_agents_without_collision(n, steps, must_arrive):
    """Agents on a circle heading for their antipodes never overlap. A dense symmetric circle
    can jam for long (a known ORCA behaviour); four agents resolve it."""
    angles = 2 * np.pi * np.arange(n) / n
    start = 5 * np.stack([np.cos(angles), np.sin(angles)], 1)
    start += np.random.default_rng(0).normal(0, 0.02, start.shape)  # break the exact symmetry
    radii = np.full(n, 0.46)
    pos, min_gap = simulate(start, -start, radii, np.ones(n), steps)
    assert min_gap > -1e-3
    if must_arrive:
        assert np.max(np.linalg.norm(pos + start, axis=1)) < 0.3


scene = st.integers(2, 12).flatmap(lambda n: st.tuples(
    st.lists(st.tuples(st.floats(-4, 4), st.floats(-4, 4)), min_size=n, max_size=n),
    st.lists(st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)), min_size=n, max_size=n),
    st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=n, max_size=n),
    st.lists(st.floats(0.2, 0.7), min_size=n, max_size=n),
    st.lists(st.floats(0.3, 1.5), min_size=n, max_size=n),
))


@settings(max_examples=300, deadline=None)
@given(scene)
@example(([(0.0, 0.0)] * 3, [(0.0, 0.0), (1.0, 0.0), (0.125, 1e-05)], [(0.0, 0.0)] * 3, [0.5] * 3,
          [1.0] * 3))  # coincident agents (found by hypothesis)
@example(([(0.0, 0.0)] * 2, [(0.0, 0.0), (4.8e-291, 2e-302)], [(0.0, 0.0)] * 2, [0.5] * 2,
          [1.0] * 2))  # coincident agents, (almost) equal velocities: RVO2 would give NaN
@example(([(0.0, 0.0)] * 9, [(0.0, 0.0)] * 7 + [(0.0, 0.5), (1e-05, 1.0)], [(0.0, 0.0)] * 9,
          [0.5] * 9, [1.0] * 9))  # many coincident agents: LP3 rounding outside the disc
def test_new_velocity_is_finite_and_within_max_speed(s):
    pos, vel, pref, radii, vmax = (np.array(x, float) for x in s)
    out = new_velocities(pos, vel, radii, vmax, pref)
    assert np.all(np.isfinite(out))
    assert np.all(np.linalg.norm(out, axis=1) <= vmax * (1 + 1e-12))


def _violation(lines, v):
    """Signed violation of each half-plane (positive = outside the permitted side)."""
    return (lines[:, 2] * (lines[:, 1] - v[1]) - lines[:, 3] * (lines[:, 0] - v[0]))


half_planes = st.integers(1, 10).flatmap(lambda m: st.lists(
    st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(0, 2 * np.pi)), min_size=m, max_size=m))


@settings(max_examples=400, deadline=None)
@given(half_planes, st.tuples(st.floats(-2, 2), st.floats(-2, 2)), st.floats(0.3, 2.0))
def test_linear_programs_feasible_or_least_violation(planes, opt, radius):
    lines = np.array([[px, py, math.cos(a), math.sin(a)] for px, py, a in planes])
    m = len(lines)
    fail, x, y = linear_program2(lines, m, radius, opt[0], opt[1], False)
    if fail == m:
        # Feasible: inside the disc, all constraints met, and no sampled feasible point is closer
        # to the optimisation velocity.
        assert math.hypot(x, y) <= radius + 1e-9
        assert np.all(_violation(lines, (x, y)) <= 1e-6)
        rng = np.random.default_rng(0)
        r = radius * np.sqrt(rng.random(4000))
        t = 2 * np.pi * rng.random(4000)
        samples = np.stack([r * np.cos(t), r * np.sin(t)], 1)
        ok = np.all(lines[:, 2][None] * (lines[:, 1][None] - samples[:, 1:2])
                    - lines[:, 3][None] * (lines[:, 0][None] - samples[:, :1]) <= 0, axis=1)
        if ok.any():
            best = np.min(np.linalg.norm(samples[ok] - np.array(opt), axis=1))
            assert math.hypot(x - opt[0], y - opt[1]) <= best + 1e-6
    else:
        # Infeasible: LP3 returns a finite velocity in the disc whose worst violation is (up to
        # sampling) minimal among velocities in the disc.
        x, y = linear_program3(lines, m, 0, fail, radius, x, y, np.empty((m, 4)))
        assert math.isfinite(x) and math.isfinite(y)
        assert math.hypot(x, y) <= radius + 1e-9
        worst = np.max(_violation(lines, (x, y)))
        rng = np.random.default_rng(1)
        r = radius * np.sqrt(rng.random(4000))
        t = 2 * np.pi * rng.random(4000)
        samples = np.stack([r * np.cos(t), r * np.sin(t)], 1)
        sampled = np.min(np.max(lines[:, 2][None] * (lines[:, 1][None] - samples[:, 1:2])
                                - lines[:, 3][None] * (lines[:, 0][None] - samples[:, :1]), axis=1))
        assert worst <= sampled + 1e-6


def test_infeasible_crowd_returns_finite_least_violation_velocity():
    # An agent overlapping six neighbours that all rush at it: LP2 fails, LP3 must answer.
    angles = 2 * np.pi * np.arange(6) / 6
    ring = 0.5 * np.stack([np.cos(angles), np.sin(angles)], 1)
    pos = np.vstack([[0, 0], ring])
    vel = np.vstack([[0, 0], -2 * ring])
    radii = np.full(7, 0.46)
    n = 7
    lines, proj = np.empty((n, 4)), np.empty((n, 4))
    v = compute_new_velocity(0, pos, vel, radii, np.arange(n), n, 1.0, 1.0, 0.0, 10.0, n, 5.0, 5.0,
                             DT, *NO_OBST, lines, proj, np.empty(n, np.int64), np.empty(n),
                             np.empty(1, np.int64), np.empty(1))
    assert np.all(np.isfinite(v)) and math.hypot(*v) <= 1.0 + 1e-9
    fail, *_ = linear_program2(lines, 6, 1.0, 1.0, 0.0, False)
    assert fail < 6, "the scene was meant to be infeasible"


def test_agent_result_ignores_other_agents_preferred_velocities():
    """One joint solve equals CrowdNav++'s one-simulator-per-human: agent i's new velocity does
    not depend on the others' goals (preferred velocities)."""
    sim = CrowdSim(CrowdSimConfig(), 1)
    sim.reset([123])
    for _ in range(10):
        sim.step(np.zeros((1, 2)))
    p = make_params(sim.config)
    s = _make_scratch(p.n_humans, p.n_pred, 0)
    base = np.empty((p.n_humans, 2))
    _humans_orca(sim.human_pos[0], sim.human_vel[0], sim.human_goal[0], sim.human_radius[0],
                 sim.human_vpref[0], sim.sim_radius[0], sim.sim_neighbor_dist[0], np.arange(p.n_humans),
                 p, p.neighbor_dist, NO_OBST, s, base)
    rng = np.random.default_rng(0)
    for i in range(p.n_humans):
        goals = sim.human_goal[0] + rng.normal(0, 5, size=sim.human_goal[0].shape)
        goals[i] = sim.human_goal[0, i]
        out = np.empty_like(base)
        _humans_orca(sim.human_pos[0], sim.human_vel[0], goals, sim.human_radius[0],
                     sim.human_vpref[0], sim.sim_radius[0], sim.sim_neighbor_dist[0],
                     np.arange(p.n_humans), p, p.neighbor_dist, NO_OBST, s, out)
        assert np.array_equal(out[i], base[i])
        assert not np.array_equal(out, base)


def test_bounding_box_is_clockwise_and_concave_from_inside():
    pts, unit_dir, nxt, prv, convex = make_obstacles([bounding_box(6.0)])
    assert not convex.any()  # RVO2: vertices of a boundary listed clockwise are non-convex
    area2 = sum(pts[i, 0] * pts[nxt[i], 1] - pts[nxt[i], 0] * pts[i, 1] for i in range(4))
    assert area2 < 0  # clockwise
    np.testing.assert_allclose(np.linalg.norm(unit_dir, axis=1), 1.0)
    assert list(prv[nxt]) == [0, 1, 2, 3]


@settings(max_examples=60, deadline=None)
@given(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), st.tuples(st.floats(-20, 20), st.floats(-20, 20)))
def test_agent_pulled_outside_box_stays_inside(start, target):
    """An ORCA agent whose goal lies outside the walls never crosses them."""
    obstacles = make_obstacles([bounding_box(6.0)])
    radius = 0.36
    pos = np.array([start], float)
    vel = np.zeros((1, 2))
    for _ in range(60):
        d = np.array(target) - pos[0]
        pref = (d / max(np.linalg.norm(d), 1e-12))[None]
        vel = new_velocities(pos, vel, np.array([radius]), np.ones(1), pref, obstacles)
        pos = pos + vel * DT
        assert np.all(np.abs(pos) + radius <= 6.0 + 1e-6), pos


def test_wall_aware_orca_robot_never_touches_a_wall_in_bounded():
    """Over many Bounded episodes the wall-aware ORCA robot collides with a wall only at the first
    step (episodes that start within one robot radius of a wall, a faithful quirk of the spawn)."""
    from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

    env = CrowdNavVectorEnv(64, robot_policy="orca", compute_intrusion=False, orca_robot_wall_aware=True)
    env.reset(seed=10_000)
    seen = 0
    while seen < 300:
        _, _, _, _, info = env.step(None)
        if "final_info" in info:
            m = info["_final_info"]
            fi = info["final_info"]
            walls = (fi["event"] == WALL_COLLISION) & m
            assert np.all(fi["length"][walls] == 1), fi["length"][walls]
            seen += int(m.sum())
