"""Write an existing dataset as a Hub repository directory: <dir>/datasets/<org>/<name>/.

    python datasets_scripts/push_dataset.py --root=outputs/datasets/local/crowdnav_orca \
        --repo_id=local/crowdnav_orca --push_to_hub_dir=outputs/hub [--overwrite=true]
"""

from lerobot_crowdnav.data.hub import main

if __name__ == "__main__":
    main()
