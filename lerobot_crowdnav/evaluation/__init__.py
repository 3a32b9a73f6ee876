"""Evaluation, in two layers (docs/architecture.md):

- below ``data/`` and ``rl/``: ``metrics`` (episode records, the benchmark metrics, markdown rows),
  ``episodes`` (``run_episodes``, ``LearnedPolicy``, ``json_safe``), ``plots`` (matplotlib figures),
  ``parameters`` (checkpoint parameter counts);
- above ``rl/``: ``eval`` (the ``lerobot-crowdnav-eval`` CLI), ``baselines``, ``figures`` and
  ``report`` (the main job's report from typed inputs).

Imports nothing at package import.
"""
