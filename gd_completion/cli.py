"""`gd-completion`: offline tools (convert, complete, play, render, train, evaluate, demo)."""
from __future__ import annotations

import argparse
import importlib
import sys

from gd_completion.errors import GDCompletionError

# Each module exposes register(subparsers) and sets a `func` default on its parser.
SUBCOMMAND_MODULES = (
    "gd_completion.tools.demo",
    "gd_completion.tools.train",
    "gd_completion.tools.convert",
    "gd_completion.tools.complete",
    "gd_completion.tools.play",
    "gd_completion.tools.render",
    "gd_completion.tools.evaluate",
)


def build_parser() -> argparse.ArgumentParser:
    """Parser with every subcommand registered."""
    parser = argparse.ArgumentParser(prog="gd-completion", description=__doc__)
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; bad input gives a one-line error and exit code 2."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except GDCompletionError as error:
        print(f"gd-completion {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
