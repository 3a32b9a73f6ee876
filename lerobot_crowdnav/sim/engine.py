"""The batched crowd simulator: B environments stepped by one compiled call.

State is a set of arrays with a leading batch axis (world frame, metres, m/s, seconds):

=================  ==============  ==========================================================
robot_pos/vel/goal  (B, 2)          robot centre, last executed velocity, goal
potential           (B,)            CrowdNav++ potential ``-|pos - goal|`` (progress reward)
step_count          (B,)            steps taken in the current episode
human_pos/vel/goal  (B, N, 2)       true human states
human_radius/vpref  (B, N)
seen_pos/vel/radius (B, N[, 2])     the robot's memory of each human (CrowdNav++
                                    ``last_human_states``): last observed state, extrapolated
                                    ``p += v dt`` while out of sight, a dummy until first seen
pred                (B, N, L+1, 2)  positions shown in the last observation (k = 0..L), absolute
visible             (B, N)          visibility in the last observation (by human index)
neighbor_dist       (B,)            the env's ORCA neighbour distance (redrawn by the quirk)
sim_radius          (B, N+1, N)     with persistent ORCA simulators (CrowdNav++): the humans' radii
sim_neighbor_dist   (B, N+1)        and the neighbour distance each one was built with, row 0 the
                                    robot's, row 1 + i human i's (0: not built yet)
future_pos/vel      (B, L+1, N, 2)  the humans' ORCA roll-out from the current state, k = 0..L
rollout_depth       (B,)            steps of that roll-out computed since the last move (0: none)
rng                 (B, 4) uint64   xoshiro256** state of the episode's own generator
=================  ==============  ==========================================================

The roll-out (robot invisible, no goal changes, no respawns) is computed at most once per step,
as deep as needed: step 1 is the humans' actual move, steps 1..L the intrusion test's true
futures and, with step 0, the look-ahead ORCA robot's 6 x N agents.

Crowd models (docs/simulator.md, "Crowd models"): the humans follow ORCA or CrowdNav++'s social
force (``human_policy``), in the roll-out too; with ``robot_visible`` they also count the robot
(its position and last executed velocity) in their actual move, computed apart from the roll-out,
which leaves the robot out as CrowdNav++'s does.

Every random draw of an episode (crowd generation, goal changes, respawns) comes from the
generator seeded with the episode seed, and no computation mixes environments, so a seed gives a
bitwise-identical episode whatever the batch size or the slot.

Step order (CrowdNav++): (1) robot action clipped, humans' ORCA velocities from current states;
(2) reward, termination and intrusion test on the pre-move positions; (3) everyone moves,
t += dt; (4) observation; (5) random goal changes when due, then respawn of humans at their goal.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from .config import HUMAN_POLICIES, ORCA_ROBOTS, CrowdSimConfig
from ..layout import SELF_DIM
from .orca import bounding_box, compute_new_velocity, insert_sorted, make_obstacles

# Episode events (``info["event"]``).
RUNNING, SUCCESS, HUMAN_COLLISION, WALL_COLLISION, TIMEOUT = 0, 1, 2, 3, 4
# The episodes' version, saved with every evaluation: bump it when a seed's episode changes (an
# evaluation saved under another one is run again, not reused). 2: a respawn kept clear of the
# human it replaces by that one's radius (2026-11-28).
SIM_VERSION = 2
EVENT_NAMES = ("running", "success", "human_collision", "wall_collision", "timeout")

ROBOT_THETA = math.pi / 2  # holonomic robot: heading stays at its initial pi/2 (CrowdNav++)
# CrowdNav++'s stand-in for a human the robot has never seen: (15, 15), v = 0, r = 0.3.
DUMMY_POS, DUMMY_RADIUS = 15.0, 0.3
LOOK_AHEAD, CURRENT_STATE = 0, 1  # Params.orca_robot, in config.ORCA_ROBOTS order
HUMANS_ORCA, HUMANS_SOCIAL_FORCE = 0, 1  # Params.human_policy, in config.HUMAN_POLICIES order

_MAX_REJECTIONS = 100_000  # rejection-sampling guard for crowded custom configs


class Params(NamedTuple):
    """The resolved config as the compiled kernels see it (a numba-friendly tuple)."""

    n_humans: int
    bounded: bool
    arena: float
    robot_radius: float
    robot_vpref: float
    min_start_goal: float
    spawn_margin: float
    sensing: float
    randomize: bool
    human_radius: float
    human_vpref: float
    radius_lo: float
    radius_hi: float
    vpref_lo: float
    vpref_hi: float
    circle_radius: float
    start_noise: float
    dt: float
    time_limit: float
    n_pred: int
    goal_every: int
    goal_prob: float
    discomfort: float
    neighbor_dist: float
    time_horizon: float
    time_horizon_obst: float
    orca_pad: float
    orca_robot: int  # LOOK_AHEAD or CURRENT_STATE
    nd_random: bool  # the neighbour-distance quirk
    persistent: bool  # CrowdNav++'s persistent RVO2 simulators
    nd_lo: float
    nd_hi: float
    success_reward: float
    collision_penalty: float
    discomfort_factor: float
    potential_factor: float
    pred_radius: float
    sentinel: float
    intrusion: bool
    robot_visible: bool  # the humans count the robot as an agent (CrowdNav++ robot.visible)
    human_policy: int  # HUMANS_ORCA or HUMANS_SOCIAL_FORCE
    sf_a: float
    sf_b: float
    sf_ki: float


def make_params(cfg: CrowdSimConfig) -> Params:
    return Params(
        n_humans=cfg.num_humans, bounded=cfg.bounded, arena=cfg.arena_size,
        robot_radius=cfg.robot_radius, robot_vpref=cfg.robot_v_pref,
        min_start_goal=cfg.robot_min_start_goal_dist, spawn_margin=cfg.robot_spawn_margin,
        sensing=cfg.sensing_range,
        randomize=cfg.randomize_attributes, human_radius=cfg.human_radius,
        human_vpref=cfg.human_v_pref, radius_lo=cfg.human_radius_range[0],
        radius_hi=cfg.human_radius_range[1], vpref_lo=cfg.human_v_pref_range[0],
        vpref_hi=cfg.human_v_pref_range[1], circle_radius=cfg.circle_radius,
        start_noise=cfg.start_noise, dt=cfg.dt, time_limit=cfg.time_limit,
        n_pred=cfg.prediction_steps, goal_every=cfg.goal_change_every,
        goal_prob=cfg.goal_change_prob, discomfort=cfg.discomfort_dist,
        neighbor_dist=cfg.orca_neighbor_dist, time_horizon=cfg.orca_time_horizon,
        time_horizon_obst=cfg.orca_time_horizon_obst,
        orca_pad=cfg.orca_radius_pad + cfg.orca_safety_space,
        orca_robot=ORCA_ROBOTS.index(cfg.orca_robot), nd_random=cfg.randomize_neighbor_dist,
        persistent=cfg.persistent_orca_sims,
        nd_lo=cfg.neighbor_dist_range[0], nd_hi=cfg.neighbor_dist_range[1],
        success_reward=cfg.success_reward, collision_penalty=cfg.collision_penalty,
        discomfort_factor=cfg.discomfort_penalty_factor, potential_factor=cfg.potential_factor,
        pred_radius=cfg.prediction_radius, sentinel=cfg.sentinel,
        intrusion=cfg.compute_intrusion, robot_visible=bool(cfg.robot_visible),
        human_policy=HUMAN_POLICIES.index(cfg.human_policy), sf_a=cfg.sf_a, sf_b=cfg.sf_b,
        sf_ki=cfg.sf_ki,
    )


# --------------------------------------------------------------------------------------------
# Per-episode random numbers: xoshiro256** seeded by splitmix64(seed).

_U1, _U5, _U7, _U9, _U11, _U17, _U45 = (np.uint64(v) for v in (1, 5, 7, 9, 11, 17, 45))
_U64 = np.uint64(64)


@nb.njit(cache=True, inline="always")
def _rotl(x, k):
    return (x << k) | (x >> (_U64 - k))


@nb.njit(cache=True)
def _splitmix64(x):
    z = x + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31)), x + np.uint64(0x9E3779B97F4A7C15)


@nb.njit(cache=True)
def seed_rng(state, seed):
    x = np.uint64(seed)
    for i in range(4):
        z, x = _splitmix64(x)
        state[i] = z


@nb.njit(cache=True, inline="always")
def uniform(s):
    """A float64 in [0, 1) from the generator state ``s`` (4 uint64), advancing it."""
    result = _rotl(s[1] * _U5, _U7) * _U9
    t = s[1] << _U17
    s[2] ^= s[0]
    s[3] ^= s[1]
    s[1] ^= s[2]
    s[0] ^= s[3]
    s[2] ^= t
    s[3] = _rotl(s[3], _U45)
    return np.float64(result >> _U11) * (1.0 / 9007199254740992.0)


# --------------------------------------------------------------------------------------------
# Crowd generation (CrowdNav++ generate_robot / generate_circle_crossing_human /
# update_human_goals_randomly).


@nb.njit(cache=True)
def _clear_of_agents(x, y, r_self, skip, rp, rg, p, hp, hg, hr, n_check):
    """True if (x, y) is at least ``r_self + r_other + discomfort`` from every agent's position
    and goal (robot, then humans ``0..n_check-1`` except ``skip``); strict ``<`` rejects."""
    d_min = r_self + p.robot_radius + p.discomfort
    if (x - rp[0]) ** 2 + (y - rp[1]) ** 2 < d_min * d_min:
        return False
    if (x - rg[0]) ** 2 + (y - rg[1]) ** 2 < d_min * d_min:
        return False
    for j in range(n_check):
        if j == skip:
            continue
        d_min = r_self + hr[j] + p.discomfort
        if (x - hp[j, 0]) ** 2 + (y - hp[j, 1]) ** 2 < d_min * d_min:
            return False
        if (x - hg[j, 0]) ** 2 + (y - hg[j, 1]) ** 2 < d_min * d_min:
            return False
    return True


@nb.njit(cache=True)
def _spawn_human(i, n_check, rng, rp, rg, hp, hv, hg, hr, hvp, nd, p):
    """Generate human ``i`` (attributes, start on the circle, antipodal goal, zero velocity),
    rejection-sampled against the robot and humans ``0..n_check-1`` (itself included: a respawn
    is checked against the human it replaces, with that one's radius, as in CrowdNav++ while the
    old human is still in its list). With the quirk, the env's ORCA neighbour distance ``nd[0]``
    is redrawn first (CrowdNav++ ``Agent.__init__``)."""
    if p.nd_random:
        nd[0] = p.nd_lo + (p.nd_hi - p.nd_lo) * uniform(rng)
    if p.randomize:
        v_pref = p.vpref_lo + (p.vpref_hi - p.vpref_lo) * uniform(rng)
        radius = p.radius_lo + (p.radius_hi - p.radius_lo) * uniform(rng)
    else:
        v_pref, radius = p.human_vpref, p.human_radius
    for _ in range(_MAX_REJECTIONS):
        a = uniform(rng) * 2.0 * math.pi
        x = p.circle_radius * math.cos(a) + uniform(rng) * p.start_noise
        y = p.circle_radius * math.sin(a) + uniform(rng) * p.start_noise
        if _clear_of_agents(x, y, radius, -1, rp, rg, p, hp, hg, hr, n_check):
            break
    hvp[i], hr[i] = v_pref, radius
    hp[i, 0], hp[i, 1] = x, y
    hg[i, 0], hg[i, 1] = -x, -y
    hv[i, 0], hv[i, 1] = 0.0, 0.0


@nb.njit(cache=True)
def _change_goals(rng, rp, rg, hp, hg, hr, hvp, p):
    """Random goal change: each human, with probability ``goal_prob``, gets a new goal on the
    circle with centred noise ``(U - 0.5) * v_pref``, clear of the robot and the other humans."""
    n = p.n_humans
    for i in range(n):
        if uniform(rng) <= p.goal_prob:
            v_pref = hvp[i] if hvp[i] != 0.0 else 1.0
            for _ in range(_MAX_REJECTIONS):
                a = uniform(rng) * 2.0 * math.pi
                x = p.circle_radius * math.cos(a) + (uniform(rng) - 0.5) * v_pref
                y = p.circle_radius * math.sin(a) + (uniform(rng) - 0.5) * v_pref
                if _clear_of_agents(x, y, hr[i], i, rp, rg, p, hp, hg, hr, n):
                    break
            hg[i, 0], hg[i, 1] = x, y


# --------------------------------------------------------------------------------------------
# One environment: reset, observation, humans' ORCA, step.


class Scratch(NamedTuple):
    """Per-environment work arrays for the ORCA solver (sized for the robot's largest scene,
    A = (L + 1) N + 1 agents, and K obstacle vertices)."""

    lines: np.ndarray  # (K + A, 4)
    proj: np.ndarray  # (K + A, 4)
    nb_idx: np.ndarray  # (A,)
    nb_dist: np.ndarray
    ob_idx: np.ndarray  # (K,)
    ob_dist: np.ndarray
    radii: np.ndarray  # (A,) ORCA radii
    agents_pos: np.ndarray  # (A, 2) robot ORCA scene: the robot, then the agents it sees
    agents_vel: np.ndarray
    candidates: np.ndarray  # (A,) 1..A-1: the robot's candidate neighbours
    order: np.ndarray  # (N,) observation sort
    move_vel: np.ndarray  # (N, 2) the humans' move when they see the robot (robot_visible)


@nb.njit(cache=True)
def _make_scratch(n, n_pred, k):
    m = (n_pred + 1) * n + 1
    return Scratch(np.empty((k + m, 4)), np.empty((k + m, 4)), np.empty(m, np.int64),
                   np.empty(m), np.empty(max(k, 1), np.int64), np.empty(max(k, 1)), np.empty(m),
                   np.empty((m, 2)), np.empty((m, 2)), np.arange(1, m + 1), np.empty(n, np.int64),
                   np.empty((n, 2)))


@nb.njit(cache=True, inline="always")
def _pref_velocity(dx, dy):
    """Unit-speed preferred velocity toward the goal (not scaled by v_pref), slowing inside 1 m."""
    d = math.sqrt(dx * dx + dy * dy)
    if d > 1.0:
        return dx / d, dy / d
    return dx, dy


@nb.njit(cache=True)
def _human_sim_radii(i, hr, sim_r, sim_nd, p, neighbor_dist, radii):
    """Human ``i``'s padded ORCA radii of the others (into ``radii[:n]``) and its neighbour
    distance (returned): the live ones, or with persistent simulators those its simulator (row
    ``1 + i`` of ``sim_r``/``sim_nd``) was built with at its first call, building it now if it
    was created since (0 = not built)."""
    if p.persistent:
        if sim_nd[1 + i] == 0.0:
            sim_r[1 + i, :] = hr
            sim_nd[1 + i] = neighbor_dist
        held, nd_i = sim_r[1 + i], sim_nd[1 + i]
    else:
        held, nd_i = hr, neighbor_dist
    for j in range(p.n_humans):
        radii[j] = held[j] + p.orca_pad
    return nd_i


@nb.njit(cache=True)
def _humans_orca(hp, hv, hg, hr, hvp, sim_r, sim_nd, all_idx, p, neighbor_dist, no_obst, s, out):
    """New velocities of all humans: each solves ORCA as agent 0 among all other humans (the
    robot is invisible to them; no walls), with the radii and neighbour distance of
    :func:`_human_sim_radii`."""
    n = p.n_humans
    for i in range(n):
        nd_i = _human_sim_radii(i, hr, sim_r, sim_nd, p, neighbor_dist, s.radii)
        px_, py_ = _pref_velocity(hg[i, 0] - hp[i, 0], hg[i, 1] - hp[i, 1])
        out[i, 0], out[i, 1] = compute_new_velocity(
            i, hp, hv, s.radii, all_idx, n, hvp[i], px_, py_, nd_i, n,
            p.time_horizon, p.time_horizon_obst, p.dt, no_obst[0], no_obst[1], no_obst[2],
            no_obst[3], no_obst[4], s.lines, s.proj, s.nb_idx, s.nb_dist, s.ob_idx, s.ob_dist)


@nb.njit(cache=True)
def _humans_orca_robot(hp, hv, hg, hr, hvp, sim_r, sim_nd, all_idx, p, neighbor_dist, no_obst, s,
                       out, rpx, rpy, rvx, rvy):
    """As :func:`_humans_orca`, with the robot one more agent to every human (CrowdNav++
    ``robot.visible``): agent ``n`` of the scene, at its position with its current (last executed)
    velocity and ORCA radius ``robot_radius + pad``, a neighbour within the neighbour distance like
    any human. The humans' own radii are those their simulators hold, as without the robot."""
    n = p.n_humans
    for j in range(n):
        s.agents_pos[j, 0], s.agents_pos[j, 1] = hp[j, 0], hp[j, 1]
        s.agents_vel[j, 0], s.agents_vel[j, 1] = hv[j, 0], hv[j, 1]
    s.agents_pos[n, 0], s.agents_pos[n, 1] = rpx, rpy
    s.agents_vel[n, 0], s.agents_vel[n, 1] = rvx, rvy
    s.radii[n] = p.robot_radius + p.orca_pad
    for i in range(n):
        nd_i = _human_sim_radii(i, hr, sim_r, sim_nd, p, neighbor_dist, s.radii)
        px_, py_ = _pref_velocity(hg[i, 0] - hp[i, 0], hg[i, 1] - hp[i, 1])
        out[i, 0], out[i, 1] = compute_new_velocity(
            i, s.agents_pos, s.agents_vel, s.radii, all_idx, n + 1, hvp[i], px_, py_, nd_i, n,
            p.time_horizon, p.time_horizon_obst, p.dt, no_obst[0], no_obst[1], no_obst[2],
            no_obst[3], no_obst[4], s.lines, s.proj, s.nb_idx, s.nb_dist, s.ob_idx, s.ob_dist)


