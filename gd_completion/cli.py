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


class _VersionAction(argparse.Action):
    """--version: `gd_completion <version>` (package.xml's, through the installed metadata), read only when asked."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the version (gd_completion X.Y.Z) and exit")

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        from gd_completion import __version__

        print(f"gd_completion {__version__}")
        parser.exit()


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Parser with every subcommand registered, or only `command` when it names one."""
    parser = argparse.ArgumentParser(prog="gd-completion", description=__doc__)
    parser.add_argument("--version", action=_VersionAction)
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
