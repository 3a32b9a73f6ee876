"""Reinforcement learning: one PPO loop for any actor-critic.

``ppo`` (the arithmetic) <- ``config`` (PPO and diffusion-PPO settings) <- ``agent`` (the
actor-critic protocol) <- ``loop`` (collect, advantages, update) <- ``families`` (the policy
families ``train_ppo`` trains) <- ``dppo`` (PDPO) and ``crowdnavpp`` (CrowdNav++, a family) as
actor-critics <- ``checkpoints``, ``run_log``, ``validation`` <- ``trainer`` (the shared PPO run)
<- ``finetune`` and ``train_ppo`` (the CLIs).
See docs/architecture.md.
"""
