"""Evaluation's commands and report, above ``rl/`` (docs/architecture.md): ``eval`` (the
``lerobot-crowdnav-eval`` CLI), ``baselines`` (``lerobot-crowdnav-baselines``), ``figures``,
``generalization``, ``report`` (the main job's report from typed inputs) and ``tables``
(``make tables``). What they measure with lives below ``data/`` and ``rl/``, in ``measure/``.

Imports nothing at package import.
"""
