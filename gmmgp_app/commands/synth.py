"""``gmmgp synth``: a synthetic scene with exact ground truth."""

from __future__ import annotations

from .options import EXIT_OK, add_command

EXAMPLES = """examples:
  gmmgp synth street --out out/street          # scan.npz + mesh.ply + scene.json
  gmmgp synth sphere --out out/sphere --seed 3
  gmmgp synth street --out out/big --density 4  # about 4x the points"""


def add_parser(subparsers):
    p = add_command(subparsers, "synth", help="make a synthetic scene with exact ground truth",
                    epilog=EXAMPLES)
    p.add_argument("name", help="scene: plane, sphere, box, street, street2, street_van")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--density", type=float, default=1.0, help="scan density multiplier")
    return p


def run(args) -> int:
    from ..synth import write_scene

    paths = write_scene(args.name, args.out, seed=args.seed, density=args.density)
    for k, v in paths.items():
        print(f"{k:6s} {v}")
    return EXIT_OK
