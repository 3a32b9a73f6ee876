"""Each contract has one home, and where two parts must agree a test says so: the checkpoint file
names (``checkpoint_files.py``: lerobot's and Hugging Face's own names, no literal elsewhere), the
learners' blocks of train seeds (``sim/config.py``: apart, inside the train split, no literal
elsewhere), and the documentation's links (inside the repository or to public references; no
path of the machine a run was made on)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lerobot_crowdnav import checkpoint_files
from lerobot_crowdnav.sim.config import (DAGGER_ROUND_SEEDS, DAGGER_SEED_BASE, PPO_ENV_SEED, PPO_PROCESS_SEEDS,
                                         PPO_STAGE2_ENV_SEED, SEED_SPLITS)

ROOT = Path(__file__).parents[1]
CODE = [*ROOT.glob("lerobot_crowdnav/**/*.py"), *ROOT.glob("policies/*/*/*.py"), *ROOT.glob("plugins/*/*/*.py"),
        *ROOT.glob("scripts/*.py"), *ROOT.glob("datasets_scripts/*.py")]
FILE_NAMES = {value for name, value in vars(checkpoint_files).items() if name.isupper() and isinstance(value, str)}


def sources() -> dict[str, str]:
    return {path.relative_to(ROOT).as_posix(): path.read_text() for path in CODE}


def constants(source: str, kind: type) -> list[tuple[int, object]]:
    return [(n.lineno, n.value) for n in ast.walk(ast.parse(source))
            if isinstance(n, ast.Constant) and type(n.value) is kind]


def test_the_lerobot_and_hub_file_names_are_the_libraries_own():
    from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE
    from lerobot.configs.train import TRAIN_CONFIG_NAME
    from lerobot.utils import constants

    cf = checkpoint_files
    assert (cf.POLICY_CONFIG, cf.WEIGHTS, cf.TRAIN_CONFIG) == (CONFIG_NAME, SAFETENSORS_SINGLE_FILE, TRAIN_CONFIG_NAME)
    assert (cf.PRETRAINED_MODEL, cf.TRAINING_STATE, cf.TRAINING_STEP) == \
        (constants.PRETRAINED_MODEL_DIR, constants.TRAINING_STATE_DIR, constants.TRAINING_STEP)


def new_literal_file_names(code: dict[str, str]) -> dict[str, set[str]]:
    """The checkpoint file names typed as literals outside checkpoint_files.py."""
    found: dict[str, set[str]] = {}
    for rel, source in code.items():
        if rel != "lerobot_crowdnav/checkpoint_files.py":
            names = {value for _, value in constants(source, str) if value in FILE_NAMES}
            if names:
                found[rel] = names
    return found


def test_checkpoint_file_names_are_typed_in_one_place():
    assert new_literal_file_names(sources()) == {}, "read them from checkpoint_files.py"


def test_the_file_name_check_fails_on_a_literal():
    code = {**sources(), "lerobot_crowdnav/rl/dppo.py": 'X = Path("run") / "critic.safetensors"\n',
            "lerobot_crowdnav/main/sources.py": 'X = "best.json"\nY = f"{path / \'config.json\'}"\n'}
    assert new_literal_file_names(code) == {"lerobot_crowdnav/rl/dppo.py": {"critic.safetensors"},
                                            "lerobot_crowdnav/main/sources.py": {"best.json", "config.json"}}


def test_the_learners_seed_blocks_lie_apart_inside_the_train_split():
    from lerobot_crowdnav.data.dagger import DaggerConfig
    from lerobot_crowdnav.rl.trainer import PPORunConfig

    lo, hi = SEED_SPLITS["train"]
    blocks = sorted([
        (0, 1_000_000),  # demonstrations: collect_orca.py walks the train seeds from --seed=0
        (PPO_ENV_SEED, PPO_ENV_SEED + 2 * PPO_PROCESS_SEEDS),  # a PPO run of up to 2 processes
        (PPO_STAGE2_ENV_SEED, PPO_STAGE2_ENV_SEED + PPO_PROCESS_SEEDS),  # the main job's second stage
        (DAGGER_SEED_BASE + DaggerConfig().round * DAGGER_ROUND_SEEDS, hi),  # DAgger rounds 1, 2, ...
    ])
    assert lo <= blocks[0][0] and blocks[-1][1] <= hi
    assert all(a[1] <= b[0] for a, b in zip(blocks, blocks[1:])), blocks
    assert PPORunConfig().env_seed == PPO_ENV_SEED
    for split in ("val", "test", "holdout"):
        assert SEED_SPLITS[split][0] >= hi


def literal_seed_blocks(code: dict[str, str]) -> list[tuple[str, int, int]]:
    starts = {PPO_ENV_SEED, PPO_STAGE2_ENV_SEED, DAGGER_SEED_BASE, *(v for span in SEED_SPLITS.values() for v in span)}
    starts.discard(0)
    return [(rel, line, value) for rel, source in code.items() if rel != "lerobot_crowdnav/sim/config.py"
            for line, value in constants(source, int) if value in starts]


def test_seed_blocks_are_typed_in_one_place():
    assert literal_seed_blocks(sources()) == [], "read them from sim/config.py"
    assert literal_seed_blocks({"scripts/x.py": "env.reset(seed=2_000_000_000)\n"}) == [("scripts/x.py", 1, 2_000_000_000)]


# -- the documentation's links ----------------------------------------------------------------------
DOCS = [ROOT / "README.md", *ROOT.glob("docs/*.md"), *ROOT.glob("models/*/*/README.md"), *ROOT.glob("policies/*/README.md"),
        *ROOT.glob("plugins/*/README.md"), *ROOT.glob("configs/**/*.yaml")]
MACHINE_PATH = re.compile(r"(?<![\w.])(/work/|/home/|/Users/|/mnt/|shared/spec|\.\./shared/)")


def link_problems(path: Path, text: str) -> list[str]:
    problems = [f"{path.name}: machine path {m.group(0)!r}" for m in MACHINE_PATH.finditer(text)]
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            if not target.startswith("https://") or re.match(r"https://(localhost|127\.|10\.|192\.168\.)", target):
                problems.append(f"{path.name}: {target} is not a public reference")
        elif target.split("#")[0] and not (path.parent / target.split("#")[0]).resolve().is_relative_to(ROOT):
            problems.append(f"{path.name}: {target} leaves the repository")
        elif target.split("#")[0] and not (path.parent / target.split("#")[0]).exists():
            problems.append(f"{path.name}: {target} does not exist")
    return problems


def test_no_link_leaves_the_repository_but_to_public_references():
    assert len(DOCS) > 20
    assert [p for path in DOCS for p in link_problems(path, path.read_text())] == []


@pytest.mark.parametrize("text", ["see [the spec](../shared/spec/env.md)", "[log](/work/runs/x/log.md)",
                                  "[run](http://localhost:8000/)", "[gone](docs/nowhere.md)", "data in /home/me/runs"])
def test_the_link_check_fails_on_a_link_out(text):
    assert link_problems(ROOT / "README.md", text)


def test_a_model_card_names_no_folder_of_the_machine_that_made_it(tmp_path):
    import json

    import torch
    from safetensors.torch import save_file

    from lerobot_crowdnav.data.hub import card_tail, pdpo_card, portable

    for root, shown in (("/work/runs/r/datasets/bounded", False), ("outputs/datasets/bounded", True)):
        save_file({"actor.w": torch.zeros(3)}, str(tmp_path / checkpoint_files.WEIGHTS))
        (tmp_path / checkpoint_files.TRAIN_CONFIG).write_text(json.dumps({"dataset": {"repo_id": "org/d", "root": root}}))
        card = str(pdpo_card(tmp_path, "org/x", {"type": "pdpo"}))
        assert "- Data: `org/d`" in card and (root in card) == shown

    assert portable("lerobot-crowdnav-main --config_path=configs/recipes/x.yaml --output_root=/work/runs/recipes "
                    "--demos=3") == "lerobot-crowdnav-main --config_path=configs/recipes/x.yaml --demos=3"
    assert portable("lerobot-crowdnav-main --output_root=runs") == "lerobot-crowdnav-main --output_root=runs"
    tail = "\n".join(card_tail("org/x", None, {"command": "lerobot-crowdnav-main --output_root=/data/r"}, None, None,
                               "PPO", "everything"))
    assert "/data/r" not in tail and f"--seed={SEED_SPLITS['test'][0]}" in tail


def test_a_stage_records_the_cpu_time_of_its_subprocesses_and_the_cores_it_could_use(tmp_path):
    """The cards' cost table: a stage that burns CPU in a subprocess reports about that much CPU
    time, one that sleeps about none; the cores are the process's affinity."""
    from lerobot_crowdnav.data.hub import stage_time_table
    from lerobot_crowdnav.main.stages import StageRunner

    runner = StageRunner(tmp_path / "stage_times.json")
    burn = [sys.executable, "-c", "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.5: pass"]
    runner.run("burn", burn, False, lambda: subprocess.run(burn, check=True))
    runner.run("sleep", ["sleep"], False, lambda: time.sleep(0.5))
    runner.run("burn", burn, True, lambda: None)  # complete: skipped, nothing added
    cpu, wall = runner.cpu_times(), runner.wall_times()
    assert 0.5 <= cpu["burn"]["cpu_s"] < 0.5 + wall["burn"] and cpu["sleep"]["cpu_s"] < 0.2
    assert cpu["burn"]["wall_s"] == pytest.approx(wall["burn"]) and cpu["burn"]["cores"] == [len(os.sched_getaffinity(0))]
    table = stage_time_table(wall, cpu)
    assert table[2].startswith("| burn | ") and not table[2].endswith("| n/a | n/a |") and "n/a" not in table[-1]
    cpu["sleep"]["cores"] = [1, 2]  # resumed on both cores after one pinned to one
    assert stage_time_table(wall, cpu)[3].endswith(" | 1-2 |")
    assert stage_time_table(wall, {"burn": cpu["burn"]})[-1].endswith("| n/a | |")  # a stage of an older run


def test_the_machine_line_says_when_the_process_is_pinned_to_fewer_cores(monkeypatch):
    """Reports, cards and benchmarks name the machine; a run pinned to one core of two says so."""
    from lerobot_crowdnav.cli import machine_description

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert machine_description().endswith(", 2 logical cores")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {1})
    assert machine_description().endswith(", 2 logical cores (pinned to 1)")


def test_the_suite_keeps_its_dataset_caches_out_of_the_users_cache():
    """Every dataset the tests load leaves an Arrow copy in 🤗 datasets' cache: the suite's go to a
    temporary folder (conftest.py), in this process and in the lerobot-train processes it starts."""
    import datasets
    from conftest import HF_DATASETS_CACHE

    assert Path(datasets.config.HF_DATASETS_CACHE) == Path(HF_DATASETS_CACHE)
    assert os.environ["HF_DATASETS_CACHE"] == HF_DATASETS_CACHE
