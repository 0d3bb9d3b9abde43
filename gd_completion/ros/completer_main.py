"""Entry point of the `completer` executable: a SIGINT or SIGTERM during start-up (importing torch and rclpy,
loading the model, compiling kernels) exits 0 at once, without a traceback; the node's own handling (finish
the frame in hand, exit within 2 s) takes over once it is constructed. Nothing heavy is imported before the
handlers are in place."""
from __future__ import annotations

import os
import signal
import sys
from typing import Any


def _leave_during_start_up(signum: int, _frame: Any) -> None:
    sys.stderr.write(f"[completer] {signal.Signals(signum).name} during start-up: exiting\n")
    sys.stderr.flush()
    os._exit(0)   # nothing to finish yet: no frame in hand, no output written


def main(args: list[str] | None = None) -> int:
    """`ros2 run gd_completion completer` (see `gd_completion.ros.completer_node.main`)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _leave_during_start_up)
    argv = list(sys.argv[1:] if args is None else args)
    if "--version" in (argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv):
        from gd_completion import __version__  # the installed metadata only: no torch, no rclpy

        print(f"gd_completion {__version__}")
        return 0
    from gd_completion.ros.params import print_help, wants_help  # no torch, no rclpy: --help answers at once

    if wants_help(argv):
        try:
            print_help()
            sys.stdout.flush()
        except BrokenPipeError:   # `completer --help | head`: the reader left; not an error
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    from gd_completion.ros.completer_node import main as node_main

    return node_main(args, start_up_handler=_leave_during_start_up)


if __name__ == "__main__":
    sys.exit(main())
