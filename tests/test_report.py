"""Table generation on hand-made metrics, and the main job end to end in a tiny configuration."""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
from pathlib import Path

import draccus
import pytest

from lerobot_crowdnav.data.hub import portable
from lerobot_crowdnav.evaluation.report import Row, boundary_audit, csv_table, markdown_table, parameter_table, wall_audit
from lerobot_crowdnav.main.config import MainConfig
from lerobot_crowdnav.main.training import Training
from lerobot_crowdnav.pipeline import main as pipeline_main

import fault_injection as fi


def metrics(sr, nt, pl, itr, sd, episodes=()):
    return {"sr": sr, "nt": nt, "pl": pl, "itr": itr, "sd": sd, "cr": 1 - sr, "tr": 0.0, "oob": None,
            "episodes": [{"event": e, "out_of_bounds": o} for e, o in episodes]}


def test_tables_from_hand_made_metrics():
    rows = [Row("ORCA", [metrics(0.662, 20.94, 13.17, 0.0918, 0.32)]),
            Row("PDPO", [metrics(0.5, 10.0, 8.0, 0.1, 0.3), metrics(0.7, 12.0, 9.0, 0.05, None)]),
            Row("never succeeds", [metrics(0.0, None, 5.0, 0.0, None)])]
    rows[0].metrics[0]["n_episodes"] = 500
    for m, n in zip(rows[1].metrics, (100, 300), strict=True):
        m["n_episodes"] = n
    md = markdown_table(rows).splitlines()
    assert md[0] == "| Method | SR (%) | SR 95 % CI | NT (s) | PL (m) | ITR (%) | SD (m) |"
    # Wilson: 331 of 500 -> [61.9, 70.2]
    assert md[2] == "| ORCA | 66.2 | [61.9, 70.2] | 20.94 | 13.17 | 9.18 | 0.32 |"
    # two seeds: mean +- population std; SD defined for one seed only -> that value, no spread; the
    # interval pools the seeds' episodes (50 + 210 of 400)
    assert md[3] == "| PDPO | 60.0 ± 10.0 | [60.2, 69.5] | 11.00 ± 1.00 | 8.50 ± 0.50 | 7.50 ± 2.50 | 0.30 |"
    assert md[4] == "| never succeeds | 0.0 | n/a | n/a | 5.00 | 0.00 | n/a |"  # no episode count: no interval
    table = list(csv.DictReader(io.StringIO(csv_table(rows))))
    assert table[1]["method"] == "PDPO" and table[1]["n_seeds"] == "2"
    assert float(table[1]["SR_mean"]) == pytest.approx(60.0) and float(table[1]["SR_std"]) == pytest.approx(10.0)
    assert float(table[0]["SR95_low"]) == pytest.approx(61.944, abs=0.001) and table[2]["SR95_high"] == ""
    assert table[2]["NT_mean"] == "" and table[2]["SD_std"] == ""


def test_wilson_interval_against_known_values():
    from lerobot_crowdnav.measure.metrics import wilson_interval

    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)  # not [0, 0] as the normal one
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(50, 100) == pytest.approx((0.4038, 0.5962), abs=1e-4)
    lo, hi = wilson_interval(366, 500)  # 73.2 %: +-3.9 points
    assert (lo, hi) == pytest.approx((0.6915, 0.7689), abs=1e-4)


def test_boundary_audit_counts_successful_episodes_only():
    rows = [Row("ORCA", [metrics(0.75, 1, 1, 0, 0, [("success", True), ("success", False), ("success", False),
                                                     ("human_collision", True)])]),
            Row("PDPO", [metrics(0.0, None, 1, 0, 0, [("timeout", True)])])]
    md, text = boundary_audit(rows)
    assert "| ORCA | 3 | 1 | 33.3 |" in md and "| PDPO | 0 | 0 | n/a |" in md
    assert list(csv.reader(io.StringIO(text)))[1] == ["ORCA", "3", "1", "33.3333"]
    md, text = parameter_table({"PDPO": {"actor": 832_000, "critic": 198_000}})
    assert "| PDPO | 0.832 | 0.198 |" in md and "| paper (PDPO) | 0.848 | 0.201 |" in md


def test_wall_audit_splits_wall_collisions_by_cause():
    env = {"arena_size": 6.0, "robot_radius": 0.2}
    episodes = [{"event": "success", "steps": 40, "goal": [5.9, 0.0]},
                {"event": "human_collision", "steps": 30, "goal": [0.0, 1.0]},
                {"event": "wall_collision", "steps": 1, "goal": [1.0, 1.0]},  # starts touching a wall
                {"event": "wall_collision", "steps": 30, "goal": [-1.0, -5.85]},  # goal in the wall zone
                {"event": "wall_collision", "steps": 30, "goal": [5.7, 2.0]},  # goal clear of it
                {"event": "wall_collision", "steps": 2, "goal": [3.0, 5.79]},  # just clear (5.8 is the edge)
                {"event": "timeout", "steps": 197, "goal": [0.0, 0.0]},
                {"event": "success", "steps": 40, "goal": [0.0, 0.0]}]
    old = [{k: v for k, v in e.items() if k != "goal"} for e in episodes]  # records written before goals
    rows = [Row("PDPO", [{"env": env, "episodes": episodes}]), Row("older", [{"env": env, "episodes": old}])]
    md, text, facts = wall_audit(rows)
    assert "| PDPO | 8 | 25.0 | 12.5 | 12.5 | 12.5 | 25.0 | 12.5 |" in md
    assert "| older | 8 | 25.0 | 12.5 | 12.5 | n/a | n/a | 12.5 |" in md
    table = list(csv.DictReader(io.StringIO(text)))
    assert table[0]["wall_other"] == "25" and table[1]["wall_goal_in_zone"] == ""
    assert facts.startswith("12.5 % of the episodes start with the robot touching a wall") and "at most 87.5 % success" in facts
    assert "and 25.0 % have their goal inside the wall zone" in facts


