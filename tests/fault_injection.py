"""Kill each long job at a named write/rename site, resume it, compare with an uninterrupted run.

A test tool, not part of the package: ``python tests/fault_injection.py --work_dir=DIR`` runs every
case below at a larger size than the test suite (tests/test_fault_injection.py and
tests/test_report.py run a few of them small; the tests import it as ``fault_injection``). A case
SIGKILLs the job in a subprocess through ``LEROBOT_CROWDNAV_FAULT`` (lerobot_crowdnav/fault.py, the
hook the product keeps at its write sites), checks that what the kill left never looks complete
when it is not, resumes the way a user would, and returns the differences from the uninterrupted
run (empty: passed). Guarantees: docs/resume.md.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pyarrow.parquet as pq
import torch
from safetensors.torch import load_file

from lerobot_crowdnav.checkpoint_files import CRITIC, FINETUNE_CONFIG, WEIGHTS
from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.data.dataset import COLLECTION_FILE
from lerobot_crowdnav.fault import ENV

ROOT = Path(__file__).resolve().parents[1]
REPO = "local/fault_orca"
# Per-file bookkeeping of the episodes table: legitimately differs when block boundaries do.
FILE_COLUMNS = ("data/chunk_index", "data/file_index", "meta/episodes/chunk_index", "meta/episodes/file_index")
COLLECT_POINTS = [("collect.create", 1), ("collect.data_written", 2), ("collect.renaming", 2),
                  ("collect.committed", 1), ("atomic.file", 1)]  # atomic.file: the README.md card
FINETUNE_POINTS = [("finetune.checkpoint_writing", 1), ("finetune.checkpoint_writing", 2),
                   ("finetune.checkpoint_renamed", 2), ("finetune.last_linked", 2)]
HUB_POINTS = [("hub.copying", 1), ("hub.copying", 4), ("atomic.dir_exchanged", 1)]
MAIN_POINTS = [("collect.data_written", 1), ("finetune.checkpoint_renamed", 2), ("hub.copying", 3),
               ("atomic.file", 1)]


def run_killed(argv: list[str], point: str, count: int) -> None:
    """Run ``python argv`` with the fault hook armed; it must die by SIGKILL at that point."""
    env = {**os.environ, ENV: f"{point}:{count}", "TQDM_DISABLE": "1"}
    proc = subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != -signal.SIGKILL:
        raise AssertionError(f"{point}:{count} not reached (exit {proc.returncode}): {proc.stderr[-2000:]}")


# -- collect_orca.py -----------------------------------------------------------------------------
def collect_argv(root: Path, keep: str, episodes: int, batch_size: int) -> list[str]:
    return [f"--episodes={episodes}", f"--batch_size={batch_size}", f"--root={root}", f"--repo_id={REPO}",
            f"--keep={keep}"]


def _table(paths: list[Path], drop: tuple[str, ...] = ()):
    import pyarrow as pa

    table = pa.concat_tables([pq.read_table(p) for p in paths])
    return table.drop_columns([c for c in drop if c in table.column_names])


def dataset_differences(a: Path, b: Path, file_boundaries: bool = True) -> list[str]:
    """What differs between two collections: frames, episodes table, tasks, info.json, stats.json
    (exact); the episodes' data and meta file indices only with ``file_boundaries``."""
    out = [rel for rel in ("meta/info.json", "meta/stats.json", COLLECTION_FILE)
           if json.loads((a / rel).read_text()) != json.loads((b / rel).read_text())]
    for pattern, drop in (("data/*/*.parquet", ()), ("meta/episodes/*/*.parquet", () if file_boundaries else FILE_COLUMNS),
                          ("meta/tasks.parquet", ())):
        if not _table(sorted(a.glob(pattern)), drop).equals(_table(sorted(b.glob(pattern)), drop)):
            out.append(pattern)
    return out


