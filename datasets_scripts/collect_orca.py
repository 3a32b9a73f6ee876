"""Collect ORCA demonstrations as a LeRobotDataset.

    python datasets_scripts/collect_orca.py --episodes 3000
    python datasets_scripts/collect_orca.py --help

See lerobot_crowdnav/data/collect.py (the stage) and lerobot_crowdnav/data/dataset.py (the data contract).
"""

from lerobot_crowdnav.data.collect import main

if __name__ == "__main__":
    main()