@nb.njit(cache=True, inline="always")
def _sf_push(ix, iy, px, py, r, ox, oy, o_r, p):
    """Add the social-force repulsion of the agent at ``(ox, oy)`` (radius ``o_r``) on the one at
    ``(px, py)`` (radius ``r``): ``A exp((r + o_r - d) / B)`` along the unit vector from the other
    to this one (CrowdNav++ ``SOCIAL_FORCE.predict``, same operation order). Coincident centres
    (CrowdNav++: 0 / 0 = NaN) push along +x."""
    dx, dy = px - ox, py - oy
    d = math.sqrt(dx * dx + dy * dy)
    mag = p.sf_a * math.exp((r + o_r - d) / p.sf_b)
    if d > 0.0:
        return ix + mag * (dx / d), iy + mag * (dy / d)
    return ix + mag, iy


@nb.njit(cache=True)
def _humans_social_force(hp, hv, hg, hr, hvp, p, robot, rpx, rpy, out):
    """New velocities of all humans by CrowdNav++'s social force: ``v' = v + (KI (v_des - v) +
    sum_j A exp((r + r_j - d_j) / B) e_j) dt``, clipped to norm v_pref, with ``v_des`` the unit
    vector to the goal times v_pref and the sum over every other human (their true states: a
    human sees every other one) and, with ``robot``, the robot (its radius, no ORCA pad). At the
    goal itself (CrowdNav++: NaN) the desired velocity is 0."""
    n = p.n_humans
    for i in range(n):
        vp = hvp[i]
        gx, gy = hg[i, 0] - hp[i, 0], hg[i, 1] - hp[i, 1]
        dist = math.sqrt(gx * gx + gy * gy)
        dvx, dvy = (gx / dist * vp, gy / dist * vp) if dist > 0.0 else (0.0, 0.0)
        ax, ay = p.sf_ki * (dvx - hv[i, 0]), p.sf_ki * (dvy - hv[i, 1])
        ix, iy = 0.0, 0.0
        for j in range(n):
            if j != i:
                ix, iy = _sf_push(ix, iy, hp[i, 0], hp[i, 1], hr[i], hp[j, 0], hp[j, 1], hr[j], p)
        if robot:
            ix, iy = _sf_push(ix, iy, hp[i, 0], hp[i, 1], hr[i], rpx, rpy, p.robot_radius, p)
        vx = hv[i, 0] + (ax + ix) * p.dt
        vy = hv[i, 1] + (ay + iy) * p.dt
        norm = math.sqrt(vx * vx + vy * vy)
        if norm > vp:
            vx, vy = vx / norm * vp, vy / norm * vp
        out[i, 0], out[i, 1] = vx, vy


