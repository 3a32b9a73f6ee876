"""Metrics on hand-built episode records, the intrusion test on a hand-built state, and the evaluation loop's records."""

import json
import math
import warnings

import numpy as np
import pytest

from lerobot_crowdnav.measure.episodes import json_safe, run_episodes
from lerobot_crowdnav.measure.metrics import EpisodeRecord, compute_metrics, markdown_header, markdown_row
from lerobot_crowdnav.sim.config import CrowdSimConfig, split_seeds
from lerobot_crowdnav.sim.engine import CrowdSim
from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv


def rec(seed, event, steps, path, intr=0, intr_sum=0.0, oob=False):
    return EpisodeRecord(seed, event, steps, path, intr, intr_sum, oob, 0.0)


def test_metrics_on_hand_built_records():
    records = [
        rec(0, "success", 40, 10.0, intr=4, intr_sum=1.6, oob=True),
        rec(1, "success", 60, 14.0),
        rec(2, "human_collision", 20, 5.0, intr=10, intr_sum=3.0),
        rec(3, "wall_collision", 1, 0.0),
        rec(4, "timeout", 197, 30.0, intr=0),
    ]
    m = compute_metrics(records, dt=0.25)
    assert m["sr"] == 0.4 and m["cr"] == 0.4 and m["tr"] == 0.2
    assert m["cr_human"] == 0.2 and m["cr_wall"] == 0.2
    assert m["nt"] == pytest.approx((39 + 59) / 2 * 0.25)  # the goal is found before the last move
    assert m["pl"] == pytest.approx((10 + 14 + 5 + 0 + 30) / 5)
    assert m["itr"] == pytest.approx((4 / 40 + 0 + 10 / 20 + 0 + 0) / 5)
    assert m["sd"] == pytest.approx((1.6 + 3.0) / 14)
    assert m["oob"] == 0.5  # one of the two successes left the workspace
    row = markdown_row(m, bounded=False)
    assert row == "| 40.0 | 12.25 | 11.80 | 12.00 | 0.33 | 40.0 | 20.0 | 50.0 |"
    assert markdown_header(bounded=True).splitlines() == [
        "| SR (%) | NT (s) | PL (m) | ITR (%) | SD (m) |", "|---|---|---|---|---|"]


def test_metrics_without_success_or_intrusion_are_nan_not_errors():
    m = compute_metrics([rec(0, "timeout", 197, 3.0)], dt=0.25)
    assert math.isnan(m["nt"]) and math.isnan(m["sd"]) and math.isnan(m["oob"])
    assert "n/a" in markdown_row(m, bounded=True)
    with pytest.raises(ValueError):
        compute_metrics([], dt=0.25)


def test_markdown_row_reads_a_saved_metrics_file():
    """metrics.json saves an undefined mean as null: the baselines reuse a saved row without
    success (OOB, NT) or intrusion (SD) and write its table line from it."""
    m = json.loads(json.dumps(json_safe(compute_metrics([rec(0, "wall_collision", 1, 0.0)], dt=0.25))))
    assert m["oob"] is None and m["nt"] is None and m["sd"] is None
    for bounded in (True, False):
        assert markdown_row(m, bounded) == markdown_row(compute_metrics([rec(0, "wall_collision", 1, 0.0)], 0.25), bounded)
    assert markdown_row(m, bounded=False) == "| 0.0 | n/a | 0.00 | 0.00 | n/a | 100.0 | 0.0 | n/a |"


def parked(cfg):
    sim = CrowdSim(cfg, 1)
    sim.reset([9])
    n = sim.config.num_humans
    sim.human_pos[0] = 1000.0 + 3.0 * np.arange(2 * n).reshape(n, 2)
    sim.human_goal[0] = sim.human_pos[0] + 1000.0
    sim.human_vel[0] = 0.0
    sim.robot_pos[0] = [0.0, 0.0]
    sim.robot_goal[0] = [0.0, 5.0]
    sim.potential[0] = -5.0
    return sim


