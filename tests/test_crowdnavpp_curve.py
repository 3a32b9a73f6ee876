"""scripts/crowdnavpp_curve.py: the CrowdNav++ run's learning curve against the reference's reward
curve. Windowed means on a hand-made progress.jsonl and hand-made reference logs whose answers are
worked out below, the committed reference CSV (its shape, and its first windows recomputed from
the reference's own first log lines), and the CLI writing the figure and the table."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
from PIL import Image

ROOT = Path(__file__).parents[1]
spec = importlib.util.spec_from_file_location("crowdnavpp_curve", ROOT / "scripts/crowdnavpp_curve.py")
curve_mod = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # dataclasses look it up
spec.loader.exec_module(curve_mod)

W = 1000  # window width of the synthetic data
ENTROPY_STD_1 = 0.5 * math.log(2 * math.pi * math.e)  # a Gaussian's entropy per dimension at std 1


def it(step, episodes, ret=None, sr=None, fail=None, **extra):
    """One PPO iteration line as lerobot-crowdnav-train-ppo writes it (no train/* but the count when
    no episode ended); ``fail``: the human collision, wall collision and timeout rates (None: a log
    that does not report them)."""
    row = {"iteration": step // 200, "env_steps": step, "train/episodes": episodes, "time/wall_s": step / 10}
    if episodes:
        row |= {"train/episode_return": ret, "train/success_rate": sr}
    if fail is not None:
        row |= {f"train/{o}_rate": r for o, r in zip(curve_mod.FAILURES, fail, strict=True)}
    return row | extra


# Window 0 [0, 1000): a validation line at 0, an iteration without episodes, a validation at 800.
# Window 1 [1000, 2000): no validation. Window 2 [2000, 3000): reached up to 2200 only (so far).
PROGRESS = [
    {"iteration": 0, "env_steps": 0, "val/success_rate": 0.0, "val/episode_return": -20.0},
    it(200, 2, -10.0, 0.0, (0.5, 0.5, 0.0), entropy=2 * ENTROPY_STD_1), it(400, 0),
    it(600, 3, -5.0, 1 / 3, (1 / 3, 1 / 3, 0.0)),
    it(800, 5, 1.0, 0.4, (0.2, 0.2, 0.2), entropy=2 * ENTROPY_STD_1 - 2, **{"val/success_rate": 0.25}),
    it(1000, 4, 2.0, 0.5), it(1200, 4, 4.0, 0.25, (0.5, 0.25, 0.0), **{"train/prediction_penalty": -1.0}),
    it(1400, 2, -1.0, 0.0, (1.0, 0.0, 0.0)),
    it(1600, 0), it(1800, 10, 3.0, 0.6, (0.2, 0.1, 0.1), **{"train/prediction_penalty": -2.0}),
    it(2000, 1, 7.0, 1.0, (0.0, 0.0, 0.0), **{"train/prediction_penalty": -3.0}),
    it(2200, 3, 3.0, 1 / 3, (1 / 3, 0.0, 1 / 3), entropy=2 * ENTROPY_STD_1,
       **{"val/success_rate": 0.5, "train/prediction_penalty": 0.0}),
]
# Episode-weighted by hand: window 0 (2 * -10 + 3 * -5 + 5 * 1) / 10 = -3.0, success (0 + 1 + 2) / 10,
# human collisions, wall collisions, timeouts (1 + 1 + 1) / 10, (1 + 1 + 1) / 10, (0 + 0 + 1) / 10;
# window 1 (8 + 16 - 2 + 30) / 20 = 2.6 and (2 + 1 + 0 + 6) / 20, its failures unknown (the line at
# 1000 does not report them); window 2 (7 + 9) / 4 = 4.0, 2 / 4, failures 1 / 4, 0, 1 / 4.
# (A plain mean over iterations would give -4.67, 2.0 and 5.0 instead.) The policy's entropy (summed
# over vx, vy) is a plain mean over the iterations that log it: window 0 2 E - 1 (std e^-1/2 = 0.61),
# window 1 none, window 2 2 E (std 1), E being the entropy per dimension at std 1. The reward without
# the prediction penalty, over the iterations that log it: window 0 none, window 1 (4 * (4 + 1) +
# 10 * (3 + 2)) / 14 = 5.0, window 2 (1 * (7 + 3) + 3 * 3) / 4 = 4.75.
# The same run had it logged the prediction penalty on every line with episodes (-1 each).
LOGGED = [r | {"train/prediction_penalty": -1.0} if r.get("train/episodes") else r for r in PROGRESS]
NAN3 = (math.nan,) * 3
EXPECTED = [  # k, reward, success, (human, wall, timeout), val success, val step, wall_s, complete
    (0, -3.0, 0.3, (0.3, 0.3, 0.1), 0.25, 800, 80.0, True),
    (1, 2.6, 0.45, NAN3, math.nan, None, 180.0, True),
    (2, 4.0, 0.5, (0.25, 0.0, 0.25), 0.5, 2200, 220.0, False),
]


def write_progress(folder: Path, rows=PROGRESS) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "progress.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"iteration": 12, "env_')
    return folder


def write_log(path: Path, points: list[tuple[int, float]]) -> Path:
    """A reference-format progress.csv (columns as the reference's train.py writes them); the
    entropy is the reward / 10 + 1.4193 (std 1 m/s at a reward of 0)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["misc/nupdates", "misc/total_timesteps", "fps", "eprewmean", "loss/policy_entropy"])
        for i, (t, v) in enumerate(points):
            w.writerow([20 * (i + 1), t, 200, v, v / 10 + ENTROPY_STD_1])
    return path


# Logged every 250 env steps: window 0 holds 250, 500, 750; window 1 holds 1000-1750; window 2
# only 2000 and 2250, and the log ends there (2250 + 250 < 3000): not covered, left out.
RAND = [(250, -9.0), (500, -6.0), (750, 0.0), (1000, 1.0), (1250, 2.0), (1500, 4.0), (1750, 9.0), (2000, 5.0),
        (2250, 6.0)]
NON_RAND = [(250, -3.0), (500, -2.0), (750, -1.5), (1000, 8.0)]  # window 0 only


def test_run_windows_are_episode_weighted_with_latest_validation_and_wall_time():
    windows = curve_mod.run_windows(PROGRESS, W)
    assert [w.k for w in windows] == [0, 1, 2]
    for w, (k, reward, success, failures, val, val_step, wall, complete) in zip(windows, EXPECTED, strict=True):
        assert w.k == k and w.complete is complete and w.val_step == val_step
        assert w.reward == pytest.approx(reward, abs=1e-12) and w.rates["success"] == pytest.approx(success, abs=1e-12)
        assert [w.rates[o] for o in curve_mod.FAILURES] == pytest.approx(failures, abs=1e-12, nan_ok=True)
        assert (math.isnan(w.val_success) and math.isnan(val)) or w.val_success == val
        assert w.wall_s == wall
    assert [w.episodes for w in windows] == [10, 20, 4]
    assert [w.reward_without_penalty for w in windows] == pytest.approx([math.nan, 5.0, 4.75], abs=1e-12, nan_ok=True)
    assert [w.split_share for w in windows] == pytest.approx([0.0, 0.7, 1.0])  # 14 of window 1's 20 episodes
    assert [w.entropy for w in windows] == pytest.approx([2 * ENTROPY_STD_1 - 1, math.nan, 2 * ENTROPY_STD_1],
                                                         abs=1e-12, nan_ok=True)


def test_the_iteration_past_the_budget_counts_in_the_budgets_last_window():
    """A 2,000-step budget: the iterations ending at 2000 and 2200 join window 1, none is left
    alone in window 2; window 1's reward (8 + 16 - 2 + 30 + 7 + 9) / 24, and it is complete."""
    windows = curve_mod.run_windows(PROGRESS, W, budget=2000)
    assert [w.k for w in windows] == [0, 1] and [w.episodes for w in windows] == [10, 24]
    assert windows[1].reward == pytest.approx(68 / 24, abs=1e-12) and windows[1].complete
    assert windows[1].last_step == 2200 and windows[1].val_step == 2200
    assert [w.k for w in curve_mod.run_windows(PROGRESS, W, budget=10_000)] == [0, 1, 2]  # a run in progress


def test_reference_logs_reduce_to_exact_window_means(tmp_path):
    rand = curve_mod.reference_log_windows(write_log(tmp_path / "rand.csv", RAND), W)
    assert rand == {"eprewmean": {0: pytest.approx(-5.0, abs=1e-12), 1: pytest.approx(4.0, abs=1e-12)},
                    "entropy": {0: pytest.approx(ENTROPY_STD_1 - 0.5, abs=1e-12),
                                1: pytest.approx(ENTROPY_STD_1 + 0.4, abs=1e-12)}}
    out = tmp_path / "ref.csv"
    rows = curve_mod.write_reference(tmp_path / "rand.csv", write_log(tmp_path / "non.csv", NON_RAND), out, W)
    assert out.read_text() == ("env_steps,eprewmean_rand,eprewmean_non_rand,entropy_rand,entropy_non_rand\n"
                               "500,-5.000000,-2.166667,0.918939,1.202272\n"
                               "1500,4.000000,,1.818939,\n")
    assert len(rows) == 2
    ref = curve_mod.read_reference(out, W)
    assert ref == {"eprewmean_rand": {0: -5.0, 1: 4.0}, "eprewmean_non_rand": {0: -2.166667},
                   "entropy_rand": {0: 0.918939, 1: 1.818939}, "entropy_non_rand": {0: 1.202272}}
    # an entropy of ln(2 pi e) / 2 per dimension is a std of 1; each nat more multiplies it by e
    assert curve_mod.policy_std(ENTROPY_STD_1) == pytest.approx(1.0, abs=1e-12)
    assert curve_mod.policy_std(ENTROPY_STD_1 - 0.5) == pytest.approx(math.exp(-0.5), abs=1e-12)
    with pytest.raises(ValueError, match="centre"):
        curve_mod.read_reference(out, 400)


def test_committed_reference_csv_is_the_reduction_of_the_reference_logs():
    """80 windows of 0.25 M env steps, the four curves to 20 M (where the reference's logs end);
    their first window recomputed from the reference's first 25 log lines (total_timesteps 10,080
    to 240,480, every 20 updates of 16 x 30 steps), copied here from the two progress.csv files."""
    with open(curve_mod.REFERENCE_CSV, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["env_steps"]) for r in rows] == [125_000 + 250_000 * k for k in range(80)]
    values = {c: [float(r[c]) for r in rows] for c in curve_mod.REFERENCE_COLUMNS}
    assert all(math.isfinite(v) for vs in values.values() for v in vs)
    first_rand = [-19.34756513, -20.09821679, -17.57117294, -17.2405179, -16.97256182, -17.62280149, -17.35363328,
                  -15.01342298, -17.11895, -16.23211242, -16.2399404, -15.01077666, -16.98431535, -16.89858911,
                  -15.08061458, -17.51793628, -17.33022533, -17.31004936, -19.17175757, -16.84911331, -15.70596161,
                  -16.1901056, -16.02629202, -16.91052895, -17.06131023]
    first_non_rand = [-18.98487425, -16.86580585, -16.55486363, -17.06672025, -15.9982422, -16.44300883,
                      -15.74378921, -15.09039705, -17.17453089, -13.85063568, -15.5046847, -16.09453213,
                      -15.86032219, -14.67720427, -16.57059128, -14.19925753, -16.85316213, -15.94426089,
                      -14.0578362, -13.9835012, -13.09644294, -14.19374541, -12.93764942, -12.69022262,
                      -13.20982481]
    entropy_rand = [1.4193906426429748, 1.4202398538589478, 1.4201084852218628, 1.4198580265045166,
                    1.419650101661682, 1.4192113399505615, 1.4187208890914917, 1.4182256579399108,
                    1.4182194709777831, 1.4181082248687744, 1.4178841710090637, 1.4177842497825623,
                    1.4177506685256958, 1.4174901127815247, 1.4176611065864564, 1.417246150970459,
                    1.416961920261383, 1.4167022824287414, 1.4170844793319701, 1.4169718742370605,
                    1.4164634466171264, 1.4155369639396667, 1.415892243385315, 1.4158755540847778, 1.4162428259849549]
    entropy_non_rand = [1.4189715027809142, 1.4189993023872376, 1.418747067451477, 1.4185497403144836,
                        1.417847502231598, 1.4172162532806396, 1.417325234413147, 1.417020332813263,
                        1.4164602756500244, 1.416001808643341, 1.415651762485504, 1.4153205275535583,
                        1.4146570563316345, 1.4140007138252257, 1.4138383984565734, 1.4133376240730287,
                        1.4117445826530457, 1.4115410685539245, 1.41027991771698, 1.4100423216819764,
                        1.4095882058143616, 1.4100745439529419, 1.4098980665206908, 1.408864390850067, 1.4089937567710877]
    for column, first in (("eprewmean_rand", first_rand), ("eprewmean_non_rand", first_non_rand),
                          ("entropy_rand", entropy_rand), ("entropy_non_rand", entropy_non_rand)):
        assert values[column][0] == pytest.approx(math.fsum(first) / 25, abs=5e-7), column
    # Both reference trainings learn: the last 2 M env steps average well above the first 2 M; their
    # policies start at std 1 m/s (log-std 0) and narrow, the non-randomized one most.
    for c in curve_mod.REWARD_COLUMNS:
        assert sum(values[c][-8:]) / 8 > sum(values[c][:8]) / 8 + 20
    stds = {c: [curve_mod.policy_std(h) for h in values[c]] for c in curve_mod.ENTROPY_COLUMNS}
    assert all(0.99 < vs[0] <= 1.0 and vs[-1] < vs[0] for vs in stds.values())
    assert stds["entropy_non_rand"][-1] < 0.4 < 0.8 < stds["entropy_rand"][-1]


def test_table_marks_the_window_so_far_and_missing_values(tmp_path):
    out = tmp_path / "ref.csv"
    curve_mod.write_reference(write_log(tmp_path / "r.csv", RAND), write_log(tmp_path / "n.csv", NON_RAND), out, W)
    windows, reference = curve_mod.run_windows(PROGRESS, W), curve_mod.read_reference(out, W)
    lines = curve_mod.table(windows, reference, W).splitlines()
    assert lines[0] == "| " + " | ".join(curve_mod.HEADER) + " |" and len(lines) == 5
    # the reference's entropies are E + reward / 10 per line: window 0 E - 0.5 (rand), E - 0.217 (non-rand)
    assert lines[2] == "| 0-1,000 | -3.00 | n/a | -5.00 | -2.17 | 30.0 | 30.0 / 30.0 / 10.0 | 0.61 / 0.61 / 0.81 | 25 at 800 | 0.02 |"
    assert lines[3] == "| 1,000-2,000 | 2.60 | 5.00 (70 % of its episodes) | 4.00 | n/a | 45.0 | n/a / n/a / n/a | n/a / 1.49 / n/a |  | 0.05 |"
    assert lines[4] == ("| 2,000-2,200 (so far) | 4.00 | 4.75 | n/a | n/a | 50.0 | 25.0 / 0.0 / 25.0 | 1.00 / n/a / n/a "
                        "| 50 at 2,200 | 0.06 |")
    # with the run's validation episodes known, each reading gets its 95 % Wilson interval
    lines = curve_mod.table(windows, reference, W, val_episodes=100).splitlines()
    assert lines[2].endswith("| 25 [18, 34] at 800 | 0.02 |") and lines[4].endswith("| 50 [40, 60] at 2,200 | 0.06 |")


def test_a_compared_run_draws_only_its_finished_windows_that_log_the_penalty_throughout():
    # PROGRESS: window 0 logs no penalty, window 1 only 70 % of its episodes, window 2 is not
    # finished: none is drawn. Penalty on every line: windows 0 and 1, not the unfinished 2.
    assert curve_mod.compare_points(curve_mod.run_windows(PROGRESS, W), W) == []
    points = curve_mod.compare_points(curve_mod.run_windows(LOGGED, W), W)
    # window 0: -3.0 + 1 = -2.0, success 0.3; window 1: 2.6 + 1 = 3.6, success 0.45
    assert [(x, round(r, 9), round(sr, 9)) for x, r, sr in points] == [(500.0, -2.0, 0.3), (1500.0, 3.6, 0.45)]


def test_cli_writes_figure_and_table(tmp_path, capsys):
    run = write_progress(tmp_path / "run")
    ref, png, md = tmp_path / "ref.csv", tmp_path / "fig" / "curve.png", tmp_path / "table.md"
    curve_mod.main([f"--run={run}", f"--reference={ref}", f"--output_png={png}", f"--output_md={md}", f"--window={W}",
                    f"--reference_rand_log={write_log(tmp_path / 'r.csv', RAND)}",
                    f"--reference_non_rand_log={write_log(tmp_path / 'n.csv', NON_RAND)}"])
    printed = capsys.readouterr().out
    table = md.read_text()
    assert table.strip() in printed and table.count("\n") == 5 and "(so far)" in table
    assert "| 25 at 800 |" in table  # no checkpoint yet: the validation episodes are unknown
    settings = run / "checkpoints" / "last" / "pretrained_model" / "train_ppo_config.json"
    settings.parent.mkdir(parents=True)
    settings.write_text(json.dumps({"val": {"n_episodes": 100}, "env_steps": 100_000}))
    png.unlink()
    curve_mod.main([f"--run={run}", f"--reference={ref}", f"--output_png={png}", f"--output_md={md}", f"--window={W}"])
    assert "| 25 [18, 34] at 800 |" in md.read_text() and png.stat().st_size > 5_000  # with error bars
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] > 500 and im.size[1] > 400
    # Another run beside it changes the figure, not the table; a compared folder without a log is refused.
    other = write_progress(tmp_path / "other_seed", LOGGED)
    alone, table = png.read_bytes(), md.read_text()
    curve_mod.main([f"--run={run}", f"--reference={ref}", f"--output_png={png}", f"--output_md={md}", f"--window={W}",
                    f"--compare=[{other}]"])
    assert png.read_bytes() != alone and md.read_text() == table
    with pytest.raises(SystemExit, match="missing/progress.jsonl: no such file"):
        curve_mod.main([f"--run={run}", f"--reference={ref}", "--output_png=null", f"--compare=[{tmp_path / 'missing'}]"])
    # Without a figure, and the errors a user can make, as one-line messages.
    curve_mod.main([f"--run={run}", f"--reference={ref}", "--output_png=null", f"--window={W}"])
    with pytest.raises(SystemExit, match="progress.jsonl: no such file"):
        curve_mod.main([f"--run={tmp_path}", f"--reference={ref}", "--output_png=null"])
    with pytest.raises(SystemExit, match="go together"):
        curve_mod.main([f"--reference_rand_log={tmp_path / 'r.csv'}"])
    with pytest.raises(SystemExit, match="give --run"):
        curve_mod.main([])


def test_help_explains_every_option(capsys):
    with pytest.raises(SystemExit) as e:
        curve_mod.main(["--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in curve_mod.CurveConfig.__dataclass_fields__:
        assert f"--{name}" in text
    for phrase in ("progress.jsonl", "GST_predictor_rand/progress.csv", "Window width in env steps", "null to write none"):
        assert phrase in text