@nb.njit(cache=True)
def _humans_act(hp, hv, hg, hr, hvp, sim_r, sim_nd, all_idx, p, neighbor_dist, no_obst, s, out,
                robot, rpx, rpy, rvx, rvy):
    """New velocities of all humans under the crowd model (``human_policy``); with ``robot``, the
    robot at ``rp`` with velocity ``rv`` is one more agent to them (the roll-out passes False)."""
    if p.human_policy == HUMANS_SOCIAL_FORCE:
        _humans_social_force(hp, hv, hg, hr, hvp, p, robot, rpx, rpy, out)
    elif robot:
        _humans_orca_robot(hp, hv, hg, hr, hvp, sim_r, sim_nd, all_idx, p, neighbor_dist, no_obst,
                           s, out, rpx, rpy, rvx, rvy)
    else:
        _humans_orca(hp, hv, hg, hr, hvp, sim_r, sim_nd, all_idx, p, neighbor_dist, no_obst, s, out)


@nb.njit(cache=True)
def _roll_out(b, depth, p, no_obst, all_idx, hp, hv, hg, hr, hvp, nd, sim_r, sim_nd, fut_pos,
              fut_vel, rollout_depth, s):
    """Extend env ``b``'s roll-out of the humans to ``depth`` steps: k = 0 is the current state,
    each further step is every human's velocity (their policy) from the previous one and the move
    by it (robot invisible, goals fixed, no respawns). Step 1 is the humans' actual next move
    unless they see the robot (``robot_visible``: CrowdNav++'s roll-out leaves it out even then)."""
    done = rollout_depth[b]
    if done >= depth:
        return
    if done == 0:
        fut_pos[b, 0] = hp[b]
        fut_vel[b, 0] = hv[b]
    for k in range(done + 1, depth + 1):
        _humans_act(fut_pos[b, k - 1], fut_vel[b, k - 1], hg[b], hr[b], hvp[b], sim_r[b], sim_nd[b],
                    all_idx, p, nd[b], no_obst, s, fut_vel[b, k], False, 0.0, 0.0, 0.0, 0.0)
        for i in range(p.n_humans):
            fut_pos[b, k, i, 0] = fut_pos[b, k - 1, i, 0] + fut_vel[b, k, i, 0] * p.dt
            fut_pos[b, k, i, 1] = fut_pos[b, k - 1, i, 1] + fut_vel[b, k, i, 1] * p.dt
    rollout_depth[b] = depth


