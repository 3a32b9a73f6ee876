"""Data side: reading our LeRobotDatasets fast (``fast_loader``). The ORCA demonstration writer
(``collect``, ``dataset``) and hub I/O (``hub``) move here after the issue-11 merge."""
