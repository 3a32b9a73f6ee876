"""Hub-format directories: exactly what a Hugging Face Hub repository would hold, written locally.

``<dir>/datasets/<org>/<name>/`` holds a dataset repository (``meta/``, ``data/``, ``README.md``
card with its YAML header), loadable with ``LeRobotDataset("<org>/<name>", root=...)``;
``<dir>/models/<org>/<name>/`` a policy repository (``config.json``, ``model.safetensors``,
processors, ``train_config.json``, ``README.md`` model card), loadable with ``--policy.path``. A push
is written aside and moved into place, so a failed push never leaves a half-written repository.

Standalone: ``python -m lerobot_crowdnav.data.hub --kind=dataset|policy --root=<dataset or
pretrained_model> --repo_id=<org>/<name> --push_to_hub_dir=<dir> [--overwrite=true]
[--metrics=<metrics.json>]``.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lerobot.datasets.utils import create_lerobot_dataset_card

from .. import fault
from ..checkpoint_files import (BEST_INFO, CRITIC, FINETUNE_CONFIG, POLICY_CONFIG, SOURCE_PREFIX, TRAIN_CONFIG,
                                TRAIN_PPO_CONFIG, WEIGHTS)
from ..cli import run_cli
from ..sim.config import SEED_SPLITS, CrowdSimConfig
from .dataset import CARD_FILE, COLLECTION_FILE, FPS, collection_complete

REPO_IGNORE = ("images", "videos", "*.tmp")  # lerobot's push_to_hub skips images/ (no videos here)


ORCA_ROBOT_CARD = {
    "look_ahead": "look-ahead ORCA robot (CrowdSimPred: every visible human at its true position now "
                  "and 1..5 steps ahead)",
    "current_state": "current-state ORCA robot (CrowdSimVarNum: each human where last seen, "
                     "extrapolated while out of sight)",
}


def dataset_card(repo_id: str, info, sim_cfg: CrowdSimConfig, collection: dict, summary: dict):
    """The dataset card (lerobot's template and YAML header) with the collection's facts."""
    outcomes = ", ".join(f"{k} {v}" for k, v in summary["outcomes"].items())
    # A resumed collection's earlier invocations are not timed: say whose time it is.
    resumed = f" (the last invocation, which resumed after {summary['resumed_after']:,} committed episodes)" \
        if summary.get("resumed_after") else ""
    description = f"""ORCA demonstrations in the crowd-navigation simulator of lerobot-crowdnav (a
batched reproduction of CrowdNav++), for pretraining the PDPO diffusion policy.

- **Environment:** `{sim_cfg.task}` ({'walls on the boundary of the 12 x 12 m workspace' if sim_cfg.bounded else 'original benchmark, no boundary'}), preset `{sim_cfg.preset}`, {sim_cfg.num_humans} ORCA humans, robot radius {sim_cfg.robot_radius} m, sensing range {sim_cfg.sensing_range} m, randomized human attributes: {sim_cfg.randomize_attributes}.
- **Demonstrator:** CrowdNav++'s {ORCA_ROBOT_CARD[sim_cfg.orca_robot]} (`orca_robot={sim_cfg.orca_robot}`; radius r + {sim_cfg.orca_radius_pad + sim_cfg.orca_safety_space:.2f} m, neighbour distance {sim_cfg.orca_neighbor_dist} m{' redrawn from U' + str(tuple(sim_cfg.neighbor_dist_range)) + ' at every new human' if sim_cfg.randomize_neighbor_dist else ''}, time horizons {sim_cfg.orca_time_horizon} s / {sim_cfg.orca_time_horizon_obst} s, max speed {sim_cfg.robot_v_pref} m/s{(', walls as static obstacles' if sim_cfg.orca_robot_wall_aware else ', unaware of the walls as in CrowdNav++') if sim_cfg.bounded else ''}).
- **Episodes:** {summary['episodes']} ({summary['frames']} frames at {FPS} fps), train seeds {summary['first_seed']} to {summary['last_seed']} (consecutive seeds from {collection['seed']}, keep = `{collection['keep']}`). Outcomes: {outcomes}.
- **Features:** `observation.state` (269 floats: robot state, velocity, 20 humans x 6 positions relative to the robot, visibility mask; names in `meta/info.json`), `action` = executed velocity (vx, vy) in m/s, `next.reward`, `next.done`, `next.success`. Episode metadata (`meta/episodes`) adds `seed` and `event`.
- **Action chunks:** not stored. A policy with `action_delta_indices = range(H)` (PDPO: H = 5) gets, at step t, the executed actions t .. t+H-1 of the same episode through lerobot's `delta_timestamps` (`[0, 0.25, ..., (H-1)/4]` s), with `action_is_pad` marking the steps past the episode's end.
- **Collected with:** `python datasets_scripts/collect_orca.py --episodes {collection['episodes']} --env.task={sim_cfg.task} --env.preset={sim_cfg.preset} --env.orca_robot={sim_cfg.orca_robot} --seed={collection['seed']} --keep={collection['keep']}` in {summary['wall_time_s']:.1f} s{resumed}.
"""
    return create_lerobot_dataset_card(
        tags=["crowd-navigation", "orca", "lerobot-crowdnav", "pdpo"], dataset_info=info,
        license="apache-2.0", repo_id=repo_id, dataset_description=description)


CURVE_FILE = "learning_curve.png"


def _publish(target: Path, overwrite: bool, fill) -> Path:
    """Write a repository directory aside with ``fill(staging_dir)``, then swap it with ``target``
    in one atomic rename (replacing an existing one only with ``overwrite``): a reader, or a kill,
    sees the old complete repository or the new one. A killed push's staging is removed by the next."""
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; pass --overwrite=true (collect_orca: --push_overwrite=true) to replace it")
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = target.with_name(f".{target.name}.push.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        fill(staging / "repo")
        fault.replace_dir(staging / "repo", target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def _copy_file(src: str, dst: str) -> None:
    fault.point("hub.copying")
    shutil.copy2(src, dst)


def push_dataset_to_dir(root: str | Path, repo_id: str, hub_dir: str | Path, overwrite: bool = False) -> Path:
    """Copy the dataset repository files of ``root`` to ``hub_dir/datasets/<org>/<name>``."""
    root = Path(root)
    if not (root / "meta/info.json").exists():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset (no meta/info.json)")
    if not collection_complete(root):
        raise FileNotFoundError(f"{root} has no dataset card ({CARD_FILE})")
    org, name = split_repo_id(repo_id)
    return _publish(Path(hub_dir) / "datasets" / org / name, overwrite,
                    lambda dst: shutil.copytree(root, dst, ignore=shutil.ignore_patterns(*REPO_IGNORE),
                                                copy_function=_copy_file))


PICKLE_SUFFIXES = (".bin", ".pt", ".pth", ".pkl", ".ckpt")
# What a policy repository holds besides its processors and card.
POLICY_FILES = (POLICY_CONFIG, WEIGHTS, CRITIC, TRAIN_CONFIG, FINETUNE_CONFIG, SOURCE_PREFIX + FINETUNE_CONFIG,
                TRAIN_PPO_CONFIG)


def split_repo_id(repo_id: str) -> tuple[str, str]:
    parts = repo_id.split("/")
    if len(parts) != 2 or not all(parts):
        raise ValueError(f"repo_id must look like <org>/<name>, got {repo_id!r}")
    return parts[0], parts[1]


def evaluation_lines(metrics: dict | None) -> list[str]:
    """A model card's evaluation section: the metrics.json of lerobot-crowdnav-eval as a table."""
    from ..measure.metrics import markdown_header, markdown_row

    lines = ["", "## Evaluation", ""]
    if not metrics:
        return lines + ["Not evaluated yet: `lerobot-crowdnav-eval --policy.path=<this directory>`."]
    bounded = metrics["env"]["task"] == "BoundedCrowdNav-v0"
    return lines + [f"{metrics['env']['task']} ({metrics['env']['preset']} preset), {metrics['n_episodes']} "
                    f"{metrics['split']} episodes (`lerobot-crowdnav-eval`):", "", markdown_header(bounded),
                    markdown_row(metrics, bounded)]


def run_steps(run: dict, what: str) -> str:
    """How far this checkpoint's PPO run got, beside its budget (a chosen checkpoint may be early)."""
    return (f"for {run['env_steps_done']:,} environment steps (this checkpoint; the {what}'s budget: "
            f"{run['env_steps']:,}) in `{run['env']['task']}` ({run['env']['preset']} preset)")


def best_checkpoint_lines(pretrained: Path, recipe: dict | None = None) -> list[str]:
    """Why these weights: how the main job chose them (``recipe["checkpoint"]``), or a PPO run's
    ``checkpoints/best``, which has ``best.json`` beside it."""
    import json

    if recipe and recipe.get("checkpoint"):
        return [recipe["checkpoint"]]
    best = pretrained.parent / BEST_INFO
    if not best.exists():
        return []
    b = json.loads(best.read_text())
    return [f"- Checkpoint: the run's `best`, at {b['env_steps']:,} env steps (validation success "
            f"{100 * b['val/success_rate']:.0f} % on the validation seeds, the paper's choice)."]


def card_tail(repo_id: str, metrics: dict | None, recipe: dict | None, curve: str | None, run: dict | None,
              algorithm: str, made: str) -> list[str]:
    """A model card's evaluation table, learning curve (``algorithm``'s), the command that
    reproduces it (what it ``made``) with its stages' wall times (and, with ``devices``, where a
    trainer's env steps ran), and how to use it."""
    lines = evaluation_lines(metrics)
    if curve:
        lines += ["", "## Learning curve", "", f"![{algorithm} learning curve]({curve})"]
    if recipe:
        times = recipe.get("wall_time_s") or {}
        lines += ["", "## Reproduce", "", f"From scratch ({made}):", "", "```bash", portable(recipe["command"]), "```",
                  ""]
        if times:
            lines += [*stage_time_table(times, recipe.get("cpu_time") or {}), "",
                      f"Machine: {recipe.get('machine', 'unknown')}."]
        for stage, by_device in (recipe.get("devices") or {}).items():  # a run moved to a lent GPU and back
            parts = "; ".join(f"{int(d['env_steps']):,} env steps in {d['wall_s'] / 60:.1f} min on "
                              f"{'the CPU' if name == 'cpu' else name.split(': ', 1)[-1]}" for name, d in by_device.items())
            lines += ["", f"Where `{stage}` ran (its trainer's records): {parts}."]
    task = ((run or {}).get("env") or (metrics or {}).get("env") or {}).get("task", "BoundedCrowdNav-v0")
    return lines + ["", "## Use", "", "```bash",
                    f"lerobot-eval --policy.path=<dir>/models/{repo_id} --env.type=crowdnav --env.task={task} "
                    f"--eval.n_episodes=50 --seed={SEED_SPLITS['test'][0]}", "```"]


def stage_time_table(wall_s: dict[str, float], cpu: dict[str, dict]) -> list[str]:
    """The card's cost table: each stage's wall time and, where the main job measured all of it
    (``main.stages.CPU_TIMES`` records), its CPU time and the logical cores it could use: wall
    time says how long a stage took on this machine as it was shared, CPU time what it cost."""
    def measured(name: str) -> dict | None:
        record = cpu.get(name)
        return record if record and record["wall_s"] >= 0.99 * wall_s[name] else None  # else partly unknown

    lines = ["| stage | wall time (min) | CPU time (min) | cores |", "|---|---|---|---|"]
    records = {name: measured(name) for name in wall_s}
    for name, r in records.items():
        cpu_cells = ("n/a", "n/a") if r is None else (
            f"{r['cpu_s'] / 60:.1f}", "-".join(map(str, sorted({min(r["cores"]), max(r["cores"])}))))
        lines.append(f"| {name} | {wall_s[name] / 60:.1f} | {cpu_cells[0]} | {cpu_cells[1]} |")
    total_cpu = "n/a" if None in records.values() else f"{sum(r['cpu_s'] for r in records.values()) / 60:.1f}"
    return lines + [f"| total | {sum(wall_s.values()) / 60:.1f} | {total_cpu} | |"]


def portable(command: str) -> str:
    """``command`` without the flags that name a folder of the machine it ran on (an absolute
    ``--output_root``): a card points at nothing outside its repository but public references."""
    return " ".join(arg for arg in command.split(" ")
                    if not (arg.startswith("--output_root=") and Path(arg.split("=", 1)[1]).is_absolute()))


# Policy type (the "type" of its config.json) -> its model card writer, ``card(pretrained, repo_id,
# config, metrics, recipe, curve) -> ModelCard``; a policy family's module registers its own.
MODEL_CARDS: dict[str, Callable] = {}


def register_model_card(policy_type: str) -> Callable[[Callable], Callable]:
    """Decorator: the decorated function writes the model card of ``policy_type`` policies."""
    def add(card: Callable) -> Callable:
        MODEL_CARDS[policy_type] = card
        return card
    return add


def policy_card(pretrained: Path, repo_id: str, metrics: dict | None = None, recipe: dict | None = None,
                curve: str | None = None):
    """The model card of the policy in ``pretrained``, by its type (``MODEL_CARDS``); with
    ``recipe`` (``command`` that reproduces it, ``wall_time_s`` per stage) and ``curve`` (the
    learning-curve image's file name in the repository) when the main job pushes it (``cpu_time``:
    the stages' CPU records, :func:`stage_time_table`)."""
    import json

    config = json.loads((pretrained / POLICY_CONFIG).read_text())
    card = MODEL_CARDS.get(config.get("type"))
    if card is None:
        raise ValueError(f"{pretrained} holds a {config.get('type')!r} policy, which has no model card "
                         f"(cards: {', '.join(sorted(MODEL_CARDS))})")
    return card(pretrained, repo_id, config, metrics, recipe, curve)


@register_model_card("pdpo")
def pdpo_card(pretrained: Path, repo_id: str, config: dict, metrics: dict | None = None, recipe: dict | None = None,
              curve: str | None = None):
    """PDPO: architecture, training data and budget (pretraining, fine-tuning), parameter counts,
    then ``card_tail``."""
    import json

    from huggingface_hub import ModelCard, ModelCardData

    from ..measure.parameters import parameter_counts

    train = json.loads((pretrained / TRAIN_CONFIG).read_text()) if (pretrained / TRAIN_CONFIG).exists() else {}
    finetune_path = pretrained / FINETUNE_CONFIG
    finetune = json.loads(finetune_path.read_text()) if finetune_path.exists() else None
    counts = parameter_counts(pretrained / WEIGHTS)
    critic_input = (finetune or {}).get("ppo", {}).get("critic_input", "latent")
    dataset = (train.get("dataset") or {}).get("repo_id")
    collection = collection_record(train)
    demonstrator = ORCA_ROBOT_CARD.get(collection.get("env", {}).get("orca_robot"))
    lines = [
        f"# {repo_id}", "",
        "PDPO (diffusion policy for short-horizon planning in robot crowd navigation), a lerobot policy "
        "trained with lerobot-crowdnav.", "",
        "## Architecture", "",
        f"- Input: `observation.state`, the 269-float crowd observation ({config.get('num_humans')} humans, "
        f"{config.get('prediction_steps')} prediction steps); output: a chunk of H = {config.get('horizon')} "
        f"world-frame velocities (m/s); the first {config.get('n_action_steps')} executed, then a new chunk (receding horizon).",
        f"- Crowd encoder: human MLP {config.get('human_mlp_dims')}, {config.get('attention_heads')}-head masked "
        f"self-attention with residual, layer norm, dropout {config.get('dropout')}; edge MLP {config.get('edge_mlp_dims')}; "
        f"attention pooling over visible humans; latent MLP {config.get('latent_mlp_dims')}.",
        f"- Diffusion actor: denoiser MLP {config.get('denoiser_dims')} (ReLU) with a {config.get('time_embed_dim')}-dim "
        f"sinusoidal timestep embedding; cosine schedule, epsilon prediction, K = {config.get('num_diffusion_steps')} "
        + (f"diffusion steps, sampled by DDIM in {config['ddim_steps']} (eta 1 while exploring, 0 when deterministic)"
           if config.get("ddim_steps") else "DDPM steps")
        + f"; EMA sampling weights: {config.get('use_ema')} (decay {config.get('ema_decay')}).",
        f"- Value head (critic): MLP {config.get('value_mlp_dims')}, Mish, on "
        + {"latent": "the encoder's latent z (the paper)", "state": "the normalized observation",
           "latent+state": "the encoder's latent z and the normalized observation"}[critic_input] + ".",
        f"- Parameters: actor (encoder + denoiser) {counts['actor'] / 1e6:.3f} M (paper: 0.848 M); "
        + (f"critic {counts['critic'] / 1e6:.3f} M (paper: 0.201 M)." if counts["critic"]
           else "no critic (a BC policy: diffusion PPO adds one)."), "",
        "## Training", "",
        f"- Data: `{dataset}`" + (f" ({root})" if (root := (train.get("dataset") or {}).get("root"))
                                  and not Path(root).is_absolute() else "")
        + (f": demonstrations of CrowdNav++'s {demonstrator}" if demonstrator else "") + ".",
        f"- Pretraining (behaviour cloning, lerobot-train): {train.get('steps')} steps at batch {train.get('batch_size')} "
        f"(AdamW lr {config.get('optimizer_lr')}, weight decay {config.get('optimizer_weight_decay')}), seed {train.get('seed')}"
        + "".join(f"; {remedy}" for remedy in pretraining_remedies(config, collection)) + ".",
    ]
    if finetune:
        ppo = finetune["ppo"]
        chain = config.get("ddim_steps") or config.get("num_diffusion_steps")  # reverse steps per sample
        lines += [
            f"- Fine-tuning: diffusion PPO (DPPO) {run_steps(finetune, 'stage')}, {finetune['num_envs']} envs x "
            f"{finetune['world_size']} process(es), seed {finetune['seed']}: "
            + (f"all {chain} denoising steps trained" if ppo["ft_denoising_steps"] >= chain else
               f"the last {ppo['ft_denoising_steps']} of {chain} denoising steps trained (a frozen copy of the "
               "pretrained nets runs the others; the model file holds both)")
            + f", actor lr {ppo['actor_lr']}, critic lr {ppo['critic_lr']}, "
            f"batch {ppo['batch_size']} env steps x {ppo['ft_denoising_steps']} denoising steps, "
            f"{ppo['update_epochs']} epochs, clip {ppo['clip_ploss_coef_base']} -> {ppo['clip_ploss_coef']}; "
            "`finetune_config.json` has every setting.",
        ]
        previous = pretrained / (SOURCE_PREFIX + FINETUNE_CONFIG)
        if previous.exists():  # this run continued a fine-tuned checkpoint
            prev = json.loads(previous.read_text())
            lines.append(f"- It continued a fine-tuned checkpoint: {prev['env_steps_done']:,} env steps of diffusion PPO "
                         f"before (freeze_encoder {prev['ppo'].get('freeze_encoder', False)}, clip "
                         f"{prev['ppo']['clip_ploss_coef_base']} -> {prev['ppo']['clip_ploss_coef']}; "
                         "`source_finetune_config.json` has every setting), from the same pretraining.")
        lines += best_checkpoint_lines(pretrained, recipe)
    lines += card_tail(repo_id, metrics, recipe, curve, finetune, "diffusion-PPO",
                       "demonstrations, pretraining, fine-tuning, evaluation, this directory")
    data = ModelCardData(license="apache-2.0", library_name="lerobot", pipeline_tag="robotics",
                         tags=["robotics", "lerobot", "pdpo", "diffusion-policy", "crowd-navigation"],
                         datasets=[dataset] if dataset else None)
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n" + "\n".join(lines) + "\n")


def collection_record(train: dict) -> dict:
    """The collection record (``meta/crowdnav_collection.json``: simulator, DAgger rounds) of the
    dataset a policy was pretrained on, where that dataset is on this machine; else ``{}``."""
    import json

    path = Path((train.get("dataset") or {}).get("root") or "") / COLLECTION_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def pretraining_remedies(config: dict, collection: dict) -> list[str]:
    """What the pretraining did against the copycat shortcut (the policy copying the robot's own
    velocity, the previous action), from the policy's config and its dataset's collection record
    (DAgger rounds)."""
    remedies = []
    if p := config.get("velocity_dropout"):
        remedies.append("the robot's own velocity (the previous action) hidden from the policy "
                        + ("always" if p == 1 else f"in {p:.0%} of the training samples"))
    if (draws := config.get("noise_draws", 1)) > 1:
        remedies.append(f"{draws} diffusion-noise draws per sample")
    if rounds := collection.get("dagger"):
        remedies.append(f"{len(rounds)} DAgger round{'s' * (len(rounds) > 1)} aggregated into the demonstrations "
                        f"({sum(r['learner_episodes'] for r in rounds):,} episodes driven by the policy being trained, "
                        f"{sum(r['snippets'] for r in rounds):,} of their states labelled with the ORCA demonstrator's chunk)")
    return remedies


# The reference network (Shuijing725/CrowdNav_Prediction_AttnGraph, selfAttn_merge_srnn) holds an
# unused Linear(256, 2) (514 parameters) that the plugin leaves out; the paper counts it.
CROWDNAVPP_DEAD_HEAD = 514
CROWDNAVPP_REFERENCE = 2_502_535


@register_model_card("crowdnavpp")
def crowdnavpp_card(pretrained: Path, repo_id: str, config: dict, metrics: dict | None = None,
                    recipe: dict | None = None, curve: str | None = None):
    """Model card of a CrowdNav++ policy trained by lerobot-crowdnav-train-ppo: architecture, the
    parameter count against the reference's, the PPO run, then ``card_tail``."""
    import json
    import math

    from huggingface_hub import ModelCard, ModelCardData
    from safetensors import safe_open

    with safe_open(str(pretrained / WEIGHTS), "pt") as f:
        n = sum(math.prod(f.get_slice(k).get_shape()) for k in f.keys())
    run_path = pretrained / TRAIN_PPO_CONFIG
    run = json.loads(run_path.read_text()) if run_path.exists() else None
    lines = [
        f"# {repo_id}", "",
        "CrowdNav++ (attention-graph recurrent RL policy for robot crowd navigation, Liu et al. ICRA 2023), a "
        "lerobot policy (`--policy.type=crowdnavpp`) trained from scratch by PPO with lerobot-crowdnav.", "",
        "## Architecture", "",
        f"- Input: `observation.state` ({config.get('num_humans')} humans, {config.get('prediction_steps')} prediction "
        "steps), read raw; output: one world-frame velocity (m/s), the mean of a Gaussian (the env clips it by norm).",
        f"- Robot embedding {config.get('feature_size')}; human-human {config.get('attn_heads')}-head self-attention "
        f"(width {config.get('attn_size')}); robot-human attention ({config.get('attention_size')}-d); node GRU "
        f"{config.get('node_rnn_size')}; actor and critic MLPs {config.get('head_hidden_size')} x 2 (Tanh).",
        f"- Parameters: {n:,} trainable ({n / 1e6:.3f} M); the reference network, whose unused "
        f"`human_node_final_linear` adds {CROWDNAVPP_DEAD_HEAD}: {n + CROWDNAVPP_DEAD_HEAD:,} "
        f"({(n + CROWDNAVPP_DEAD_HEAD) / 1e6:.3f} M; reference sizes: {CROWDNAVPP_REFERENCE:,}; paper: 2.503 M).", "",
        "## Training", "",
    ]
    if run:
        ppo = run["ppo"]
        lines.append(
            f"- PPO from scratch {run_steps(run, 'run')}, {run['num_envs']} envs x {run['world_size']} process(es), seed "
            f"{run['seed']}: Adam lr {ppo['actor_lr']} eps {ppo['adam_eps']}, {ppo['n_steps']}-step rollouts, "
            f"{ppo['update_epochs']} epochs, clip {ppo['clip_ploss_coef']}, clipped value loss {ppo['clip_vloss']}, "
            f"gradient norm {ppo['max_grad_norm']}; `train_ppo_config.json` has every setting.")
        lines += best_checkpoint_lines(pretrained, recipe)
    else:
        lines.append("- Not trained by lerobot-crowdnav-train-ppo (no `train_ppo_config.json`).")
    lines += card_tail(repo_id, metrics, recipe, curve, run, "PPO", "PPO training, evaluation, this directory")
    data = ModelCardData(license="apache-2.0", library_name="lerobot", pipeline_tag="robotics",
                         tags=["robotics", "lerobot", "crowdnavpp", "reinforcement-learning", "crowd-navigation"])
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n" + "\n".join(lines) + "\n")


def push_policy_to_dir(pretrained: str | Path, repo_id: str, hub_dir: str | Path, overwrite: bool = False,
                       metrics_path: str | Path | None = None, curve: str | Path | None = None,
                       recipe: dict | None = None) -> Path:
    """Copy a ``pretrained_model`` directory to ``hub_dir/models/<org>/<name>`` with a model card:
    config, safetensors weights, processors, train config, and the learning curve ``curve`` (a
    PNG) when given. Pickled weights are refused."""
    import json

    pretrained = Path(pretrained)
    for required in (POLICY_CONFIG, WEIGHTS):
        if not (pretrained / required).exists():
            raise FileNotFoundError(f"{pretrained} is not a pretrained_model directory (no {required})")
    pickles = [p.name for p in pretrained.iterdir() if p.suffix in PICKLE_SUFFIXES]
    if pickles:
        raise ValueError(f"refusing pickled files {pickles}: the hub format holds safetensors only")
    files = [p for p in pretrained.iterdir() if p.is_file() and (
        p.name in POLICY_FILES
        or (p.name.startswith(("policy_preprocessor", "policy_postprocessor")) and p.suffix in (".json", ".safetensors")))]
    metrics = json.loads(Path(metrics_path).read_text()) if metrics_path else None
    curve = Path(curve) if curve else None
    card = policy_card(pretrained, repo_id, metrics, recipe, CURVE_FILE if curve else None)
    org, name = split_repo_id(repo_id)

    def fill(dst: Path) -> None:
        dst.mkdir(parents=True)
        for f in files:
            _copy_file(f, dst / f.name)
        if curve:
            _copy_file(curve, dst / CURVE_FILE)
        card.save(dst / "README.md")

    return _publish(Path(hub_dir) / "models" / org / name, overwrite, fill)


@dataclass
class PushConfig:
    # What to publish: dataset (a LeRobotDataset root) or policy (a pretrained_model directory).
    kind: str = "dataset"
    # Dataset root, or the policy's pretrained_model directory.
    root: Path | None = None
    # Repository name, <org>/<name>.
    repo_id: str = ""
    # Hub-format directory: the repository goes to <dir>/datasets|models/<org>/<name>/.
    push_to_hub_dir: Path | None = None
    # Replace an existing repository directory.
    overwrite: bool = False
    # Policies: a metrics.json of lerobot-crowdnav-eval to put in the model card.
    metrics: Path | None = None
    # Policies: a learning-curve PNG (a fine-tuning run's training_curves.png) to show in the card.
    curve: Path | None = None


def push(cfg: PushConfig) -> None:
    if cfg.root is None or cfg.push_to_hub_dir is None or not cfg.repo_id:
        raise ValueError("--root, --repo_id and --push_to_hub_dir are required")
    if cfg.kind == "dataset":
        print(push_dataset_to_dir(cfg.root, cfg.repo_id, cfg.push_to_hub_dir, cfg.overwrite))
    elif cfg.kind == "policy":
        print(push_policy_to_dir(cfg.root, cfg.repo_id, cfg.push_to_hub_dir, cfg.overwrite, cfg.metrics, cfg.curve))
    else:
        raise ValueError(f"--kind must be dataset or policy, got {cfg.kind!r}")


def main(argv: list[str] | None = None) -> None:
    run_cli(PushConfig, push, argv)


if __name__ == "__main__":
    main()
