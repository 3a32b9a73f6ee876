"""The copycat probe (scripts/probe_sensitivity.py): policies whose answers are known exactly
(one copies its velocity, one heads for the goal) must score as such, and the teacher sensibly."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from lerobot_crowdnav.sim.config import CrowdSimConfig
from lerobot_crowdnav.sim.engine import CrowdSim

spec = importlib.util.spec_from_file_location("probe_sensitivity", Path(__file__).parents[1] / "scripts/probe_sensitivity.py")
probe_mod = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # dataclasses look it up
spec.loader.exec_module(probe_mod)

CONFIG = CrowdSimConfig(task="BoundedCrowdNav-v0", compute_intrusion=False).resolve()


@pytest.fixture(scope="module")
def states():
    return probe_mod.collect_states(CONFIG, episodes=4, every=10)


def copycat(sim):
    return sim.obs[:, 7:9].astype(np.float64)


def goal_seeker(sim):
    d = (sim.obs[:, 3:5] - sim.obs[:, 0:2]).astype(np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True) * sim.obs[:, 5:6]


def test_states_are_moving_teacher_states_with_humans(states):
    assert len(states["seeds"]) >= 10
    assert np.all(np.linalg.norm(states["robot_vel"], axis=1) > 0.1)
    assert np.all(states["visible"].any(axis=1))
    assert set(states["seeds"]) <= set(range(1_000_000_000, 1_000_000_004))


def test_copycat_follows_velocity_and_ignores_goal(states):
    r = probe_mod.probe(states, CONFIG, copycat, batch_size=5)
    assert r["velocity_follow"] == pytest.approx(1.0, abs=1e-6)
    assert r["goal_turn_deg"] == pytest.approx(0.0, abs=1e-6)
    assert r["r2_action_is_velocity"] == pytest.approx(1.0, abs=1e-6)


def test_goal_seeker_ignores_velocity_and_turns_with_goal(states):
    r = probe_mod.probe(states, CONFIG, goal_seeker)
    assert r["velocity_follow"] == pytest.approx(0.0, abs=1e-6)
    assert r["goal_turn_deg"] == pytest.approx(30.0, abs=1e-4)
    assert r["r2_action_is_velocity"] < 0.99


def test_teacher_scores_are_sensible(states):
    r = probe_mod.probe(states, CONFIG, probe_mod.teacher_act)
    assert r["states"] >= 10
    for value in (r["velocity_follow"], r["goal_turn_deg"] / 30.0, r["r2_action_is_velocity"]):
        assert math.isfinite(value) and -0.5 <= value <= 1.5
    # the teacher reacts to both, partly (docs: follow 0.56, goal turn 4.0 degrees on 50 episodes)
    assert 0.2 < r["velocity_follow"] < 0.9 and 0.5 < r["goal_turn_deg"] < 15, r


def test_observe_changes_only_the_perturbed_entries_and_not_the_teacher(states):
    """The probe's unperturbed state is the teacher's: observing it again leaves the look-ahead
    robot's action as executed, and a perturbation moves only its own observation entries."""
    sim = CrowdSim(CONFIG, len(states["seeds"]))
    sim.load_state_dict(states)
    executed = probe_mod.teacher_act(sim)
    sim.load_state_dict(states)
    base = sim.observe().copy()
    np.testing.assert_array_equal(probe_mod.teacher_act(sim), executed)
    for perturb, entries in ((probe_mod.turn_velocity(20.0), [7, 8]), (probe_mod.turn_goal(30.0), [3, 4])):
        sim.load_state_dict(states)
        perturb(sim)
        changed = np.flatnonzero(np.any(sim.observe() != base, axis=0))
        assert changed.tolist() == entries