def test_generalization_table_from_hand_made_metrics():
    """A row per policy; per crowd SR with its Wilson interval over the pooled seeds, its change
    from the first crowd (points) and human / wall CR / TR; the CSV keeps a line per (policy, crowd)."""
    from lerobot_crowdnav.evaluation.generalization import check_crowds, generalization_csv, generalization_markdown, read_csv

    def m(sr, n=500, human=0.1, wall=0.05):
        return {"sr": sr, "n_episodes": n, "cr_human": human, "cr_wall": wall, "tr": 1 - sr - human - wall, "nt": None,
                "itr": 0.02}

    results = {"ORCA": {"orca": [m(0.49)], "reactive_orca": [m(0.6, wall=0.2)]},
               "PDPO": {"orca": [m(0.5, 100), m(0.7, 300)], "reactive_orca": [m(0.4, 100), m(0.6, 300)]}}
    text = generalization_csv(results, ["orca", "reactive_orca"])
    rows = read_csv(text)
    assert [(r["method"], r["crowd"], r["n_seeds"], r["n_episodes"]) for r in rows] == [
        ("ORCA", "orca", "1", "500"), ("ORCA", "reactive_orca", "1", "500"), ("PDPO", "orca", "2", "400"),
        ("PDPO", "reactive_orca", "2", "400")]
    assert rows[0]["NT_mean"] == "" and float(rows[1]["SR_change"]) == pytest.approx(11.0)
    md = generalization_markdown(rows, bounded=True).splitlines()
    assert md[0] == ("| Method | trained (ORCA): SR (%) [95 % CI] | trained (ORCA): human CR / wall CR / TR (%) | "
                     "reactive ORCA: SR (%) [95 % CI] | reactive ORCA: SR change | reactive ORCA: human CR / wall CR / TR (%) |")
    assert md[2] == "| ORCA | 49.0 [44.6, 53.4] | 10.0 / 5.0 / 36.0 | 60.0 [55.6, 64.2] | +11.0 | 10.0 / 20.0 / 10.0 |"
    # two seeds: mean ± population std, the interval over both seeds' episodes (50 + 210 of 400)
    assert md[3] == "| PDPO | 60.0 ± 10.0 [60.2, 69.5] | 10.0 / 5.0 / 25.0 | 50.0 ± 10.0 [50.1, 59.8] | -10.0 | 10.0 / 5.0 / 35.0 |"
    assert generalization_markdown(rows, bounded=False).splitlines()[2] == \
        "| ORCA | 49.0 [44.6, 53.4] | 10.0 / 36.0 | 60.0 [55.6, 64.2] | +11.0 | 10.0 / 10.0 |"
    check_crowds([], allow_empty=True)
    for bad in (["orca", "calm"], ["orca", "orca"], []):
        with pytest.raises(ValueError, match="--crowds must list distinct crowds among orca, reactive_orca"):
            check_crowds(bad)


def check_selection(root: Path, task: str, select_dir: str, model: Path, evaluation: str, run: str) -> None:
    """The main job's checkpoint choice (``select/<select_dir>``): every candidate evaluated on the
    validation seeds, the best of them shipped in ``model``, evaluated on the test seeds and named
    on the card."""
    sel = json.loads((root / "select" / select_dir / "selected.json").read_text())
    assert (sel["episodes"], sel["split"], sel["chosen"]) == (2, "val", max(
        sel["candidates"], key=lambda r: (r["val_success_rate"], -r["env_steps"])))
    for r in sel["candidates"]:
        m = json.loads((root / "select" / select_dir / f"{r['env_steps']:09d}" / "metrics.json").read_text())
        assert (m["split"], m["n_episodes"], m["sr"]) == ("val", 2, r["val_success_rate"])
    chosen = Path(sel["chosen"]["policy"])
    assert (model / "model.safetensors").read_bytes() == (chosen / "model.safetensors").read_bytes()
    assert f"--policy.path={chosen}" in json.loads((root / "commands.json").read_text())[f"eval {task} {evaluation}"]
    assert f"- Checkpoint: the one at {sel['chosen']['env_steps']:,} env steps of {run}" in (model / "README.md").read_text()


@pytest.fixture(scope="module")
def tiny_main(tmp_path_factory) -> Path:
    """The output_root of an uninterrupted tiny main job."""
    out = tmp_path_factory.mktemp("main")
    pipeline_main(fi.main_argv(out))
    return out


