"""Measuring a policy, below ``data/`` and ``rl/`` so that DAgger and PPO validation use the same code
as the evaluation commands (docs/architecture.md): ``episodes`` (``run_episodes``,
``LearnedPolicy``, ``json_safe``), ``metrics`` (episode records, the benchmark metrics, markdown
rows), ``plots`` (matplotlib figures) and ``parameters`` (checkpoint parameter counts).

Imports nothing at package import.
"""