@nb.njit(cache=True)
def _observe(b, p, rp, rv, rg, hp, hv, hr, seen_pos, seen_vel, seen_r, pred, visible, obs, s):
    """Write observation ``obs[b]`` from the current state and update the robot's memory.

    Layout (269 floats for N = 20, L = 5): robot ``px, py, radius, gx, gy, v_pref, theta``;
    robot ``vx, vy``; N rows of ``(x_k, y_k) for k = 0..L`` relative to the robot (current and
    constant-velocity predicted positions, velocity as last observed, one step stale), visible
    rows first sorted by distance, the others filled with the sentinel; N mask values. Memory
    (CrowdNav++ ``update_last_human_states``): a visible human's state is stored, an invisible
    one's is extrapolated one step at its remembered velocity ("Plan A").
    """
    n, L = p.n_humans, p.n_pred
    o = obs[b]
    rx, ry = rp[b, 0], rp[b, 1]
    o[0], o[1], o[2] = rx, ry, p.robot_radius
    o[3], o[4], o[5], o[6] = rg[b, 0], rg[b, 1], p.robot_vpref, ROBOT_THETA
    o[7], o[8] = rv[b, 0], rv[b, 1]
    n_vis = 0
    for i in range(n):
        dx, dy = hp[b, i, 0] - rx, hp[b, i, 1] - ry
        dist = math.sqrt(dx * dx + dy * dy)
        vis = dist - p.robot_radius - hr[b, i] <= p.sensing
        visible[b, i] = vis
        for k in range(L + 1):
            # Prediction with the velocity last observed (before this observation's update).
            pred[b, i, k, 0] = hp[b, i, 0] + k * p.dt * seen_vel[b, i, 0]
            pred[b, i, k, 1] = hp[b, i, 1] + k * p.dt * seen_vel[b, i, 1]
        if vis:
            # Visible humans sorted by distance (stable: ties keep index order).
            insert_sorted(s.nb_dist, s.order, n_vis, dist, i)
            n_vis += 1
    for i in range(n):
        if visible[b, i]:
            seen_pos[b, i, 0], seen_pos[b, i, 1] = hp[b, i, 0], hp[b, i, 1]
            seen_vel[b, i, 0], seen_vel[b, i, 1] = hv[b, i, 0], hv[b, i, 1]
            seen_r[b, i] = hr[b, i]
        else:
            seen_pos[b, i, 0] += seen_vel[b, i, 0] * p.dt
            seen_pos[b, i, 1] += seen_vel[b, i, 1] * p.dt
    row_len = 2 * (L + 1)
    base = SELF_DIM
    mask_base = base + n * row_len
    for q in range(n):
        off = base + q * row_len
        if q < n_vis:
            i = s.order[q]
            for k in range(L + 1):
                o[off + 2 * k] = pred[b, i, k, 0] - rx
                o[off + 2 * k + 1] = pred[b, i, k, 1] - ry
            o[mask_base + q] = 1.0
        else:
            for c in range(row_len):
                o[off + c] = p.sentinel
            o[mask_base + q] = 0.0


