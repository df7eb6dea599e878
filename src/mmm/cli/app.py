"""The `mmm` parser, logging set-up and the mapping of errors to exit codes."""

from __future__ import annotations

import argparse
import logging
import sys

from mmm import __version__
from mmm.cli import data, generate, registry, train
from mmm.cli.common import CLIError, Parser
from mmm.config import conf_dir

# The subcommands in the order `mmm --help` lists them.
COMMANDS = (
    data.add_convert,
    data.add_data,
    train.add_train,
    train.add_tokenize,
    generate.add_generate,
    generate.add_edit,
    generate.add_generate_long,
    train.add_evaluate,
    train.add_ablate,
    train.add_pipeline,
    registry.add_promote,
    registry.add_import,
    registry.add_export,
    registry.add_dashboard,
    registry.add_models,
    data.add_render,
)


class _PrintVersion(argparse.Action):
    """`--version`: one line, never wrapped (argparse's own version action wraps a long path)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"mmm-motion {__version__}, configs from {conf_dir()}")
        parser.exit()


def build_parser() -> Parser:
    parser = Parser(prog="mmm", description="MMM: text-to-motion training, generation and tracking")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument(
        "--version",
        action=_PrintVersion,
        help="the package's version and the folder its configs are read from, then exit",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    return parser


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time (not the one at set-up), so that `main` can be
    called again after stderr was replaced, as tests and notebooks do."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


def _configure_logging(verbose: bool) -> None:
    """This package's INFO lines and everyone's warnings, once each (Lightning prints its own
    INFO lines through its own handler)."""
    fmt = logging.Formatter("%(levelname)s %(name)s: %(message)s")
    logging.basicConfig(level=logging.WARNING, handlers=[_StderrHandler()])
    for handler in logging.getLogger().handlers:
        handler.setLevel(logging.DEBUG if verbose else logging.WARNING)
        handler.setFormatter(fmt)
    ours = logging.getLogger("mmm")
    ours.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not ours.handlers:
        handler = _StderrHandler()
        handler.setFormatter(fmt)
        ours.addHandler(handler)
        ours.propagate = False


def parse_arguments(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line as a Namespace. argparse stops a command's `key=value` overrides at its
    first option, so overrides after one (`mmm train stage1 --resume last trainer.max_steps=20`)
    are appended to the others here, in their order, instead of refused as unrecognized."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and hasattr(args, "overrides") and all("=" in a and not a.startswith("-") for a in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv: list[str] | None = None) -> int:
    """Exit status 0 on success, 2 with a one-paragraph error (file, value, fix) on bad input."""
    args = parse_arguments(argv)
    _configure_logging(args.verbose)
    from mmm.config import ConfigError
    from mmm.data.arrays import DataError

    try:
        args.func(args)
    except (CLIError, DataError, ConfigError, FileExistsError, FileNotFoundError, ValueError) as e:
        if args.verbose:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