def test_turn_degrees_wraps_to_half_open_interval():
    a = np.array([[1.0, 0.0], [-1.0, 1e-12], [-1.0, -1e-12]])
    b = np.array([[-1.0, 0.0], [-1.0, -1e-12], [-1.0, 1e-12]])
    np.testing.assert_allclose(probe_mod.turn_degrees(a, b), [180.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(probe_mod.turn_degrees(a[:1], probe_mod.rotate(a[:1], -170.0)), [-170.0])


def test_cli_merges_repeated_paths_and_reports_bad_input_in_one_line():
    assert probe_mod.merge_paths(["--policy.path=orca", "--policy.path=[a,b]", "--every=3"]) == \
        ["--every=3", "--policy.path=[orca,a,b]"]
    with pytest.raises(SystemExit, match="^error: --episodes must be in"):
        probe_mod.main(["--episodes=0"])
    with pytest.raises(SystemExit, match="^error: .*every"):
        probe_mod.main(["--every=x"])
    with pytest.raises(SystemExit, match="^error: --policy.path=nowhere: no config.json"):
        probe_mod.main(["--policy.path=nowhere", "--episodes=1"])


def test_imitation_table_reads_the_runs_files(tmp_path):
    """scripts/imitation_table.py: Wilson intervals from the metrics files, the test split's
    outcomes and the probe's figures of the named policy, in the header's order."""
    spec_t = importlib.util.spec_from_file_location("imitation_table", Path(__file__).parents[1] / "scripts/imitation_table.py")
    table_mod = sys.modules[spec_t.name] = importlib.util.module_from_spec(spec_t)
    spec_t.loader.exec_module(table_mod)
    import json

    for split, sr in (("val", 0.5), ("test", 0.662)):
        (tmp_path / f"{split}.json").write_text(json.dumps(
            {"sr": sr, "n_episodes": {"val": 100, "test": 500}[split], "cr_human": 0.2, "cr_wall": 0.1, "tr": 0.038}))
    (tmp_path / "probe.json").write_text(json.dumps(
        {"policies": {"DIR": {"velocity_follow": 0.0449, "goal_turn_deg": 12.46}}}))
    manifest = {"rows": [{"label": "masked", "val": str(tmp_path / "val.json"), "test": str(tmp_path / "test.json"),
                          "probe": str(tmp_path / "probe.json"), "probe_policy": "DIR", "cost": "30,000 steps"},
                         {"label": "no val, no probe", "test": str(tmp_path / "test.json")}]}
    lines = table_mod.table(manifest).splitlines()
    assert lines[0].startswith("| remedy | val SR (%) [95 % CI] | test SR (%) [95 % CI] |")
    assert lines[2] == "| masked | 50.0 [40.4, 59.6] | 66.2 [61.9, 70.2] | 20.0 | 10.0 | 3.8 | 0.04 | 12.5 | 30,000 steps |"
    assert lines[3] == "| no val, no probe | n/a | 66.2 [61.9, 70.2] | 20.0 | 10.0 | 3.8 | n/a | n/a |  |"
    with pytest.raises(SystemExit, match="^error: --manifest"):
        table_mod.main([f"--manifest={tmp_path / 'missing.json'}"])


def test_imitation_table_curve_against_epochs(tmp_path, capsys):
    """The curve of a longer BC: epochs from steps, batch and frames; validation success with its
    Wilson interval, the outcomes and the probe (where given) per checkpoint; the figure written;
    --plot without a curve is refused."""
    table_mod = sys.modules["imitation_table"]
    import json

    for step, sr in ((30000, 0.2), (60000, 0.31)):
        (tmp_path / f"{step}.json").write_text(json.dumps(
            {"sr": sr, "n_episodes": 500, "cr_human": 0.6, "cr_wall": 0.15, "tr": 0.05}))
    (tmp_path / "probe.json").write_text(json.dumps({"policies": {
        "A": {"velocity_follow": 0.944, "goal_turn_deg": 0.88}, "orca": {"velocity_follow": 0.56, "goal_turn_deg": 4.0}}}))
    curve = {"label": "plain BC", "frames": 256_000, "batch": 128, "references": [
        {"label": "30,000 steps", "val": str(tmp_path / "30000.json")},
        {"label": "teacher", "probe": str(tmp_path / "probe.json"), "probe_policy": "orca"}],
        "points": [{"step": 30000, "val": str(tmp_path / "30000.json"), "probe": str(tmp_path / "probe.json"),
                    "probe_policy": "A"}, {"step": 60000, "val": str(tmp_path / "60000.json")}]}
    lines = table_mod.curve_table(curve).splitlines()
    assert lines[0] == ("| lerobot-train steps | epochs | val SR (%) [95 % CI] | val human CR (%) | val wall CR (%) "
                        "| val TR (%) | velocity follow | goal turn (deg) |")
    assert lines[2:] == ["| 30,000 | 15.0 | 20.0 [16.7, 23.7] | 60.0 | 15.0 | 5.0 | 0.94 | 0.9 |",
                         "| 60,000 | 30.0 | 31.0 [27.1, 35.2] | 60.0 | 15.0 | 5.0 | n/a | n/a |"]
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"rows": [], "curve": curve}))
    table_mod.main([f"--manifest={manifest}", f"--plot={tmp_path / 'fig' / 'c.png'}"])
    assert (tmp_path / "fig" / "c.png").read_bytes()[:4] == b"\x89PNG"
    assert "| 60,000 | 30.0 |" in capsys.readouterr().out
    manifest.write_text(json.dumps({"rows": []}))
    with pytest.raises(SystemExit, match="^error: --plot=.*no curve"):
        table_mod.main([f"--manifest={manifest}", f"--plot={tmp_path / 'x.png'}"])