@pytest.mark.parametrize("start, intrudes, closest", [(1.5, True, 0.25), (1.8, False, 0.55)])
def test_intrusion_uses_true_future_positions(start, intrudes, closest):
    sim = parked(CrowdSimConfig(task="CrowdNav-v0"))
    # A human at rest walking toward the robot (which it does not see) at 1 m/s: its true
    # positions k steps ahead are start - 0.25 k.
    sim.human_pos[0, 0] = [start, 0.0]
    sim.human_goal[0, 0] = [-20.0, 0.0]
    sim.human_vpref[0, 0] = 1.0
    sim.observe()
    res = sim.step(np.zeros((1, 2)))
    assert bool(res.intrusion[0]) is intrudes
    assert res.intrusion_distance[0] == pytest.approx(closest)
    # The observation's constant-velocity prediction saw the human at rest: no prediction penalty.
    assert res.reward[0] == pytest.approx(0.0)


def test_intrusion_ignores_humans_out_of_sensing_range_and_can_be_off():
    cfg = CrowdSimConfig(task="CrowdNav-v0", sensing_range=1.0)
    sim = parked(cfg)
    sim.human_pos[0, 0] = [1.6, 0.0]  # surface distance 1.6 - 0.2 - 0.3 > 1.0: invisible, yet
    sim.human_radius[0, 0] = 0.3  # its true position 5 steps ahead (0.35 m) would intrude
    sim.human_vpref[0, 0] = 1.0
    sim.human_goal[0, 0] = [-20.0, 0.0]
    sim.observe()
    res = sim.step(np.zeros((1, 2)))
    assert not res.intrusion[0] and math.isinf(res.intrusion_distance[0])
    sim = parked(CrowdSimConfig(task="CrowdNav-v0", compute_intrusion=False))
    sim.human_pos[0, 0] = [1.5, 0.0]
    sim.human_goal[0, 0] = [-20.0, 0.0]
    res = sim.step(np.zeros((1, 2)))
    assert not res.intrusion[0]


@pytest.mark.parametrize("task, robot_at, goal_at, event", [
    ("CrowdNav-v0", [0.0, 0.0], [0.0, 0.05], "success"),
    ("BoundedCrowdNav-v0", [0.0, 5.9], [0.0, 0.0], "wall_collision"),
])
def test_the_step_that_ends_the_episode_is_never_an_intrusion(task, robot_at, goal_at, event):
    """CrowdNav++ reports an intrusion only on steps the episode goes on from: the human walking
    at the robot intrudes as in the test above, yet the step that ends the episode does not count
    (ITR's denominator still counts it)."""
    from lerobot_crowdnav.sim.engine import EVENT_NAMES
    sim = parked(CrowdSimConfig(task=task))
    sim.robot_pos[0], sim.robot_goal[0] = robot_at, goal_at
    sim.human_pos[0, 0] = [robot_at[0] + 1.5, robot_at[1]]
    sim.human_goal[0, 0] = [-20.0, robot_at[1]]
    sim.human_vpref[0, 0] = 1.0
    sim.observe()
    res = sim.step(np.zeros((1, 2)))
    assert EVENT_NAMES[res.event[0]] == event
    assert not res.intrusion[0] and math.isinf(res.intrusion_distance[0])


def test_run_episodes_waits_quietly_while_only_extra_seeds_end():
    """A wider env than the episodes asked for runs extra seeds; when they end first, the progress
    bar has no wanted episode to average yet (no empty-mean warning) and the records stay the
    wanted seed's."""
    env = CrowdNavVectorEnv(4, task="CrowdNav-v0", compute_intrusion=False)
    ended_first = []

    def policy(obs, fresh):  # slot 0 (the wanted seed) stands still, the others drive to their goals
        actions = env.expert_actions("straight")
        actions[0] = 0.0
        ended_first.append(fresh[1:].any() and not fresh[0])
        return actions

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        records = run_episodes(env, policy, "test", 1, progress=True)
    assert any(ended_first)  # an extra seed ended while the wanted one still ran
    assert [r.seed for r in records] == split_seeds("test", 1)