@nb.njit(cache=True)
def _reset_one(b, seed, p, rng, step_count, potential, rp, rv, rg, hp, hv, hg, hr, hvp, seen_pos,
               seen_vel, seen_r, pred, visible, nd, sim_r, sim_nd, fut_pos, fut_vel, rollout_depth,
               obs, s):
    """Start episode ``seed`` in slot ``b``. With persistent ORCA simulators (CrowdNav++ keeps the
    robot's across episodes), the robot's was built in another episode: it holds the radii (its
    memory then: true if visible, 0.3 if not) and the neighbour distance of the first observation
    of episode ``seed + 1``, and each human's is built at its first call (0 = not built yet)."""
    state = (rng, step_count, potential, rp, rv, rg, hp, hv, hg, hr, hvp, seen_pos, seen_vel, seen_r,
             pred, visible, nd, rollout_depth, obs, s)
    if p.persistent:
        _start_episode(b, seed + 1, p, *state)
        sim_r[b, 0] = seen_r[b]
        sim_nd[b, 0] = nd[b]
    _start_episode(b, seed, p, *state)
    sim_nd[b, 1:] = 0.0


@nb.njit(cache=True)
def _start_episode(b, seed, p, rng, step_count, potential, rp, rv, rg, hp, hv, hg, hr, hvp, seen_pos,
                   seen_vel, seen_r, pred, visible, nd, rollout_depth, obs, s):
    r = rng[b]
    seed_rng(r, seed)
    a = p.arena - p.spawn_margin
    for _ in range(_MAX_REJECTIONS):
        px = -a + 2 * a * uniform(r)
        py = -a + 2 * a * uniform(r)
        gx = -a + 2 * a * uniform(r)
        gy = -a + 2 * a * uniform(r)
        if (px - gx) ** 2 + (py - gy) ** 2 >= p.min_start_goal ** 2:
            break
    rp[b, 0], rp[b, 1], rg[b, 0], rg[b, 1] = px, py, gx, gy
    rv[b, 0], rv[b, 1] = 0.0, 0.0
    nd[b] = p.neighbor_dist
    for i in range(p.n_humans):
        _spawn_human(i, i, r, rp[b], rg[b], hp[b], hv[b], hg[b], hr[b], hvp[b], nd[b:b + 1], p)
    step_count[b] = 0
    potential[b] = -math.sqrt((px - gx) ** 2 + (py - gy) ** 2)
    seen_pos[b, :, :] = DUMMY_POS
    seen_vel[b, :, :] = 0.0
    seen_r[b, :] = DUMMY_RADIUS
    rollout_depth[b] = 0
    _observe(b, p, rp, rv, rg, hp, hv, hr, seen_pos, seen_vel, seen_r, pred, visible, obs, s)


@nb.njit(cache=True)
def _step_one(b, action, p, no_obst, all_idx, rng, step_count, potential, rp, rv, rg, hp, hv, hg,
              hr, hvp, seen_pos, seen_vel, seen_r, pred, visible, nd, sim_r, sim_nd, fut_pos,
              fut_vel, rollout_depth, obs, out_reward, out_pred, out_event, out_dmin, out_intrusion,
              out_intr_dist, out_distance, out_oob, s):
    n, L, dt = p.n_humans, p.n_pred, p.dt
    # (1) Robot action, clipped by norm to v_pref; humans' velocities from current states (step 1
    # of the roll-out; all L steps when the intrusion test needs the true futures). Humans that see
    # the robot move by their own solve with it (its pre-move position and last velocity, as
    # CrowdNav++'s get_human_actions), apart from the robot-blind roll-out.
    ax, ay = action[0], action[1]
    speed = math.sqrt(ax * ax + ay * ay)
    if speed > p.robot_vpref:
        ax, ay = ax * (p.robot_vpref / speed), ay * (p.robot_vpref / speed)
    if p.robot_visible:
        if p.intrusion:
            _roll_out(b, L, p, no_obst, all_idx, hp, hv, hg, hr, hvp, nd, sim_r, sim_nd, fut_pos,
                      fut_vel, rollout_depth, s)
        _humans_act(hp[b], hv[b], hg[b], hr[b], hvp[b], sim_r[b], sim_nd[b], all_idx, p, nd[b],
                    no_obst, s, s.move_vel, True, rp[b, 0], rp[b, 1], rv[b, 0], rv[b, 1])
    else:
        _roll_out(b, L if p.intrusion else 1, p, no_obst, all_idx, hp, hv, hg, hr, hvp, nd, sim_r,
                  sim_nd, fut_pos, fut_vel, rollout_depth, s)

    # (2) Reward and termination on the pre-move positions.
    rx, ry = rp[b, 0], rp[b, 1]
    t = step_count[b] * dt
    dmin = math.inf
    collided = False
    for i in range(n):
        d = math.sqrt((hp[b, i, 0] - rx) ** 2 + (hp[b, i, 1] - ry) ** 2) - hr[b, i] - p.robot_radius
        if d < 0.0:
            collided = True
        if d < dmin:
            dmin = d
    wall = p.bounded and (abs(rx) + p.robot_radius >= p.arena or abs(ry) + p.robot_radius >= p.arena)
    goal_dist = math.sqrt((rx - rg[b, 0]) ** 2 + (ry - rg[b, 1]) ** 2)
    event = RUNNING
    if t >= p.time_limit - 1.0:
        reward, event = 0.0, TIMEOUT
    elif collided:
        reward, event = p.collision_penalty, HUMAN_COLLISION
    elif wall:
        reward, event = p.collision_penalty, WALL_COLLISION
    elif goal_dist < p.robot_radius:
        reward, event = p.success_reward, SUCCESS
    elif dmin < p.discomfort:
        reward = (dmin - p.discomfort) * p.discomfort_factor * dt
    else:
        reward = p.potential_factor * (-goal_dist - potential[b])
        potential[b] = -goal_dist
    # Prediction penalty: worst k over visible humans' predicted positions in the observation.
    worst = 0.0
    thresh_sq = (p.robot_radius + p.pred_radius) ** 2
    for i in range(n):
        if visible[b, i]:
            for k in range(1, L + 1):
                if (pred[b, i, k, 0] - rx) ** 2 + (pred[b, i, k, 1] - ry) ** 2 < thresh_sq:
                    worst = min(worst, p.collision_penalty / 2.0 ** (k + 1))
                    break  # smaller k is worse; later k cannot beat it for this human
    out_reward[b] = reward + worst
    out_pred[b] = worst  # also apart: CrowdNav++'s training log reports returns without it
    out_event[b] = event
    out_dmin[b] = dmin
    out_oob[b] = abs(rx) > p.arena or abs(ry) > p.arena

    # Intrusion: robot within r + 0.3 of a currently visible human's TRUE position k = 1..L steps
    # ahead (the roll-out). Not on the step that ends the episode: CrowdNav++ reports an intrusion
    # (its `Danger` info) only in the branch after timeout, collision and goal, so its ITR never
    # counts that step (its denominator does).
    out_intrusion[b] = False
    out_intr_dist[b] = math.inf
    if p.intrusion and event == RUNNING:
        for i in range(n):
            d_now = math.sqrt((hp[b, i, 0] - rx) ** 2 + (hp[b, i, 1] - ry) ** 2)
            if d_now - p.robot_radius - hr[b, i] <= p.sensing:
                for k in range(1, L + 1):
                    c = math.sqrt((fut_pos[b, k, i, 0] - rx) ** 2 + (fut_pos[b, k, i, 1] - ry) ** 2)
                    if c < out_intr_dist[b]:
                        out_intr_dist[b] = c
        out_intrusion[b] = out_intr_dist[b] < p.robot_radius + p.pred_radius

    # (3) Move everyone (humans by roll-out step 1, or by their solve with the robot); (4) observe.
    rp[b, 0] = rx + ax * dt
    rp[b, 1] = ry + ay * dt
    rv[b, 0], rv[b, 1] = ax, ay
    out_distance[b] = 0.0 if event != RUNNING else math.sqrt(ax * ax + ay * ay) * dt
    if p.robot_visible:
        for i in range(n):
            hv[b, i, 0], hv[b, i, 1] = s.move_vel[i, 0], s.move_vel[i, 1]
            hp[b, i, 0] = hp[b, i, 0] + s.move_vel[i, 0] * dt
            hp[b, i, 1] = hp[b, i, 1] + s.move_vel[i, 1] * dt
    else:
        for i in range(n):
            hv[b, i, 0], hv[b, i, 1] = fut_vel[b, 1, i, 0], fut_vel[b, 1, i, 1]
            hp[b, i, 0], hp[b, i, 1] = fut_pos[b, 1, i, 0], fut_pos[b, 1, i, 1]
    rollout_depth[b] = 0
    step_count[b] += 1
    _observe(b, p, rp, rv, rg, hp, hv, hr, seen_pos, seen_vel, seen_r, pred, visible, obs, s)

    # (5) Random goal changes when due, then respawn of humans that reached their goal.
    r = rng[b]
    if p.goal_prob > 0.0 and step_count[b] % p.goal_every == 0:  # 0: goal changes off
        _change_goals(r, rp[b], rg[b], hp[b], hg[b], hr[b], hvp[b], p)
    for i in range(n):
        if (hg[b, i, 0] - hp[b, i, 0]) ** 2 + (hg[b, i, 1] - hp[b, i, 1]) ** 2 < hr[b, i] ** 2:
            _spawn_human(i, n, r, rp[b], rg[b], hp[b], hv[b], hg[b], hr[b], hvp[b], nd[b:b + 1], p)
            sim_nd[b, 1 + i] = 0.0  # a new human, a new simulator


