"""`python -m gd_completion.warmup`: compile the CPU kernels once (numba caches them on disk), so that the first
`completer` start after an install is ready in seconds instead of about a minute. `scripts/install.sh` runs it."""
from __future__ import annotations

import sys
import time


def main() -> int:
    """Complete one synthetic vehicle with the shipped weights: every kernel of a forward and of the merge is
    compiled (or found in numba's cache)."""
    from gd_completion.kernels import kernels_cached
    from gd_completion.pipeline import VehicleCompleter

    start = time.perf_counter()
    cached = kernels_cached()
    completer = VehicleCompleter.from_checkpoint(None, num_threads=1)
    try:
        completer.warm_up()
    finally:
        completer.close()
    state = "loaded from numba's cache (or recompiled after a source change)" if cached else "compiled and cached"
    print(f"gd_completion warm-up: CPU kernels {state}; {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
