"""The main job (``lerobot-crowdnav-main``, driven by ``lerobot_crowdnav/pipeline.py``) in parts with
one job each, lowest first (docs/architecture.md):

``config`` (``MainConfig``), ``paths`` (the run folder and the stage names, which runs in progress
resume on), ``rows`` (the table row type both sources produce) <- ``stages`` (the resumable stage
runner and its wall times) <- ``training`` (demonstrations, pretraining with its DAgger segments,
fine-tuning stages, CrowdNav++ PPO, hub pushes) and ``evaluation`` (test-seed evaluations,
figures, the report) <- ``sources`` (the two sources of rows: ``ShippedModels``, the default, and
``TrainedFromScratch``).

Imports nothing at package import.
"""
