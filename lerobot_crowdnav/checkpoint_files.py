"""The file names of a policy checkpoint, in one place: a lerobot ``pretrained_model`` directory
(config, weights, processors) plus what this project adds beside it. The PPO runs and agents write
them, the parameter counts and the hub push read them, the main job finds its runs by them.
"""

import hashlib
from pathlib import Path

POLICY_CONFIG = "config.json"  # lerobot: the policy's config (its "type")
WEIGHTS = "model.safetensors"  # lerobot: the policy's weights
CRITIC = "critic.safetensors"  # a fine-tuned PDPO policy's critic (rl/dppo.py)
TRAIN_CONFIG = "train_config.json"  # lerobot-train's settings (pretraining), carried by PPO runs
FINETUNE_CONFIG = "finetune_config.json"  # lerobot-crowdnav-finetune's settings
TRAIN_PPO_CONFIG = "train_ppo_config.json"  # lerobot-crowdnav-train-ppo's settings
SOURCE_PREFIX = "source_"  # + a run's settings file: the settings of the run it continued
BEST_INFO = "best.json"  # beside checkpoints/best/pretrained_model: when and why it is the best

# lerobot's checkpoint layout (lerobot.utils.constants), which the PPO runs write too:
# <run>/checkpoints/<step>/{pretrained_model, training_state}; lerobot-train's step counter.
PRETRAINED_MODEL = "pretrained_model"
TRAINING_STATE = "training_state"
TRAINING_STEP = "training_step.json"  # in lerobot-train's training_state/


# Beside an evaluation's (or a checkpoint choice's) metrics.json: the digest of the policy it
# evaluated, so that the main job runs it again when another policy stands at that path.
POLICY_DIGEST = "policy.sha256"


def policy_digest(model_dir: Path) -> str:
    """SHA-256 over a model directory's weights and configs (``*.safetensors``, ``*.json``)."""
    h = hashlib.sha256()
    for path in sorted(Path(model_dir).iterdir()):
        if path.is_file() and path.suffix in (".safetensors", ".json"):
            h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()
