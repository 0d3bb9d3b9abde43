"""Progress bars of the offline tools: tqdm on stderr, off with --quiet or when stderr is not a terminal."""
from __future__ import annotations

import sys

from tqdm import tqdm


def progress_bar(desc: str, unit: str, *, total: int | None = None, quiet: bool = False) -> tqdm:
    """A tqdm bar counting `unit` ('frames'); use `update(n)` and `close()`, or it as a context manager."""
    return tqdm(total=total, desc=desc, unit=f" {unit}", file=sys.stderr, disable=True if quiet else None)
