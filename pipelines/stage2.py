"""The stage2 pipeline: `python pipelines/stage2.py [key=value ...] [--force STEP]` (same as `mmm pipeline
stage2`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "stage2", *sys.argv[1:]]))
