"""Hub-format directories: exactly what a Hugging Face Hub repository would hold, written locally.

``<dir>/datasets/<org>/<name>/`` holds a dataset repository (``meta/``, ``data/``, ``README.md``
card with its YAML header), loadable with ``LeRobotDataset("<org>/<name>", root=...)``. A push
is written aside and moved into place, so a failed push never leaves a half-written repository.

Standalone: ``python -m lerobot_crowdnav.hub --root=<dataset> --repo_id=<org>/<name>
--push_to_hub_dir=<dir> [--overwrite=true]``.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import draccus
from lerobot.datasets.utils import create_lerobot_dataset_card

from .config import CrowdSimConfig

REPO_IGNORE = ("images", "videos", "*.tmp")  # lerobot's push_to_hub skips images/ (no videos here)


def dataset_card(repo_id: str, info, sim_cfg: CrowdSimConfig, collection: dict, summary: dict):
    """The dataset card (lerobot's template and YAML header) with the collection's facts."""
    from .dataset import FPS

    outcomes = ", ".join(f"{k} {v}" for k, v in summary["outcomes"].items())
    description = f"""ORCA demonstrations in the crowd-navigation simulator of lerobot-crowdnav (a
batched reproduction of CrowdNav++), for pretraining the PDPO diffusion policy.

- **Environment:** `{sim_cfg.task}` ({'walls on the boundary of the 12 x 12 m workspace' if sim_cfg.bounded else 'original benchmark, no boundary'}), preset `{sim_cfg.preset}`, {sim_cfg.num_humans} ORCA humans, robot radius {sim_cfg.robot_radius} m, sensing range {sim_cfg.sensing_range} m, randomized human attributes: {sim_cfg.randomize_attributes}.
- **Demonstrator:** the ORCA robot (radius r + {sim_cfg.orca_radius_pad + sim_cfg.orca_safety_space:.2f} m, neighbour distance {sim_cfg.orca_neighbor_dist} m, time horizons {sim_cfg.orca_time_horizon} s / {sim_cfg.orca_time_horizon_obst} s, max speed {sim_cfg.robot_v_pref} m/s{', walls as static obstacles' if sim_cfg.bounded else ''}).
- **Episodes:** {summary['episodes']} ({summary['frames']} frames at {FPS} fps), train seeds {summary['first_seed']} to {summary['last_seed']} (consecutive seeds from {collection['seed']}, keep = `{collection['keep']}`). Outcomes: {outcomes}.
- **Features:** `observation.state` (269 floats: robot state, velocity, 20 humans x 6 positions relative to the robot, visibility mask; names in `meta/info.json`), `action` = executed velocity (vx, vy) in m/s, `next.reward`, `next.done`, `next.success`. Episode metadata (`meta/episodes`) adds `seed` and `event`.
- **Action chunks:** not stored. A policy with `action_delta_indices = range(H)` (PDPO: H = 5) gets, at step t, the executed actions t .. t+H-1 of the same episode through lerobot's `delta_timestamps` (`[0, 0.25, ..., (H-1)/4]` s), with `action_is_pad` marking the steps past the episode's end.
- **Collected with:** `python datasets_scripts/collect_orca.py --episodes {collection['episodes']} --env.task={sim_cfg.task} --env.preset={sim_cfg.preset} --seed={collection['seed']} --keep={collection['keep']}` in {summary['wall_time_s']:.1f} s.
"""
    return create_lerobot_dataset_card(
        tags=["crowd-navigation", "orca", "lerobot-crowdnav", "pdpo"], dataset_info=info,
        license="apache-2.0", repo_id=repo_id, dataset_description=description)


def push_dataset_to_dir(root: str | Path, repo_id: str, hub_dir: str | Path, overwrite: bool = False) -> Path:
    """Copy the dataset repository files of ``root`` to ``hub_dir/datasets/<org>/<name>``."""
    root = Path(root)
    if not (root / "meta/info.json").exists():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset (no meta/info.json)")
    if not (root / "README.md").exists():
        raise FileNotFoundError(f"{root} has no dataset card (README.md)")
    org, name = repo_id.split("/")
    target = Path(hub_dir) / "datasets" / org / name
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; pass --overwrite=true (collect_orca: --push_overwrite=true) to replace it")
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=target.parent))
    try:
        shutil.copytree(root, staging / "repo", ignore=shutil.ignore_patterns(*REPO_IGNORE))
        if target.exists():
            old = staging / "old"
            target.replace(old)
        (staging / "repo").replace(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


@dataclass
class PushConfig:
    # Dataset directory to publish.
    root: Path
    # Repository name, <org>/<name>.
    repo_id: str
    # Hub-format directory: the repository goes to <dir>/datasets/<org>/<name>/.
    push_to_hub_dir: Path
    # Replace an existing repository directory.
    overwrite: bool = False


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=PushConfig, args=argv)
    try:
        print(push_dataset_to_dir(cfg.root, cfg.repo_id, cfg.push_to_hub_dir, cfg.overwrite))
    except (FileExistsError, FileNotFoundError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None


if __name__ == "__main__":
    main()