def test_main_job_runs_end_to_end_in_a_tiny_configuration(tiny_main):
    argv = fi.main_argv(tiny_main)
    root = tiny_main / "tiny"
    report = (root / "report.md").read_text()
    for section in ("## Budget", "## Bounded CrowdNav", "## original CrowdNav", "### Boundary audit", "### Wall audit (Bounded)",
                    "## Parameter counts", "## Figures", "## Stages", "## Reproduce"):
        assert section in report, section
    methods = ["ORCA (look-ahead)", "ORCA (current-state)", "straight", "PDPO pretrained only (H = 5, BC)", "PDPO w/o action chunk (H = 1, fine-tuned)",
               "PDPO (H = 5, fine-tuned)", "CrowdNav++ (Const. Vel.)"]
    for name in ("results_bounded.csv", "results_original.csv", "boundary_audit.csv", "wall_audit.csv"):
        rows = list(csv.DictReader(io.StringIO((root / "tables" / name).read_text())))
        assert [r["method"] for r in rows] == methods, name
    for label in methods:
        assert f"| {label} | " in report
    assert (root / "tables" / "parameters.csv").read_text().count("\n") == 1 + 4  # 2 tasks x 2 fine-tuned policies
    for task in ("bounded", "original"):
        for fig in ("storyboard.png", "multimodality.png", "finetune_curves.png"):
            assert (root / "figures" / task / fig).stat().st_size > 5_000
        assert list((root / "eval" / task / "orca" / "videos").glob("*.gif"))
        # both ORCA robots: the preset's (paper: look-ahead) and the recipes' demonstrator
        for name, robot in (("orca", "look_ahead"), ("orca_current_state", "current_state")):
            assert json.loads((root / "eval" / task / name / "metrics.json").read_text())["env"]["orca_robot"] == robot
        model = root / "hub" / "models" / "local" / f"pdpo_{task}_h5"
        assert (model / "model.safetensors").exists() and (model / "learning_curve.png").stat().st_size > 5_000
        card = (model / "README.md").read_text()
        assert "![diffusion-PPO learning curve](learning_curve.png)" in card
        # the reproduce line is the command typed, less the folder of this machine it wrote to
        assert portable(" ".join(["lerobot-crowdnav-main", *argv])) in card and f"--output_root={tiny_main}" not in card
        assert re.search(rf"\| finetune {task} H=5 seed=1000 \| [\d.]+ \| [\d.]+ \| \d \|", card)  # wall, CPU, cores
        assert re.search(r"\| total \| [\d.]+ \| [\d.]+ \| \|", card)  # every stage's CPU time measured
        assert f"| finetune2 {task} H=5 seed=1000 | " in card and "- It continued a fine-tuned checkpoint: " in card
        # the policy is the checkpoint chosen on the validation seeds (tiny.yaml: select_top 2, 2 episodes)
        check_selection(root, task, f"{task}_h5_s1000", model, "pdpo_ft_h5_s1000", "the last fine-tuning stage")
        assert f"| select {task} H=5 seed=1000 | " in card
        stages_curve = root / "finetune" / f"{task}_h5_s1000_stage2" / "training_curves_stages.png"
        assert (model / "learning_curve.png").read_bytes() == stages_curve.read_bytes()  # both stages on one axis
        # the shipped policy is stage 2's: it continued stage 1's last checkpoint with its own flags and seeds
        stage2, first = (json.loads((model / name).read_text()) for name in ("finetune_config.json", "source_finetune_config.json"))
        assert stage2["policy"]["path"] == str(root / "finetune" / f"{task}_h5_s1000" / "checkpoints" / "last" / "pretrained_model")
        assert (stage2["ppo"]["update_epochs"], first["ppo"]["update_epochs"]) == (3, 5)
        assert (stage2["seed"], stage2["env_seed"]) == (1001, 520_000_000)
        last = root / "finetune" / f"{task}_h5_s1000_stage2" / "checkpoints" / "last" / "pretrained_model"
        assert json.loads((last / "finetune_config.json").read_text())["env_steps_done"] == 128
        assert (root / "hub" / "datasets" / "local" / f"crowdnav_orca_{task}" / "meta" / "info.json").exists()
        baseline = root / "hub" / "models" / "local" / f"crowdnavpp_{task}"
        assert json.loads((baseline / "config.json").read_text())["type"] == "crowdnavpp"
        assert (baseline / "learning_curve.png").stat().st_size > 5_000
        assert f"| train crowdnavpp {task} seed=1000 | " in (baseline / "README.md").read_text()
        # CrowdNav++'s checkpoint is chosen on the validation seeds as PDPO's is
        check_selection(root, task, f"crowdnavpp_{task}_s1000", baseline, "crowdnavpp_s1000", "the PPO run")
        assert f"| select crowdnavpp {task} seed=1000 | " in (baseline / "README.md").read_text()
        assert "Where `" not in card  # every stage ran on the CPU: the machine line says it all
    commands = json.loads((root / "commands.json").read_text())
    assert commands["pretrain bounded H=5 seed=1000"][0] == "lerobot-train"
    assert commands["train crowdnavpp original seed=1000"][:2] == ["lerobot-crowdnav-train-ppo", "--policy.type=crowdnavpp"]
    assert "trained from scratch by `lerobot-crowdnav-train-ppo" in report
    assert "| CrowdNav++ PPO from scratch per task | 240 env steps |" in report
    assert "| 256 env steps, then 128 more from its last checkpoint (stage 2) |" in report
    assert commands["finetune2 original H=1 seed=1000"][0] == "lerobot-crowdnav-finetune"
    # stage 2 on stage 1's axes: from the end of stage 1 in env steps and in wall time
    cfg = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml", args=[f"--output_root={tiny_main}"])
    records = Training(cfg).finetune_records("BoundedCrowdNav-v0", 5, 1000, "PDPO")
    first, second = records["PDPO, stage 1"], records["PDPO, stage 2"]
    last = root / "finetune" / "bounded_h5_s1000" / "checkpoints" / "last" / "pretrained_model" / "finetune_config.json"
    start = json.loads(last.read_text())["env_steps_done"]
    assert start == max(r["env_steps"] for r in first)
    stage2 = (root / "finetune" / "bounded_h5_s1000_stage2" / "progress.jsonl").read_text().splitlines()
    assert [r["env_steps"] for r in second] == [start + json.loads(line)["env_steps"] for line in stage2]
    assert second[0]["time/wall_s"] == max(r.get("time/wall_s") or 0 for r in first) < second[-1]["time/wall_s"]
    tables = {p.name: p.read_text() for p in (root / "tables").iterdir()}

    # A rerun skips every stage; re-evaluating the saved checkpoints gives identical tables.
    shutil.rmtree(root / "eval" / "bounded" / "pdpo_ft_h5_s1000")
    pipeline_main(argv)
    assert {p.name: p.read_text() for p in (root / "tables").iterdir()} == tables
    rerun = (root / "report.md").read_text()
    assert "| pretrain bounded H=5 seed=1000 |" in rerun and "skipped (complete)" in rerun
    evaluated = {p: p.stat().st_mtime_ns for p in (root / "eval").rglob("metrics.json")}
    pipeline_main(argv + ["--rerun_eval=true"])  # every row evaluated again, to the same tables
    assert all(p.stat().st_mtime_ns != t for p, t in evaluated.items()) and len(evaluated) >= 14
    assert {p.name: p.read_text() for p in (root / "tables").iterdir()} == tables

    # Another preset does not take the finished demonstrations: the resume they get refuses it.
    datasets = {p: p.read_bytes() for p in (root / "datasets").rglob("*") if p.is_file()}
    with pytest.raises(SystemExit, match="different settings than the existing collection"):
        pipeline_main(argv + ["--preset=crowdnavpp"])
    assert {p: p.read_bytes() for p in (root / "datasets").rglob("*") if p.is_file()} == datasets
    pipeline_main(argv)  # the run as it was


