"""The parts pipeline: `python pipelines/parts.py [key=value ...] [--force STEP]` (same as `mmm pipeline
parts`)."""

import sys

from mmm.cli import main

if __name__ == "__main__":
    sys.exit(main(["pipeline", "parts", *sys.argv[1:]]))
