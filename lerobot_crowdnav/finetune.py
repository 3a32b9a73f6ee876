"""``lerobot-crowdnav-finetune`` and ``accelerate launch -m lerobot_crowdnav.finetune``: the CLI
entry of diffusion-PPO fine-tuning, which lives in ``lerobot_crowdnav.rl.finetune``."""

from .rl.finetune import main

if __name__ == "__main__":
    main()