def test_provenance_names_the_checkpoint_a_row_was_evaluated_from(tmp_path):
    """The trainer's ``best`` (with best.json) or a numbered checkpoint the main job chose."""
    from lerobot_crowdnav.evaluation.report import Evaluated, Stage, _provenance

    best = tmp_path / "checkpoints" / "best" / "pretrained_model"
    chosen = tmp_path / "checkpoints" / "001200128" / "pretrained_model"
    for path in (best, chosen):
        path.mkdir(parents=True)
    (best.parent / "best.json").write_text(json.dumps({"env_steps": 2002944, "val/success_rate": 0.75}))
    stages = dict(evaluate=Stage("eval", ["lerobot-crowdnav-eval"]), pretrain=Stage("pretrain", ["lerobot-train"]),
                  finetune=Stage("finetune", ["lerobot-crowdnav-finetune"]))

    def lines(checkpoint):
        return _provenance(Evaluated("pdpo", tmp_path, checkpoint=checkpoint, **stages), "PDPO", lambda st: st.argv[0])

    assert lines(best)[-1].endswith("checkpoint `best` = 2,002,944 env steps (validation SR 75 %)")
    assert lines(chosen)[-1].endswith("checkpoint at 1,200,128 env steps, chosen on the validation seeds (the run's select stage)")


def test_select_candidates_are_the_best_read_saved_checkpoints(tmp_path):
    """Readings without a saved checkpoint are not candidates, ``best`` is one wherever it was
    saved, ties go to the earlier checkpoint, and a reading logged twice (a resumed run) counts once."""
    from lerobot_crowdnav.main.training import select_candidates

    readings = {0: 0.70, 100: 0.74, 200: 0.76, 300: 0.74, 400: 0.80, 500: 0.74, 600: 0.72}
    lines = [{"env_steps": s, "val/success_rate": r} for s, r in readings.items()] + [{"env_steps": 150, "loss": 1.0}]
    (tmp_path / "progress.jsonl").write_text("\n".join(json.dumps(x) for x in [*lines, lines[3]]))
    for steps in (100, 300, 500, 600, 700):  # 400 (the best reading) was never saved under its number
        (tmp_path / "checkpoints" / f"{steps:09d}" / "pretrained_model").mkdir(parents=True)
    (tmp_path / "checkpoints" / "best" / "pretrained_model").mkdir(parents=True)
    (tmp_path / "checkpoints" / "best" / "best.json").write_text(json.dumps({"env_steps": 400}))
    got = select_candidates(tmp_path, 3)
    assert [(s, r) for s, r, _ in got] == [(400, 0.80), (100, 0.74), (300, 0.74)]
    assert got[0][2] == tmp_path / "checkpoints" / "best" / "pretrained_model"
    assert got[1][2] == tmp_path / "checkpoints" / "000000100" / "pretrained_model"
    assert [s for s, _, _ in select_candidates(tmp_path, 10)] == [400, 100, 300, 500, 600]