@nb.njit(cache=True)
def _orca_robot_one(b, p, robot_obst, no_obst, all_idx, rp, rv, rg, hp, hv, hg, hr, hvp, seen_pos,
                    seen_vel, seen_r, visible, nd, sim_r, sim_nd, fut_pos, fut_vel, rollout_depth,
                    s, out):
    """The ORCA robot's velocity: agent 0, max speed v_pref, preferred velocity toward its goal,
    every agent it sees a neighbour candidate (CrowdNav++ ``ORCA.predict``).

    ``LOOK_AHEAD`` (CrowdSimPred): agent ``1 + k N + i`` is human ``i`` at roll-out step
    ``k = 0..L`` if it was visible at the last observation, else a dummy. ``CURRENT_STATE``
    (CrowdSimVarNum): agent ``1 + i`` is the memory of human ``i``. Radii are the remembered ones
    plus the ORCA pad; walls only if ``robot_obst`` holds them (wall-aware robot)."""
    n, L = p.n_humans, p.n_pred
    if p.orca_robot == LOOK_AHEAD:  # first: the roll-out uses the same scratch
        _roll_out(b, L, p, no_obst, all_idx, hp, hv, hg, hr, hvp, nd, sim_r, sim_nd, fut_pos,
                  fut_vel, rollout_depth, s)
    if p.persistent:
        held, nd_r = sim_r[b, 0], sim_nd[b, 0]
    else:
        held, nd_r = seen_r[b], nd[b]
    s.agents_pos[0, 0], s.agents_pos[0, 1] = rp[b, 0], rp[b, 1]
    s.agents_vel[0, 0], s.agents_vel[0, 1] = rv[b, 0], rv[b, 1]
    s.radii[0] = p.robot_radius + p.orca_pad
    if p.orca_robot == LOOK_AHEAD:
        n_agents = (L + 1) * n
        for k in range(L + 1):
            for i in range(n):
                a = 1 + k * n + i
                if visible[b, i]:
                    s.agents_pos[a, 0], s.agents_pos[a, 1] = fut_pos[b, k, i, 0], fut_pos[b, k, i, 1]
                    s.agents_vel[a, 0], s.agents_vel[a, 1] = fut_vel[b, k, i, 0], fut_vel[b, k, i, 1]
                else:
                    s.agents_pos[a, 0], s.agents_pos[a, 1] = DUMMY_POS, DUMMY_POS
                    s.agents_vel[a, 0], s.agents_vel[a, 1] = 0.0, 0.0
                s.radii[a] = held[i] + p.orca_pad
    else:
        n_agents = n
        for i in range(n):
            s.agents_pos[i + 1, 0], s.agents_pos[i + 1, 1] = seen_pos[b, i, 0], seen_pos[b, i, 1]
            s.agents_vel[i + 1, 0], s.agents_vel[i + 1, 1] = seen_vel[b, i, 0], seen_vel[b, i, 1]
            s.radii[i + 1] = held[i] + p.orca_pad
    px_, py_ = _pref_velocity(rg[b, 0] - rp[b, 0], rg[b, 1] - rp[b, 1])
    out[b, 0], out[b, 1] = compute_new_velocity(
        0, s.agents_pos, s.agents_vel, s.radii, s.candidates, n_agents, p.robot_vpref, px_, py_,
        nd_r, n_agents, p.time_horizon, p.time_horizon_obst, p.dt, robot_obst[0], robot_obst[1],
        robot_obst[2], robot_obst[3], robot_obst[4], s.lines, s.proj, s.nb_idx, s.nb_dist,
        s.ob_idx, s.ob_dist)


