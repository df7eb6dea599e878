"""The `mmm` command: data, training, generation and editing, the model registry.

Every subcommand exits 0 on success and 2 with a one-paragraph error (file, value, fix) on bad input.

    app.py       the parser (every command in order), logging, errors -> exit codes
    common.py    CLIError, the parser class, .npy input and output
    data.py      convert, data synth/stats/check/preview, render
    train.py     train, tokenize, evaluate, ablate, pipeline
    generate.py  generate, edit, generate-long
    options.py   the options those three share (the sampling flags: SamplingConfig's fields)
    registry.py  promote, import, export, dashboard, models list

Building the parser imports no torch or mlflow: each command imports the library inside its
function, so `mmm --help` stays fast.
"""

from mmm.cli.app import build_parser, main
from mmm.cli.common import CLIError

__all__ = ["CLIError", "build_parser", "main"]
