"""`gd-completion`: offline tools (convert, complete, play, render, train, train-refiner, evaluate, demo)."""
from __future__ import annotations

import argparse
import importlib
import sys

from gd_completion.errors import GDCompletionError

# Subcommand -> module exposing register(subparsers), which sets a `func` default on its parser. A module
# imports only what its parser needs at the top (no torch): `gd-completion VERB ...` imports VERB's module alone.
SUBCOMMANDS = {
    "demo": "gd_completion.tools.demo",
    "train": "gd_completion.tools.train",
    "train-refiner": "gd_completion.tools.train_refiner",
    "convert": "gd_completion.tools.convert",
    "complete": "gd_completion.tools.complete",
    "complete-cloud": "gd_completion.tools.complete_cloud",
    "play": "gd_completion.tools.play",
    "render": "gd_completion.tools.render",
    "evaluate": "gd_completion.tools.evaluate",
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Parser with every subcommand registered, or only `command` when it names one."""
    parser = argparse.ArgumentParser(prog="gd-completion", description=__doc__)
    subparsers = parser.add_subparsers(dest="command", required=True)
    names = [command] if command in SUBCOMMANDS else list(SUBCOMMANDS)
    for name in names:
        importlib.import_module(SUBCOMMANDS[name]).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; bad input and unwritable outputs give a one-line error and exit code 2."""
    argv = sys.argv[1:] if argv is None else argv
    command = next((arg for arg in argv if not arg.startswith("-")), None)  # gd-completion has no option values
    args = build_parser(command).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except GDCompletionError as error:
        message = str(error)
    except OSError as error:  # a file the system refused outside the writers, which raise OutputError for theirs
        message = f"{error.filename}: {error.strerror}" if error.filename and error.strerror else str(error)
    print(f"gd-completion {args.command}: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
