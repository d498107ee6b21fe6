"""`dovesei preview`: pictures of a world and of what the camera sees in it.

Writes into --out: `world.png` (for a synthetic world: a crop beside its label map and an overview;
for a world folder: the image beside its colour-coded labels), `camera.png` (the camera's view
and labels at 100, 50 and 20 m over one point) and, unless --no-perception, `perception.png`
(a camera frame beside its simulated heatmaps at noise 0, 1 and 2, and two consecutive frames
showing the flicker).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from dovesei.pictures.world import render_preview, render_views, world_sheet
from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import DoveseiError
from dovesei.sim.camera import CameraModel, render
from dovesei.sim.synthetic.generate import parse_spec
from dovesei.sim.world import load_world

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei preview", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default="synthetic",
                   help="synthetic[:seed=N,style=S,...], dubai, tiles:<url>,... or a world folder")
    p.add_argument("--at", metavar="X_M,Y_M", help="where the camera looks (default: the world's centre)")
    p.add_argument("--out", type=Path, default=Path("runs/preview"))
    p.add_argument("--no-perception", action="store_true", help="skip the simulated perception sheet")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from dovesei.pictures.perception import render_noise_preview

    try:
        world = load_world(args.world)
        if args.at:
            x_m, y_m = (float(v) for v in args.at.split(","))
        else:
            x_m, y_m = world.width_m / 2.0, world.height_m / 2.0
        if not world.contains(x_m, y_m):
            raise DoveseiError(f"--at {x_m:g},{y_m:g} is outside the world ({world.width_m:.0f} x {world.height_m:.0f} m)")
    except (DoveseiError, ValueError) as exc:
        print(f"dovesei preview: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    if args.world.startswith("synthetic"):
        written.append(render_preview(parse_spec(args.world), args.out / "world.png"))
    else:
        world_sheet(world, args.out / "world.png")
        written.append(args.out / "world.png")
    written.append(render_views(world, x_m, y_m, args.out / "camera.png"))
    if not args.no_perception and world.labels is not None:
        seen = world.perceived()  # the perception reads the world as a camera sees it
        image, labels, _ = render(seen, x_m, y_m, 100.0, 0.0, CameraModel())
        classes = {i: (c.name, c.safe) for i, c in seen.classes.items()}
        written.append(render_noise_preview(args.out / "perception.png", labels=labels, classes=classes,
                                            image_rgb=image))
    for path in written:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
