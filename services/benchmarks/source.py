"""`gridslam bench source`: how fast the synthetic world renders, and how long it takes to build.

Prints a Markdown table of medians over the frames rendered (one core: OpenCV threads are
limited to 1 unless --threads says otherwise).
"""

from __future__ import annotations

import statistics
import time

import cv2

from services.common.settings import CommandParser
from services.source.spec import load_preset
from services.source.synthetic import SyntheticWorld, WorldConfig, default_camera


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench source", description=__doc__)
    parser.add_argument("--frames", type=int, default=200, help="frames rendered per configuration")
    parser.add_argument("--sizes", default="320x240,640x480", help="comma-separated image sizes WxH")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", help="the world's settings from a source preset (e.g. campus; default: the corridor's defaults)")
    args = parser.parse_args(argv)
    cv2.setNumThreads(args.threads)
    settings = {}
    if args.preset:
        _, settings = load_preset(args.preset)
        settings.pop("grey", None)
    config = WorldConfig(seed=args.seed, **settings)
    print(f"Synthetic world rendering ({config.layout}), seed {args.seed}, {args.frames} frames each "
          f"(spread over the route), OpenCV threads {args.threads}\n")
    print("| image | camera | build (s) | textures (MB) | median ms/frame | frames/s (median) |")
    print("|---|---|---:|---:|---:|---:|")
    for size in args.sizes.split(","):
        width, height = parse_size(size)
        for mono in (True, False):
            started = time.perf_counter()
            world = SyntheticWorld(config, camera=default_camera(width, height), mono=mono)
            build = time.perf_counter() - started
            textures = (world._wall_atlas.nbytes + world._plane_atlas.nbytes) / 2**20
            times = []
            for seq in range(0, len(world), max(1, len(world) // args.frames))[:args.frames]:
                started = time.perf_counter()
                world[seq]
                times.append(time.perf_counter() - started)
            median = statistics.median(times)
            print(f"| {width}×{height} | {'mono' if mono else 'stereo'} | {build:.2f} | {textures:.0f} | {1000 * median:.2f} | {1 / median:.0f} |")
    return 0