# --------------------------------------------------------------------------------------------
# Batched entry points: one parallel loop over environments for steps. Small batches skip the
# thread pool and call the per-environment kernels from Python (see CrowdSim).


@nb.njit(cache=True)
def reset_many(idx, seeds, p, rng, step_count, potential, rp, rv, rg, hp, hv, hg, hr, hvp, seen_pos,
               seen_vel, seen_r, pred, visible, nd, sim_r, sim_nd, fut_pos, fut_vel, rollout_depth,
               obs):
    # Serial: a reset costs a few microseconds, less than waking the thread pool for the handful
    # of slots an autoreset touches.
    s = _make_scratch(p.n_humans, p.n_pred, 0)
    for q in range(idx.shape[0]):
        _reset_one(idx[q], seeds[q], p, rng, step_count, potential, rp, rv, rg, hp, hv, hg, hr, hvp,
                   seen_pos, seen_vel, seen_r, pred, visible, nd, sim_r, sim_nd, fut_pos, fut_vel,
                   rollout_depth, obs, s)


@nb.njit(cache=True, parallel=True)
def step_many(n_chunks, actions, p, no_obst, all_idx, rng, step_count, potential, rp, rv, rg, hp,
              hv, hg, hr, hvp, seen_pos, seen_vel, seen_r, pred, visible, nd, sim_r, sim_nd,
              fut_pos, fut_vel, rollout_depth, obs, out_reward, out_pred, out_event, out_dmin,
              out_intrusion, out_intr_dist, out_distance, out_oob):
    n_env = actions.shape[0]
    for c in nb.prange(n_chunks):
        s = _make_scratch(p.n_humans, p.n_pred, 0)
        for b in range(c * n_env // n_chunks, (c + 1) * n_env // n_chunks):
            _step_one(b, actions[b], p, no_obst, all_idx, rng, step_count, potential, rp, rv, rg,
                      hp, hv, hg, hr, hvp, seen_pos, seen_vel, seen_r, pred, visible, nd, sim_r,
                      sim_nd, fut_pos, fut_vel, rollout_depth, obs, out_reward, out_pred, out_event,
                      out_dmin, out_intrusion, out_intr_dist, out_distance, out_oob, s)


@nb.njit(cache=True, parallel=True)
def orca_robot_many(n_chunks, p, robot_obst, no_obst, all_idx, rp, rv, rg, hp, hv, hg, hr, hvp,
                    seen_pos, seen_vel, seen_r, visible, nd, sim_r, sim_nd, fut_pos, fut_vel,
                    rollout_depth, out):
    n_env = rp.shape[0]
    for c in nb.prange(n_chunks):
        s = _make_scratch(p.n_humans, p.n_pred, robot_obst[0].shape[0])
        for b in range(c * n_env // n_chunks, (c + 1) * n_env // n_chunks):
            _orca_robot_one(b, p, robot_obst, no_obst, all_idx, rp, rv, rg, hp, hv, hg, hr, hvp,
                            seen_pos, seen_vel, seen_r, visible, nd, sim_r, sim_nd, fut_pos,
                            fut_vel, rollout_depth, s, out)


PARALLEL_MIN_BATCH = 16  # below this, a Python loop over the per-env kernels is faster


class StepResult(NamedTuple):
    """Per-environment outputs of one step (arrays of length B)."""

    reward: np.ndarray  # float64, the prediction penalty included
    prediction_penalty: np.ndarray  # its prediction-penalty part (<= 0); CrowdNav++'s training log
    # leaves it out of the episode returns it reports (added outside its envs' episode monitor)
    event: np.ndarray  # int64, see EVENT_NAMES; RUNNING while the episode goes on
    min_distance: np.ndarray  # closest human surface distance before the move (m)
    intrusion: np.ndarray  # bool: robot inside r + 0.3 of a visible human's true future position;
    # False on the step that ends the episode (as CrowdNav++'s ITR)
    intrusion_distance: np.ndarray  # closest such centre distance over k = 1..L (m); inf if no
    # visible human, on the final step, or with compute_intrusion off
    distance: np.ndarray  # robot path length added by this step (m), 0 on the final step
    out_of_bounds: np.ndarray  # bool: robot centre outside the workspace before the move


class CrowdSim:
    """B crowd-navigation environments as arrays. The engine under the gymnasium envs.

    ``reset(seeds, idx)`` starts episodes ``seeds`` in slots ``idx``; ``step(actions)`` advances
    every slot one step (a slot whose episode ended keeps stepping until reset: the caller owns
    episode boundaries). ``obs`` is the ``(B, obs_dim)`` float32 observation.
    """

    def __init__(self, config: CrowdSimConfig, num_envs: int = 1):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.config = config.resolve()
        self.params = make_params(self.config)
        self.num_envs = B = num_envs
        n, L = self.config.num_humans, self.config.prediction_steps
        walls = self.config.bounded and self.config.orca_robot_wall_aware
        self.robot_obstacles = make_obstacles([bounding_box(self.config.arena_size)] if walls else [])
        self._no_obstacles = make_obstacles([])  # humans ignore walls
        self._all_idx = np.arange(n + 1, dtype=np.int64)  # the humans, then the robot (robot_visible)
        self.rng = np.zeros((B, 4), np.uint64)
        self.step_count = np.zeros(B, np.int64)
        self.potential = np.zeros(B)
        self.robot_pos, self.robot_vel, self.robot_goal = (np.zeros((B, 2)) for _ in range(3))
        self.human_pos, self.human_vel, self.human_goal = (np.zeros((B, n, 2)) for _ in range(3))
        self.human_radius, self.human_vpref = np.zeros((B, n)), np.zeros((B, n))
        self.seen_pos, self.seen_vel = np.zeros((B, n, 2)), np.zeros((B, n, 2))
        self.seen_radius = np.zeros((B, n))
        self.pred = np.zeros((B, n, L + 1, 2))
        self.visible = np.zeros((B, n), np.bool_)
        self.neighbor_dist = np.zeros(B)
        self.sim_radius, self.sim_neighbor_dist = np.zeros((B, n + 1, n)), np.zeros((B, n + 1))
        self.future_pos, self.future_vel = np.zeros((B, L + 1, n, 2)), np.zeros((B, L + 1, n, 2))
        self.rollout_depth = np.zeros(B, np.int64)
        self.obs = np.zeros((B, self.config.obs_dim), np.float32)
        self.seeds = np.full(B, -1, np.int64)
        self._parallel = B >= PARALLEL_MIN_BATCH
        self._scratch = _make_scratch(n, L, self.robot_obstacles[0].shape[0])

    # The state arrays, in the order the kernels take them.
    STATE_FIELDS = ("rng", "step_count", "potential", "robot_pos", "robot_vel", "robot_goal",
                    "human_pos", "human_vel", "human_goal", "human_radius", "human_vpref",
                    "seen_pos", "seen_vel", "seen_radius", "pred", "visible", "neighbor_dist",
                    "sim_radius", "sim_neighbor_dist", "future_pos", "future_vel", "rollout_depth",
                    "obs")

    def _state(self):
        return tuple(getattr(self, name) for name in self.STATE_FIELDS)

    def state_dict(self) -> dict[str, np.ndarray]:
        """Copies of every state array (and the episode seeds): with :meth:`load_state_dict`, a
        paused batch continues bitwise identically (resumable training)."""
        return {name: getattr(self, name).copy() for name in (*self.STATE_FIELDS, "seeds")}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """States saved before the persistent ORCA simulators lack ``sim_radius`` and
        ``sim_neighbor_dist``; they load where nothing reads them (``persistent_orca_sims`` off)."""
        for name in (*self.STATE_FIELDS, "seeds"):
            current = getattr(self, name)
            if name.startswith("sim_") and name not in state and not self.params.persistent:
                current[...] = 0.0
                continue
            value = np.asarray(state[name])
            if value.shape != current.shape or value.dtype != current.dtype:
                raise ValueError(f"simulator state {name!r}: got {value.dtype}{value.shape}, "
                                 f"expected {current.dtype}{current.shape}")
            current[...] = value

    def reset(self, seeds, idx=None) -> np.ndarray:
        """Start episode ``seeds[q]`` in slot ``idx[q]`` (all slots when ``idx`` is None)."""
        idx = np.arange(self.num_envs) if idx is None else np.asarray(idx, np.int64).reshape(-1)
        seeds = np.asarray(seeds, np.int64).reshape(-1)
        if seeds.shape != idx.shape:
            raise ValueError(f"need one seed per reset slot: {seeds.shape[0]} seeds, {idx.shape[0]} slots")
        if np.any(seeds < 0):
            raise ValueError("episode seeds must be non-negative")
        if np.any((idx < 0) | (idx >= self.num_envs)):
            raise ValueError(f"slot index out of range [0, {self.num_envs})")
        self.seeds[idx] = seeds
        reset_many(idx, seeds, self.params, *self._state())
        return self.obs

    def observe(self) -> np.ndarray:
        """Rebuild every slot's observation from the current state, as at the end of a step (the
        robot's memory of the humans is updated too, and the humans' roll-out is recomputed when
        next needed). For hand-built states."""
        self.rollout_depth[:] = 0
        for b in range(self.num_envs):
            _observe(b, self.params, self.robot_pos, self.robot_vel, self.robot_goal, self.human_pos,
                     self.human_vel, self.human_radius, self.seen_pos, self.seen_vel,
                     self.seen_radius, self.pred, self.visible, self.obs, self._scratch)
        return self.obs

    def check_actions(self, actions) -> np.ndarray:
        """Validate ``(B, 2)`` world-frame velocities (m/s); non-finite values are an error."""
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.num_envs, 2):
            raise ValueError(f"actions must have shape ({self.num_envs}, 2) (vx, vy in m/s), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
            raise ValueError(f"non-finite action (NaN or inf) in env slot(s) {bad.tolist()}")
        return np.ascontiguousarray(a)

    def step(self, actions) -> StepResult:
        a = self.check_actions(actions)
        B = self.num_envs
        res = StepResult(np.empty(B), np.empty(B), np.empty(B, np.int64), np.empty(B),
                         np.empty(B, np.bool_), np.empty(B), np.empty(B), np.empty(B, np.bool_))
        outs = (res.reward, res.prediction_penalty, res.event, res.min_distance, res.intrusion,
                res.intrusion_distance, res.distance, res.out_of_bounds)
        if self._parallel:
            step_many(self._n_chunks(), a, self.params, self._no_obstacles, self._all_idx,
                      *self._state(), *outs)
        else:
            for b in range(B):
                _step_one(b, a[b], self.params, self._no_obstacles, self._all_idx, *self._state(),
                          *outs, self._scratch)
        return res

    def orca_actions(self) -> np.ndarray:
        """The ORCA robot's velocities ``(B, 2)`` for the current observations (``config.orca_robot``
        picks which of CrowdNav++'s two; the look-ahead robot's roll-out is reused by ``step``)."""
        out = np.empty((self.num_envs, 2))
        args = (self.params, self.robot_obstacles, self._no_obstacles, self._all_idx,
                self.robot_pos, self.robot_vel, self.robot_goal, self.human_pos, self.human_vel,
                self.human_goal, self.human_radius, self.human_vpref, self.seen_pos, self.seen_vel,
                self.seen_radius, self.visible, self.neighbor_dist, self.sim_radius,
                self.sim_neighbor_dist, self.future_pos,
                self.future_vel, self.rollout_depth)
        if self._parallel:
            orca_robot_many(self._n_chunks(), *args, out)
        else:
            for b in range(self.num_envs):
                _orca_robot_one(b, *args, self._scratch, out)
        return out

    def _n_chunks(self) -> int:
        """Contiguous env chunks for the parallel kernels: a few per thread for load balance, each
        with one scratch allocation (not one per env)."""
        return min(self.num_envs, 4 * nb.get_num_threads())

    def clip_actions(self, actions: np.ndarray) -> np.ndarray:
        """What ``step`` executes: each velocity scaled down to norm v_pref if faster."""
        speed = np.linalg.norm(actions, axis=-1, keepdims=True)
        vmax = self.config.robot_v_pref
        return np.where(speed > vmax, actions * (vmax / np.maximum(speed, 1e-300)), actions)

    def straight_actions(self) -> np.ndarray:
        """Full speed toward the goal, ignoring humans (a floor for learned policies)."""
        d = self.robot_goal - self.robot_pos
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        return d / np.maximum(norm, 1e-12) * self.config.robot_v_pref
