"""Reinforcement learning: one PPO loop for any actor-critic.

``ppo`` (the arithmetic) <- ``config`` (PPO and diffusion-PPO settings) <- ``agent`` (the
actor-critic protocol) <- ``loop`` (collect, advantages, update) <- ``dppo`` (PDPO as an
actor-critic) <- ``checkpoints``, ``run_log``, ``validation`` <- ``finetune`` (the CLI run).
See docs/architecture.md.
"""
