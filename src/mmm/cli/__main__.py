"""`python -m mmm.cli ARGS`: the `mmm` command."""

import sys

from mmm.cli.app import main

sys.exit(main())