# -- the exploration carry-over probe (scripts/probe_exploration.py) ---------------------------
sys.path.insert(0, str(Path(__file__).parents[1] / "scripts"))
spec_x = importlib.util.spec_from_file_location("probe_exploration", Path(__file__).parents[1] / "scripts/probe_exploration.py")
explore_mod = sys.modules[spec_x.name] = importlib.util.module_from_spec(spec_x)
spec_x.loader.exec_module(explore_mod)


def noisy(rho: float, sigma: float = 0.05, seed: int = 0):
    """Heads for the goal at 0.6 m/s, blended with a fraction rho of its own velocity; exploring adds
    N(0, sigma^2) per component. The AR(1) walk's carry-over is 1 / sqrt(1 - rho^2)."""
    rng = np.random.default_rng(seed)

    def act(obs, explore):
        d = (obs[:, 3:5] - obs[:, 0:2]).astype(np.float64)
        a = rho * obs[:, 7:9] + (1 - rho) * 0.6 * d / np.linalg.norm(d, axis=1, keepdims=True)
        return a + rng.normal(0, sigma, a.shape) if explore else a

    return act


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_carry_over_is_one_for_redrawn_noise_and_grows_as_the_ar1_walk(rho):
    r = explore_mod.carry_over(CONFIG, noisy(rho), episodes=64, steps=40, warmup=20)
    assert r["rms_noise"] == pytest.approx(0.05 * math.sqrt(2), rel=0.1)
    assert r["carry_over"] == pytest.approx(1 / math.sqrt(1 - rho**2), rel=0.15)


def test_exploration_probe_runs_a_pdpo_checkpoint(tmp_path):
    from conftest import make_tiny_checkpoint

    path = make_tiny_checkpoint(tmp_path / "bc")
    cfg = explore_mod.ExplorationConfig(env=CrowdSimConfig(task="BoundedCrowdNav-v0"), episodes=4, steps=4, warmup=1,
                                        policy=probe_mod.PolicyPaths([str(path)]), output=tmp_path / "x.json")
    r = explore_mod.run(cfg)["policies"][str(path)]
    assert r["rms_noise"] > 0 and np.isfinite(r["carry_over"]) and (tmp_path / "x.json").exists()
    with pytest.raises(ValueError, match="warmup"):
        explore_mod.ExplorationConfig(warmup=4, steps=4, policy=probe_mod.PolicyPaths([str(path)])).validate()
