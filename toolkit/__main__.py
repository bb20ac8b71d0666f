"""``python -m toolkit``: inspect and convert Gaussian scene files.

    python -m toolkit info SCENE            summary of a .safetensors or .ply scene
    python -m toolkit convert IN OUT        convert between .safetensors and .ply (by extension)
"""

from __future__ import annotations

import os
import sys
from typing import Sequence

from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.io import check_not_an_input
from toolkit.scene import GaussianScene


def main(argv: Sequence[str] | None = None) -> int:
    ap = CliParser(prog="python -m toolkit", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("info", help="print a summary of a scene file")
    p.add_argument("scene")
    p = sub.add_parser("convert", help="convert a scene between .safetensors and .ply")
    p.add_argument("src")
    p.add_argument("dst")
    args = ap.parse_args(argv)
    if args.cmd == "info":
        scene = GaussianScene.read(args.scene)
        print(f"{args.scene}")
        print(scene.summary())
    elif args.cmd == "convert":
        check_not_an_input(args.dst, [args.src], "dst")
        ext = os.path.splitext(args.dst)[1].lower()
        if ext not in (".ply", ".safetensors"):  # before reading: a typo costs nothing
            raise ToolkitError(f"{args.dst}: unknown output extension; expected .safetensors or .ply")
        scene = GaussianScene.read(args.src)
        # Each writer refuses, before writing, what its reader would refuse (toolkit.ply, GaussianScene.save).
        if ext == ".ply":
            scene.to_ply(args.dst)
        else:
            scene.save(args.dst)
        print(f"wrote {args.dst} ({scene.num_gaussians} Gaussians)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