def check_partial_dataset(root: Path) -> None:
    """A killed collection: either no dataset yet, or the committed blocks, which load, and no
    card (the card marks a complete dataset)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if not root.exists():
        return
    info = json.loads((root / "meta/info.json").read_text())
    assert info["total_tasks"] == 1, info
    if info["total_episodes"]:
        ds = LeRobotDataset(REPO, root=root)
        assert ds.num_episodes == info["total_episodes"] and len(ds) == info["total_frames"]
        ds[len(ds) - 1]


def collect_case(work: Path, keep: str, point: str, count: int, reference: Path, episodes: int,
                 batch_size: int) -> list[str]:
    from lerobot_crowdnav.data.collect import main as collect_main

    root = work / f"collect_{keep}_{point}_{count}"
    argv = collect_argv(root, keep, episodes, batch_size)
    run_killed([str(ROOT / "datasets_scripts/collect_orca.py"), *argv], point, count)
    if point != "atomic.file":  # killed while writing the card: the frames are all committed
        assert not (root / "README.md").exists(), "a killed collection looks complete"
    check_partial_dataset(root)
    collect_main([*argv, "--resume=true"])
    return dataset_differences(root, reference, file_boundaries=keep == "all")


# -- lerobot-crowdnav-finetune -------------------------------------------------------------------
def untrained_checkpoint(out: Path, dataset_root: Path, config) -> Path:
    """``out/pretrained_model``: an untrained PDPO (``config``, a PDPOConfig) with the statistics of
    the dataset in ``dataset_root``, saved the way lerobot-train saves a checkpoint."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot_policy_pdpo import PDPOPolicy, make_pdpo_pre_post_processors

    config.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (269,))}
    config.output_features = {"action": PolicyFeature(FeatureType.ACTION, (2,))}
    stats = LeRobotDatasetMetadata(REPO, root=dataset_root).stats
    torch.manual_seed(0)
    path = out / "pretrained_model"
    PDPOPolicy(config).save_pretrained(path)
    for processor in make_pdpo_pre_post_processors(config, stats):
        processor.save_pretrained(path)
    return path


FINETUNE_RUN = ["--num_envs=4", "--ppo.n_steps=8", "--ppo.batch_size=16", "--ppo.update_epochs=2",
                "--ppo.n_critic_warmup_itr=1", "--val.n_episodes=2", "--val.freq=32", "--save_freq=32",
                "--seed=3"]
COMPARED = ("iteration", "env_steps", "rollout_digest", "loss/policy_loss", "loss/value_loss", "train/episodes",
            "val/success_rate")


def finetune_argv(pretrained: Path, out: Path, env_steps: int) -> list[str]:
    return [f"--policy.path={pretrained}", f"--output_dir={out}", f"--env_steps={env_steps}", *FINETUNE_RUN]


def check_last_checkpoint(out: Path) -> None:
    """``last``, if any, is a complete checkpoint: weights, optimizers, env and RNG state."""
    last = out / "checkpoints" / "last"
    if not last.exists():
        return
    for rel in (f"pretrained_model/{WEIGHTS}", f"pretrained_model/{FINETUNE_CONFIG}",
                "training_state/optimizers.pt", "training_state/env_rank0.npz", "training_state/rng_rank0.json"):
        assert (last / rel).is_file(), f"checkpoints/last -> {last.resolve().name} lacks {rel}"
    torch.load(last / "training_state/optimizers.pt", weights_only=True)


def finetune_record(out: Path) -> tuple[list[dict], dict]:
    """The run's compared progress fields and its last and best weights (actor and critic)."""
    records = [{k: r.get(k) for k in COMPARED} for r in map(json.loads, (out / "progress.jsonl").read_text().splitlines())]
    weights = {f"{name}/{file}/{k}": v for name in ("last", "best") for file in (WEIGHTS, CRITIC)
               for k, v in load_file(out / "checkpoints" / name / "pretrained_model" / file).items()}
    return records, weights


def finetune_differences(a: Path, b: Path) -> list[str]:
    (ra, wa), (rb, wb) = finetune_record(a), finetune_record(b)
    out = [f"progress {x} != {y}" for x, y in zip(ra, rb, strict=False) if x != y]
    if len(ra) != len(rb):
        out.append(f"{len(ra)} != {len(rb)} progress records")
    if wa.keys() != wb.keys() or any(not torch.equal(wa[k], wb[k]) for k in wa):
        out.append("weights differ")
    return out


def finetune_case(work: Path, pretrained: Path, point: str, count: int, reference: Path, env_steps: int) -> list[str]:
    from lerobot_crowdnav.rl.finetune import main as finetune_main

    out = work / f"finetune_{point}_{count}"
    argv = finetune_argv(pretrained, out, env_steps)
    run_killed(["-m", "lerobot_crowdnav.rl.finetune", *argv], point, count)
    check_last_checkpoint(out)
    finetune_main([*argv, "--resume=true"])
    return finetune_differences(out, reference)


# -- hub-format pushes ---------------------------------------------------------------------------
def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def hub_case(work: Path, kind: str, source: Path, old_source: Path, point: str, count: int) -> list[str]:
    """Push ``old_source``, then kill a push of ``source`` over it: the repository must be the old
    one or the new one, whole; a rerun of the push gives the new one."""
    from lerobot_crowdnav.data.hub import main as push_main

    hub = work / f"hub_{kind}_{point}_{count}"
    repo_id = f"local/fault_{kind}"
    argv = [f"--kind={kind}", f"--repo_id={repo_id}", f"--push_to_hub_dir={hub}", "--overwrite=true"]
    push_main([*argv, f"--root={old_source}"])
    target = hub / ("datasets" if kind == "dataset" else "models") / repo_id
    old = tree(target)
    run_killed(["-m", "lerobot_crowdnav.data.hub", *argv, f"--root={source}"], point, count)
    seen = tree(target)
    push_main([*argv, f"--root={source}"])
    new = tree(target)
    out = [] if seen in (old, new) else ["a killed push left neither the old nor the new repository"]
    if old == new:
        out.append("the old and new sources must differ for the case to mean anything")
    if sorted(p.name for p in target.parent.iterdir()) != [target.name]:
        out.append(f"staging left in {target.parent}")
    return out


