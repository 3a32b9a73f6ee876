"""The evaluation CLI, ``lerobot_crowdnav.evaluation.eval`` (``lerobot-crowdnav-eval``)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import pytest
from PIL import Image

from lerobot_crowdnav.evaluation.eval import EvalSettings, main
from lerobot_crowdnav.sim.config import split_seeds

TASKS = ("BoundedCrowdNav-v0", "CrowdNav-v0")
POLICIES = ("orca", "straight")
METRIC_KEYS = {"sr", "cr", "tr", "nt", "pl", "itr", "sd", "oob", "n_episodes", "env", "episodes"}
EVENTS = {"success", "human_collision", "wall_collision", "timeout"}


def _eval(out, *args, n_episodes=12, batch_size=5, policy="orca", task="BoundedCrowdNav-v0") -> dict:
    main([f"--policy.type={policy}", f"--env.task={task}", f"--eval.n_episodes={n_episodes}",
          f"--eval.batch_size={batch_size}", f"--output_dir={out}", *args])
    return json.loads((out / "metrics.json").read_text())


def _row_cells(line: str) -> list[str]:
    assert line.startswith("|") and line.endswith("|"), line
    return [c.strip() for c in line[1:-1].split("|")]


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("policy", POLICIES)
def test_eval_writes_metrics_and_prints_row(tmp_path, capsys, policy, task):
    out = tmp_path / "eval"
    result = _eval(out, policy=policy, task=task)

    assert METRIC_KEYS <= set(result)
    assert result["n_episodes"] == 12
    assert result["policy"] == policy and result["split"] == "test"
    assert result["env"]["task"] == task and result["env"]["preset"] == "paper"
    assert result["env"]["num_humans"] == 20  # the resolved config, not the None placeholders
    # Which ORCA robot ran: the paper preset's look-ahead one, wall-unaware.
    assert result["env"]["orca_robot"] == "look_ahead" and not result["env"]["orca_robot_wall_aware"]
    assert result["policy_description"] == ("orca (look_ahead)" if policy == "orca" else policy)

    episodes = result["episodes"]
    assert [e["seed"] for e in episodes] == split_seeds("test", 12)
    assert all(e["event"] in EVENTS for e in episodes)
    assert all(1 <= e["steps"] <= 197 for e in episodes)
    for key in ("sr", "cr", "tr", "itr", "oob"):
        assert 0.0 <= result[key] <= 1.0, (key, result[key])
    assert result["sr"] + result["cr"] + result["tr"] == pytest.approx(1.0)
    n = len(episodes)
    assert result["sr"] == pytest.approx(sum(e["event"] == "success" for e in episodes) / n)
    assert result["tr"] == pytest.approx(sum(e["event"] == "timeout" for e in episodes) / n)
    assert result["pl"] == pytest.approx(sum(e["path_length"] for e in episodes) / n)
    successes = [e for e in episodes if e["event"] == "success"]
    assert successes, "expected at least one success in 12 episodes"
    assert result["nt"] == pytest.approx(sum(e["steps"] - 1 for e in successes) * 0.25 / len(successes))
    assert result["pl"] > 0 and math.isfinite(result["sd"])
    if task == "CrowdNav-v0":
        assert not any(e["event"] == "wall_collision" for e in episodes)
    if policy == "straight":
        # Full speed (1 m/s, dt 0.25 s) in a straight line: 0.25 m a step, arriving exactly.
        assert all(e["path_length"] <= 0.25 * e["steps"] + 1e-6 for e in episodes)

    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert len(lines) == 3, lines  # header, separator, row
    header, row = _row_cells(lines[0]), _row_cells(lines[2])
    n_cols = 5 if task == "BoundedCrowdNav-v0" else 8
    assert len(header) == n_cols and len(row) == n_cols
    assert header[0] == "SR (%)"
    assert lines[2] == result["markdown"]
    assert float(row[0]) == pytest.approx(100 * result["sr"], abs=0.05)
    assert float(row[2]) == pytest.approx(result["pl"], abs=0.005)


def test_eval_results_do_not_depend_on_batch_size(tmp_path, capsys):
    small = _eval(tmp_path / "b3", batch_size=3, task="CrowdNav-v0")
    large = _eval(tmp_path / "b12", batch_size=12, task="CrowdNav-v0")
    assert small["episodes"] == large["episodes"]
    for key in ("sr", "cr", "tr", "nt", "pl", "itr", "sd", "oob"):
        assert small[key] == large[key], key
    assert small["markdown"] == large["markdown"]
    # batch_size > n_episodes is capped, not an error, and gives the same episodes.
    capped = _eval(tmp_path / "b64", batch_size=64, task="CrowdNav-v0")
    assert capped["episodes"] == small["episodes"]


def test_existing_output_dir_is_refused_then_overwritten(tmp_path, capsys):
    out = tmp_path / "eval"
    out.mkdir()
    metrics = out / "metrics.json"
    metrics.write_text('{"sentinel": true}')
    before = metrics.stat().st_mtime_ns

    with pytest.raises(SystemExit) as exc:
        _eval(out, n_episodes=3, batch_size=3, policy="straight")
    message = str(exc.value.code)
    assert "--overwrite" in message and "metrics.json" in message
    assert metrics.read_text() == '{"sentinel": true}'
    assert metrics.stat().st_mtime_ns == before
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]

    result = _eval(out, "--overwrite=true", n_episodes=3, batch_size=3, policy="straight")
    assert "sentinel" not in result
    assert result["n_episodes"] == 3
    assert [e["seed"] for e in result["episodes"]] == split_seeds("test", 3)
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]  # no leftover temp file


@pytest.mark.parametrize("arg, message", [
    ("--eval.split=bogus", "--eval.split must be one of"),
    ("--eval.n_episodes=0", "--eval.n_episodes must be in [1, 500]"),
    ("--eval.n_episodes=501", "--eval.n_episodes must be in [1, 500]"),
    ("--eval.n_episodes=abc", "`eval.n_episodes`: Couldn't parse 'abc' into an int"),
    ("--eval.batch_size=0", "--eval.batch_size must be >= 1"),
    ("--eval.n_videos=-1", "--eval.n_videos must be >= 0"),
    ("--env.task=Nope-v0", "unknown task 'Nope-v0'"),
    ("--env.preset=nope", "unknown preset 'nope'"),
])
def test_bad_input_exits_with_clear_message(tmp_path, arg, message):
    out = tmp_path / "eval"
    with pytest.raises(SystemExit) as exc:
        main(["--policy.type=straight", f"--output_dir={out}", arg])
    text = exc.value.code
    assert isinstance(text, str), f"expected a message, got exit code {text!r}"
    assert text.startswith("error: ") and message in text, text
    assert not out.exists()  # nothing written


def test_val_split_takes_val_seeds(tmp_path, capsys):
    result = _eval(tmp_path / "val", "--eval.split=val", n_episodes=2, batch_size=2, policy="straight")
    assert [e["seed"] for e in result["episodes"]] == split_seeds("val", 2)
    with pytest.raises(SystemExit) as exc:
        _eval(tmp_path / "val1001", "--eval.split=val", n_episodes=1001, policy="straight")
    assert "[1, 1000]" in str(exc.value.code)
    # the holdout seeds (beyond 2^31) run through the same CLI
    result = _eval(tmp_path / "holdout", "--eval.split=holdout", n_episodes=2, batch_size=2, policy="orca")
    assert [e["seed"] for e in result["episodes"]] == split_seeds("holdout", 2) and result["n_episodes"] == 2


def test_module_help_mentions_every_setting():
    res = subprocess.run([sys.executable, "-m", "lerobot_crowdnav.evaluation.eval", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    for f in dataclasses.fields(EvalSettings):
        assert f"--eval.{f.name}" in res.stdout, f.name
    for flag in ("--policy.type {orca,straight,pretrained}", "--policy.path", "--env.task", "--env.preset",
                 "--env.orca_robot", "--env.orca_robot_wall_aware", "--env.randomize_neighbor_dist",
                 "--output_dir", "--overwrite"):
        assert flag in res.stdout, flag


def test_n_videos_writes_gif(tmp_path, capsys):
    out = tmp_path / "eval"
    result = _eval(out, "--eval.n_videos=1", n_episodes=2, batch_size=2, policy="straight")
    seed = split_seeds("test", 1)[0]
    gifs = sorted((out / "videos").iterdir())
    assert [g.name for g in gifs] == [f"straight_seed{seed}.gif"]
    with Image.open(gifs[0]) as im:
        assert im.format == "GIF"
        assert im.size == (512, 512)
        # One frame for the start and one per step of the first episode.
        assert im.n_frames == result["episodes"][0]["steps"] + 1


def test_undefined_metrics_are_null_in_strict_json(tmp_path, capsys):
    """No success (every episode times out after 2 s): NT and OOB are undefined -> null."""
    out = tmp_path / "timeouts"
    main(["--policy.type=orca", "--env.task=CrowdNav-v0", "--env.time_limit=2", "--eval.n_episodes=3",
          f"--output_dir={out}"])

    def refuse(token):
        raise AssertionError(f"non-standard JSON constant {token}")

    result = json.loads((out / "metrics.json").read_text(), parse_constant=refuse)
    assert result["tr"] == 1.0 and result["nt"] is None and result["oob"] is None
    assert "n/a" in result["markdown"]


@pytest.mark.parametrize("name", ["bounded_orca", "bounded_straight", "original_orca",
                                  "original_straight", "original_crowdnavpp_orca", "crowdnavpp_orca_baseline"])
def test_shipped_eval_configs_parse(name):
    import draccus

    from lerobot_crowdnav.evaluation.eval import EvalConfig

    cfg = draccus.parse(EvalConfig, config_path=f"configs/eval/{name}.yaml", args=[])
    sim = cfg.env.resolve()
    assert sim.bounded == name.startswith("bounded")
    assert cfg.policy.name == ("orca" if "orca" in name else "straight")
    assert cfg.eval.n_episodes == 500 and cfg.eval.split == "test"
    if "crowdnavpp" in name:
        assert sim.preset == "crowdnavpp" and sim.randomize_attributes is False
        assert sim.orca_robot == "current_state" and not sim.randomize_neighbor_dist
    if name == "crowdnavpp_orca_baseline":
        assert sim.goal_change_prob == 0.0


def test_baselines_command_writes_tables_and_resumes(tmp_path, capsys):
    from lerobot_crowdnav.evaluation.baselines import main as baselines_main

    args = ["--n_episodes=4", "--batch_size=4", "--only=[crowdnavpp_orca_baseline]", f"--output_dir={tmp_path}"]
    baselines_main(args)
    text = (tmp_path / "baselines.md").read_text()
    assert "| ORCA look-ahead |" in text and "| ORCA current-state |" in text
    metrics = sorted(tmp_path.rglob("metrics.json"))
    assert len(metrics) == 2
    row = json.loads(metrics[0].read_text())
    assert row["n_episodes"] == 4 and row["env"]["goal_change_prob"] == 0.0
    stamps = [m.stat().st_mtime_ns for m in metrics]
    baselines_main(args)  # a rerun keeps finished rows
    assert [m.stat().st_mtime_ns for m in metrics] == stamps
    assert (tmp_path / "baselines.md").read_text() == text
    with pytest.raises(SystemExit, match="unknown tables"):
        baselines_main(["--only=[nope]", f"--output_dir={tmp_path}"])
    baselines_main(["--n_episodes=4", "--batch_size=4", "--only=[bounded_paper]", f"--output_dir={tmp_path}"])
    audit = (tmp_path / "baselines.md").read_text().split("Wall audit")[1]  # a Bounded table's
    assert "| ORCA current-state, wall-aware | 4 | " in audit and "| straight | 4 | " in audit


def test_a_saved_evaluation_is_reused_only_for_the_same_request(tmp_path, capsys):
    """The main job and the baselines reuse a metrics.json only when it answers the same
    evaluation: another preset, crowd, policy setting or metric definition runs it again (and,
    for a trained policy, another batch size)."""
    from lerobot_crowdnav.evaluation.eval import parse, request, saved_result

    args = ["--policy.type=straight", "--env.task=BoundedCrowdNav-v0", "--eval.n_episodes=2", f"--output_dir={tmp_path}"]
    main(args)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved_result(parse(args)) == saved
    assert saved_result(parse(args + ["--eval.batch_size=1"])) == saved  # the numbers do not depend on it
    for other in (["--env.preset=crowdnavpp"], ["--env.human_policy=social_force"], ["--eval.n_episodes=3"],
                  ["--eval.split=val"], ["--policy.type=orca"]):
        assert saved_result(parse(args + other)) is None, other
    trained = lambda *a: request(parse(["--policy.path=/nowhere", *args[1:], *a]))  # noqa: E731
    assert trained("--eval.batch_size=1") != trained("--eval.batch_size=2")  # its sampling noise is drawn per batch
    assert trained("--eval.batch_size=2") == trained("--eval.batch_size=64")  # capped at the episode count
    for version in ("metrics_version", "sim_version"):  # evaluated under older metrics, or episodes
        older = json.loads(json.dumps(saved))
        older["request"][version] -= 1
        (tmp_path / "metrics.json").write_text(json.dumps(older))
        assert saved_result(parse(args)) is None, version
