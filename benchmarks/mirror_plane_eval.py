"""`gd-completion evaluate` with the measured merge's mirror plane moved by a share of what the seen side gives
(`merge.PLANE_SHARE`, the node's `mirror_plane`; 1 by default) where that offset is at least a minimum move
(`merge.PLANE_MIN_MOVE`, 0.02 lengths by default), everywhere the evaluation merges: PandaSet, box noise, the
synthetic sets, classification, track fusion and reuse. The arguments after --share / --min-move are evaluate's.
`--share 0` gives the box's own plane (the defaults before 2026-12-07); `--share 1 --min-move 0` every move:

    python benchmarks/mirror_plane_eval.py --share 1 --min-move 0 --output /tmp/mirror_plane \
        --ablation-checkpoints docs/evaluation/ablation/ggd_nc128.pt docs/evaluation/ablation/ggd_nc256.pt \
        docs/evaluation/ablation/ggd_nc512.pt
"""
from __future__ import annotations

import argparse
import sys

from gd_completion import merge


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--share", type=float, required=True, help="the mirror plane's share, in [0, 1]")
    parser.add_argument("--min-move", type=float, default=merge.PLANE_MIN_MOVE,
                        help=f"smallest offset that moves the plane, lengths (default {merge.PLANE_MIN_MOVE})")
    args, rest = parser.parse_known_args()
    if not 0.0 <= args.min_move < merge.PLANE_LIMIT:
        parser.error(f"--min-move must be in [0, {merge.PLANE_LIMIT})")
    # before the pipeline and the settings read them
    merge.PLANE_SHARE = merge.check_plane_share(args.share)
    merge.PLANE_MIN_MOVE = args.min_move
    from gd_completion.cli import main as cli_main
    return cli_main(["evaluate", *rest])


if __name__ == "__main__":
    sys.exit(main())
