"""The full pipeline: `python pipelines/full.py [key=value ...] [--force STEP]` (same as `mmm pipeline
full`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "full", *sys.argv[1:]]))
