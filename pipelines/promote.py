"""The promote pipeline: `python pipelines/promote.py [key=value ...] [--force STEP]` (same as `mmm pipeline
promote`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "promote", *sys.argv[1:]]))
