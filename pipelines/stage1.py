"""The stage1 pipeline: `python pipelines/stage1.py [key=value ...] [--force STEP]` (same as `mmm pipeline
stage1`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "stage1", *sys.argv[1:]]))
