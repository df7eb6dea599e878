"""The evaluate pipeline: `python pipelines/evaluate.py [key=value ...] [--force STEP]` (same as `mmm
pipeline evaluate`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "evaluate", *sys.argv[1:]]))
