"""`gd-completion evaluate` with the measured merge's mirror plane moved by a share of what the seen side gives
(`merge.PLANE_SHARE`, the node's `mirror_plane`; 0 by default), everywhere the evaluation merges: PandaSet, box
noise, the synthetic sets, classification, track fusion and reuse. The arguments after --share are evaluate's.

    python benchmarks/mirror_plane_eval.py --share 1 --output docs/evaluation/mirror_plane \
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
    args, rest = parser.parse_known_args()
    merge.PLANE_SHARE = merge.check_plane_share(args.share)   # before the pipeline and the settings read it
    from gd_completion.cli import main as cli_main
    return cli_main(["evaluate", *rest])


if __name__ == "__main__":
    sys.exit(main())