def test_a_card_says_where_a_stage_moved_to_a_gpu_ran(tiny_main):
    """A fine-tuning run moved to a lent GPU and back: the card splits its env steps and training
    time by device, from the trainer's records (here the first of its two iterations relabelled)."""
    cfg = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml", args=[f"--output_root={tiny_main}"])
    job = Training(cfg)
    progress = tiny_main / "tiny" / "finetune" / "bounded_h5_s1000" / "progress.jsonl"
    card = tiny_main / "tiny" / "hub" / "models" / "local" / "pdpo_bounded_h5" / "README.md"
    before, kept = progress.read_text(), {p: p.read_text() for p in card.parent.parent.glob("*/README.md")}
    records = [json.loads(line) for line in before.splitlines()]
    records[1]["device"] = "cuda: NVIDIA H100 80GB HBM3"
    progress.write_text("".join(json.dumps(r) + "\n" for r in records))
    try:
        job.push("BoundedCrowdNav-v0")
        lines = [line for line in card.read_text().splitlines() if line.startswith("Where `")]
        gpu_steps, gpu_s = records[1]["env_steps"], records[1]["time/wall_s"]
        cpu_steps, cpu_s = records[-1]["env_steps"] - gpu_steps, records[-1]["time/wall_s"] - gpu_s
        assert lines == [f"Where `finetune bounded H=5 seed=1000` ran (its trainer's records): {gpu_steps:,} env steps "
                         f"in {gpu_s / 60:.1f} min on NVIDIA H100 80GB HBM3; {cpu_steps:,} env steps in {cpu_s / 60:.1f} "
                         f"min on the CPU."]
    finally:  # the fixture's run as it was, for the tests after this one
        progress.write_text(before)
        for path, text in kept.items():  # the push rewrote every card of the task
            path.write_text(text)


def test_the_checkpoint_choice_is_made_again_when_its_settings_change(tiny_main, tmp_path):
    """selected.json records what it was made from (top, episodes, the stage's env steps): the
    same settings skip the stage, others choose again, reusing the candidates' evaluations."""
    shutil.copytree(tiny_main / "tiny", tmp_path / "tiny", symlinks=True)

    def select(*args: str):
        cfg = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml",
                            args=[f"--output_root={tmp_path}", *args])
        training = Training(cfg)
        stage = training.select("BoundedCrowdNav-v0", 5, 1000)
        return stage, json.loads(training.paths.selected_file("BoundedCrowdNav-v0", 5, 1000).read_text())

    stage, before = select()
    assert stage.wall_time_s is None and (before["top"], before["episodes"]) == (2, 2)
    evaluated = {p: p.stat().st_mtime_ns for p in (tmp_path / "tiny" / "select").rglob("metrics.json")}
    stage, after = select("--select_top=1")
    assert stage.wall_time_s is not None and after["top"] == 1
    def scores(rows):
        return [(r["env_steps"], r["reading"], r["val_success_rate"]) for r in rows]

    assert scores(after["candidates"]) == scores(before["candidates"][:1]) == scores([after["chosen"]])
    assert {p: p.stat().st_mtime_ns for p in evaluated} == evaluated  # nothing evaluated again
    # The run removed and redone to the same budget: other weights at the same paths (here: other
    # config bytes), so the choice is made again and the changed candidate evaluated again.
    chosen = Path(after["chosen"]["policy"])
    last = tmp_path / "tiny" / "finetune" / "bounded_h5_s1000_stage2" / "checkpoints" / "last" / "pretrained_model"
    for model in {chosen.resolve(), last.resolve()}:
        with open(model / "config.json", "a") as f:
            f.write(" ")
    stage, again = select("--select_top=1")
    assert stage.wall_time_s is not None and again["last_digest"] != after["last_digest"]
    metrics = tmp_path / "tiny" / "select" / "bounded_h5_s1000" / f"{after['chosen']['env_steps']:09d}" / "metrics.json"
    assert metrics.stat().st_mtime_ns != evaluated[metrics]


def test_stage2_refuses_to_resume_from_another_checkpoint_of_stage1(tiny_main, tmp_path):
    """Stage 2 continued stage 1's ``last``: a config asking for ``best`` is refused with the way
    out, before anything runs, whether stage 2 would resume (a longer budget) or is done; a bad
    value is refused at validation."""
    shutil.copytree(tiny_main / "tiny", tmp_path / "tiny", symlinks=True)
    stage2 = tmp_path / "tiny" / "finetune" / "bounded_h5_s1000_stage2"
    before = sorted(p.name for p in (stage2 / "checkpoints").iterdir())
    cfg = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml",
                        args=[f"--output_root={tmp_path}", "--ft2_from=best", "--ft2_env_steps=1024"])
    with pytest.raises(ValueError, match="continued stage 1's `last` checkpoint, this config asks for `best`"):
        Training(cfg).finetune("BoundedCrowdNav-v0", 5, 1000, stage=2)
    done = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml",
                         args=[f"--output_root={tmp_path}", "--ft2_from=best"])
    with pytest.raises(ValueError, match="or pass --ft2_from=last to go on with it as it started"):
        Training(done).finetune("BoundedCrowdNav-v0", 5, 1000, stage=2)
    assert sorted(p.name for p in (stage2 / "checkpoints").iterdir()) == before
    bad = draccus.parse(MainConfig, config_path=fi.ROOT / "configs/main/tiny.yaml", args=["--ft2_from=middle"])
    with pytest.raises(ValueError, match="--ft2_from must be 'best' or 'last'"):
        bad.validate()


