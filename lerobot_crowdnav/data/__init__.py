"""The data layer: ``dataset`` (the ORCA demonstration writer, resumable) <- ``collect`` (the
collection CLI); ``hub`` (hub-format dataset and policy repositories); ``fast_loader`` (opt-in
fast reads of our LeRobotDatasets, installed by PDPO training). Imports nothing at package import.
"""
