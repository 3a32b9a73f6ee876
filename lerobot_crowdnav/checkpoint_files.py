"""The file names of a policy checkpoint, in one place: a lerobot ``pretrained_model`` directory
(config, weights, processors) plus what this project adds beside it. The PPO runs and agents write
them, the parameter counts and the hub push read them, the main job finds its runs by them.
"""

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