def test_main_job_evaluates_shipped_models_without_training(tiny_main, tmp_path):
    """The default mode: model directories in, tables out. A shipped copy of a trained policy gets
    exactly the metrics its training run measured; a missing model is named, not a crash."""
    shipped = tmp_path / "models"
    shutil.copytree(tiny_main / "tiny" / "hub" / "models" / "local", shipped)
    shutil.rmtree(shipped / "pdpo_original_h1")
    shutil.rmtree(shipped / "crowdnavpp_bounded")
    out = tmp_path / "out"
    # the trained crowd only (shipped models under other crowds: test_shipped_models_under_other_crowds_*)
    pipeline_main([f"--models={shipped}", f"--output_root={out}", "--run=shipped", "--test_episodes=4",
                   "--figure_steps=[0,2]", "--figure_samples=4", "--crowds=[orca]"])
    root = out / "shipped"
    assert sorted(p.name for p in root.iterdir()) == ["commands.json", "eval", "figures", "main_config.json", "report.md",
                                                       "stage_cpu.json", "stage_times.json", "tables"]  # nothing trained, nothing pushed
    report = (root / "report.md").read_text()
    assert "## Policies" in report and "## Budget" not in report and "### Boundary audit" in report
    assert "Not shipped yet (no row): `crowdnavpp_bounded`." in report
    assert "Not shipped yet (no row): `pdpo_original_h1`." in report
    orca = ["ORCA (look-ahead)", "ORCA (current-state)", "straight"]
    methods = {"bounded": [*orca, "PDPO w/o action chunk (H = 1, fine-tuned)", "PDPO (H = 5, fine-tuned)"],
               "original": [*orca, "PDPO (H = 5, fine-tuned)", "CrowdNav++ (Const. Vel.)"]}
    for task, labels in methods.items():
        rows = list(csv.DictReader(io.StringIO((root / "tables" / f"results_{task}.csv").read_text())))
        assert [r["method"] for r in rows] == labels
        for fig in ("storyboard.png", "multimodality.png", "curve_pdpo_" + task + "_h5.png"):
            assert (root / "figures" / task / fig).stat().st_size > 5_000
        pairs = [("pdpo_ft_h5_s1000", f"pdpo_{task}_h5"), ("orca", "orca")]
        for trained, copy in pairs + ([("crowdnavpp_s1000", "crowdnavpp_original")] if task == "original" else []):
            a, b = (json.loads((d / "eval" / task / name / "metrics.json").read_text())
                    for d, name in ((tiny_main / "tiny", trained), (root, copy)))
            keys = ["sr", "cr", "nt", "pl", "itr", "sd", "oob", "mean_return", "n_episodes"]
            assert [a[k] for k in keys] == [b[k] for k in keys]
    assert (root / "tables" / "parameters.csv").read_text().count("\n") == 1 + 3
    # A model replaced in place is evaluated again on a rerun (no stale row), and one in the wrong
    # slot is refused: here Bounded H = 5 becomes the original-benchmark policy.
    before = (root / "tables" / "results_bounded.csv").read_text()
    shutil.rmtree(shipped / "pdpo_bounded_h5")
    shutil.copytree(shipped / "pdpo_original_h5", shipped / "pdpo_bounded_h5")
    argv = [f"--models={shipped}", f"--output_root={out}", "--run=shipped", "--test_episodes=4", "--figure_steps=[0,2]",
            "--figure_samples=4", "--tasks=[BoundedCrowdNav-v0]", "--crowds=[orca]"]
    pipeline_main(argv)
    after = {r["method"]: r for r in csv.DictReader(io.StringIO((root / "tables" / "results_bounded.csv").read_text()))}
    old = {r["method"]: r for r in csv.DictReader(io.StringIO(before))}
    assert after["PDPO (H = 5, fine-tuned)"] != old["PDPO (H = 5, fine-tuned)"]
    assert after["ORCA (look-ahead)"] == old["ORCA (look-ahead)"]
    shutil.rmtree(shipped / "pdpo_bounded_h1")
    shutil.copytree(shipped / "pdpo_original_h5", shipped / "pdpo_bounded_h1")
    with pytest.raises(SystemExit, match="H = 5: its row"):
        pipeline_main(argv)