# -- lerobot-crowdnav-main -----------------------------------------------------------------------
def main_argv(output_root: Path) -> list[str]:
    return [f"--config_path={ROOT / 'configs/main/tiny.yaml'}", f"--output_root={output_root}"]


def report_tables(output_root: Path) -> dict[str, str]:
    tables = output_root / "tiny" / "tables"
    return {p.name: p.read_text() for p in sorted(tables.iterdir())}


def main_case(work: Path, point: str, count: int, reference: Path) -> list[str]:
    """``reference``: the output_root of an uninterrupted run."""
    from lerobot_crowdnav.pipeline import main as pipeline_main

    root = work / f"main_{point}_{count}"
    run_killed(["-m", "lerobot_crowdnav.pipeline", *main_argv(root)], point, count)
    pipeline_main(main_argv(root))
    a, b = report_tables(root), report_tables(reference)
    return [name for name in sorted(a.keys() | b.keys()) if a.get(name) != b.get(name)]


# -- the script ----------------------------------------------------------------------------------
@dataclass
class FaultInjectionConfig:
    # Where the runs go (each case in its own directory; the uninterrupted references too).
    work_dir: Path = Path("outputs/fault_injection")
    # Jobs to test: any of collect, finetune, hub, main.
    jobs: tuple[str, ...] = ("collect", "finetune", "hub", "main")
    # collect_orca.py: episodes and block size (several blocks, so kills land between them).
    episodes: int = 600
    batch_size: int = 128
    # lerobot-crowdnav-finetune: env steps (32 per iteration and per checkpoint).
    env_steps: int = 160


def run_all(cfg: FaultInjectionConfig) -> dict[str, list[str]]:
    from lerobot_crowdnav.data.collect import main as collect_main
    from lerobot_crowdnav.rl.finetune import main as finetune_main
    from lerobot_crowdnav.pipeline import main as pipeline_main

    work = Path(cfg.work_dir)
    if work.exists():
        shutil.rmtree(work)
    results: dict[str, list[str]] = {}

    def record(name: str, differences: list[str]) -> None:
        results[name] = differences
        print(f"{'PASS' if not differences else 'FAIL'} {name} {'; '.join(differences)}", flush=True)

    if "collect" in cfg.jobs or "hub" in cfg.jobs:
        for keep in ("all", "success"):
            reference = work / f"reference_{keep}"
            collect_main(collect_argv(reference, keep, cfg.episodes, cfg.batch_size))
            for point, count in COLLECT_POINTS if "collect" in cfg.jobs else []:
                record(f"collect keep={keep} {point}:{count}",
                       collect_case(work, keep, point, count, reference, cfg.episodes, cfg.batch_size))
    if "finetune" in cfg.jobs or "hub" in cfg.jobs:
        from lerobot_policy_pdpo import PDPOConfig

        pretrained = untrained_checkpoint(work / "pretrained", work / "reference_all", PDPOConfig(device="cpu"))
        reference = work / "reference_finetune"
        finetune_main(finetune_argv(pretrained, reference, cfg.env_steps))
        for point, count in FINETUNE_POINTS if "finetune" in cfg.jobs else []:
            record(f"finetune {point}:{count}", finetune_case(work, pretrained, point, count, reference, cfg.env_steps))
    if "hub" in cfg.jobs:
        checkpoints = sorted((reference / "checkpoints").glob("0*"))
        for point, count in HUB_POINTS:
            record(f"hub dataset {point}:{count}", hub_case(work, "dataset", work / "reference_success",
                                                            work / "reference_all", point, count))
            record(f"hub policy {point}:{count}", hub_case(work, "policy", checkpoints[-1] / "pretrained_model",
                                                           checkpoints[0] / "pretrained_model", point, count))
    if "main" in cfg.jobs:
        reference = work / "reference_main"
        pipeline_main(main_argv(reference))
        for point, count in MAIN_POINTS:
            record(f"main {point}:{count}", main_case(work, point, count, reference))
    return results


def main(argv: list[str] | None = None) -> None:
    def run(cfg: FaultInjectionConfig) -> None:
        results = run_all(cfg)
        failed = [name for name, diff in results.items() if diff]
        print(f"{len(results) - len(failed)} of {len(results)} cases passed")
        if failed:
            raise SystemExit(1)

    run_cli(FaultInjectionConfig, run, argv)


if __name__ == "__main__":
    main()
