"""Kill every long job at each named write/rename site, resume, compare with an uninterrupted run:
``python scripts/fault_injection.py --help`` (see lerobot_crowdnav/fault_injection.py, docs/resume.md)."""

from lerobot_crowdnav.fault_injection import main

if __name__ == "__main__":
    main()