def test_main_job_killed_mid_stage_reruns_to_the_same_tables(tiny_main, tmp_path):
    """A run whose Bounded H = 5 policy is still to make, killed writing its first fine-tuning
    checkpoint (no last yet: the rerun restarts that stage with --resume=true): the rerun skips the
    complete stages, makes that policy (fine-tuning, choice, evaluations, push), and its tables and
    weights equal the uninterrupted run's. The whole job killed at more points:
    tests/fault_injection.py (as a script)."""
    run = tmp_path / "tiny"
    shutil.copytree(tiny_main / "tiny", run, symlinks=True)
    for rel in ("finetune/bounded_h5_s1000", "finetune/bounded_h5_s1000_stage2", "select/bounded_h5_s1000",
                "eval/bounded/pdpo_ft_h5_s1000", "eval/bounded/pdpo_ft_h5_s1000_reactive_social_force",
                "hub/models/local/pdpo_bounded_h5", "tables"):
        shutil.rmtree(run / rel)
    fi.run_killed(["-m", "lerobot_crowdnav.pipeline", *fi.main_argv(tmp_path)], "finetune.checkpoint_writing", 1)
    assert (run / "finetune/bounded_h5_s1000").is_dir() and not (run / "finetune/bounded_h5_s1000/checkpoints/last").exists()
    pipeline_main(fi.main_argv(tmp_path))
    assert fi.report_tables(tmp_path) == fi.report_tables(tiny_main)
    weights = "hub/models/local/pdpo_bounded_h5/model.safetensors"
    assert (run / weights).read_bytes() == (tiny_main / "tiny" / weights).read_bytes()


CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("path", sorted([*(CONFIGS / "main").glob("*.yaml"), *(CONFIGS / "recipes").glob("*.yaml")]),
                         ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_main_and_recipe_configs_parse_and_their_flags_do_too(path):
    """Every main-job config validates, and its bc_args / ft_args are flags that lerobot-train's
    PDPO config and lerobot-crowdnav-finetune accept, and its crowdnavpp_args lerobot-crowdnav-train-ppo."""
    import draccus
    from lerobot_policy_pdpo import PDPOConfig

    from lerobot_crowdnav.rl.finetune import FinetuneConfig
    from lerobot_crowdnav.rl.train_ppo import TrainPPOConfig

    cfg = draccus.parse(MainConfig, config_path=str(path), args=[])
    cfg.validate()
    draccus.parse(TrainPPOConfig, args=list(cfg.crowdnavpp_args)).validate()
    if path.parent.name == "recipes":
        assert cfg.run == path.stem and len(cfg.tasks) == 1 and cfg.test_episodes == 500
        assert (len(cfg.horizons), cfg.crowdnavpp_env_steps > 0) in ((1, False), (0, True))  # one policy each
        assert f"configs/recipes/{path.name}" in path.read_text()  # its own command in the header
    assert all(f.startswith("--policy.") for f in cfg.bc_args), "bc_args: only policy flags are recipe settings"
    draccus.parse(PDPOConfig, args=[f"--{f.removeprefix('--policy.')}" for f in cfg.bc_args])
    draccus.parse(FinetuneConfig, args=[*cfg.ft_args, *cfg.ft2_args]).ppo.validate()
    Training(cfg).check_finetune_commands()  # each fine-tuning stage's whole command, as the job checks it first


def test_a_fine_tuning_setting_the_trainer_refuses_fails_before_anything_runs(tmp_path):
    """--ft_num_envs=4 gives 256 env steps an iteration, fewer than the 500 of a PPO batch: the
    fine-tuning refuses it, and the main job says so at once, not after collection and BC."""
    import draccus

    from lerobot_crowdnav.pipeline import Pipeline

    cfg = draccus.parse(MainConfig, config_path=str(CONFIGS / "recipes" / "bounded_pdpo_h5.yaml"),
                        args=[f"--output_root={tmp_path}", "--ft_num_envs=4"])
    with pytest.raises(ValueError, match=r"finetune bounded H=5 seed=1000: an iteration has 256 env steps"):
        Pipeline(cfg)
    assert not list(tmp_path.iterdir())  # nothing written


# -- the generalization table (--crowds) ---------------------------------------------------------
def _stage_rows(report: str) -> dict[str, str]:
    """The report's Stages table: stage name -> its wall-time cell."""
    table = report.split("## Stages\n", 1)[1].split("\n## ", 1)[0]
    return {cells[1].strip(): cells[3].strip() for line in table.splitlines()[3:] if (cells := line.split("|"))[1:]}


def _without_generalization(report: str) -> str:
    """The report less its wall times (the first line's, and the stages that run every time, such as
    the policy pushes), the generalization tables and their stages."""
    lines = [re.sub(r"\| \d+ s \|$", "| ... |", line) for line in report.splitlines()
             if not line.startswith("Machine: ") and not (line.startswith("| eval ") and " crowd=" in line)]
    return re.sub(r"### Generalization: crowds it was not trained in\n.*?\n(?=## )", "", "\n".join(lines), flags=re.S)


def test_main_job_generalization_table_resumes_and_crowds_off_is_the_report_before(tiny_main):
    """tiny.yaml's --crowds=[orca,reactive_social_force]: every row of each results table again
    under the other crowd, in its own stage and directory (the trained crowd's are unchanged);
    the report's table is its CSV's; a rerun evaluates nothing again; --crowds=[] gives the
    report without the tables (nor their CSVs), the rest as it was; a bad crowd is one error line."""
    from lerobot_crowdnav.evaluation.generalization import generalization_markdown, read_csv

    argv = fi.main_argv(tiny_main)
    root = tiny_main / "tiny"
    pipeline_main(argv)  # complete whatever the tests before left
    report = (root / "report.md").read_text()
    assert report.count("### Generalization: crowds it was not trained in") == 2
    names = ["orca", "orca_current_state", "straight", "pdpo_bc_h5_s1000", "pdpo_ft_h1_s1000", "pdpo_ft_h5_s1000", "crowdnavpp_s1000"]
    for short, bounded in (("bounded", True), ("original", False)):
        results = {r["method"]: r for r in csv.DictReader(io.StringIO((root / "tables" / f"results_{short}.csv").read_text()))}
        rows = read_csv((root / "tables" / f"generalization_{short}.csv").read_text())
        assert [(r["method"], r["crowd"]) for r in rows] == [(m, c) for m in results for c in ("orca", "reactive_social_force")]
        assert f"\n{generalization_markdown(rows, bounded)}\n" in report
        for r in rows:
            if r["crowd"] == "orca":  # the trained crowd: the results table's own row
                assert (r["SR_mean"], r["SR95_low"], r["SR_change"]) == (results[r["method"]]["SR_mean"],
                                                                        results[r["method"]]["SR95_low"], "")
            else:
                assert r["SR_change"] != "" and r["n_episodes"] == "4"
        for name in names:
            env = json.loads((root / "eval" / short / f"{name}_reactive_social_force" / "metrics.json").read_text())["env"]
            assert (env["robot_visible"], env["human_policy"]) == (True, "social_force")
            env = json.loads((root / "eval" / short / name / "metrics.json").read_text())["env"]
            assert (env["robot_visible"], env["human_policy"]) == (False, "orca")
    stages = _stage_rows(report)
    crowd_stages = [name for name in stages if name.endswith(" crowd=reactive_social_force")]
    assert len(crowd_stages) == 2 * len(names) and all(stages[name] == "skipped (complete)" for name in crowd_stages)
    commands = json.loads((root / "commands.json").read_text())
    assert commands["eval bounded orca crowd=reactive_social_force"][4:6] == ["--env.robot_visible=true",
                                                                            "--env.human_policy=social_force"]
    assert commands["eval bounded orca"] == [  # the trained crowd's stage as it was
        "lerobot-crowdnav-eval", "--policy.type=orca", "--env.task=BoundedCrowdNav-v0", "--env.preset=paper",
        "--eval.n_episodes=4", "--eval.split=test", "--eval.batch_size=4", "--eval.n_videos=1",
        f"--output_dir={root / 'eval' / 'bounded' / 'orca'}", "--overwrite=true"]
    tables = {p.name: p.read_text() for p in (root / "tables").iterdir()}

    pipeline_main([*argv, "--crowds=[]"])
    before = (root / "report.md").read_text()
    assert "Generalization" not in before and " crowd=" not in before
    assert {p.name: p.read_text() for p in (root / "tables").iterdir()} == {
        name: text for name, text in tables.items() if not name.startswith("generalization_")}
    assert _without_generalization(report) == _without_generalization(before)
    pipeline_main(argv)  # and back: nothing evaluated again, the same tables
    assert {p.name: p.read_text() for p in (root / "tables").iterdir()} == tables
    assert all(time == "skipped (complete)" for name, time in _stage_rows((root / "report.md").read_text()).items()
               if name.startswith("eval "))
    with pytest.raises(SystemExit) as error:
        pipeline_main([*argv, "--crowds=[orca,calm]"])
    message = str(error.value)
    assert "\n" not in message and "--crowds" in message and "calm" in message and "reactive_orca" in message


def test_shipped_models_under_other_crowds_rerun_only_when_the_model_changes(tiny_main, tmp_path):
    """With shipped models the trained crowd's evaluation always runs (as before); another crowd's
    runs again only when the model directory's files changed (copies keep their mtime: a digest)."""
    shipped = tmp_path / "models"
    shutil.copytree(tiny_main / "tiny" / "hub" / "models" / "local", shipped)
    argv = [f"--models={shipped}", f"--output_root={tmp_path / 'out'}", "--run=shipped", "--test_episodes=2",
            "--figure_steps=[0]", "--figure_samples=2", "--tasks=[CrowdNav-v0]", "--crowds=[orca,social_force]"]
    pipeline_main(argv)
    root = tmp_path / "out" / "shipped"
    digest = root / "eval" / "original" / "pdpo_original_h5_social_force" / "policy.sha256"
    first = digest.read_text()
    pipeline_main(argv)
    stages = _stage_rows((root / "report.md").read_text())
    assert stages["eval original pdpo_original_h5"] != "skipped (complete)"
    assert stages["eval original pdpo_original_h5 crowd=social_force"] == "skipped (complete)"
    shutil.rmtree(shipped / "pdpo_original_h5")
    shutil.copytree(shipped / "pdpo_bounded_h5", shipped / "pdpo_original_h5")  # another H = 5 policy, same mtimes
    pipeline_main(argv)
    stages = _stage_rows((root / "report.md").read_text())
    assert stages["eval original pdpo_original_h5 crowd=social_force"] != "skipped (complete)"
    assert stages["eval original orca crowd=social_force"] == "skipped (complete)"
    assert digest.read_text() != first
