"""`gridslam world`: describe a synthetic world: its layout, route, revisits and look-alike places.

The revisits come from the ground truth (services/source/synthetic.py, ``revisits``): each is a
stretch of frames that passes a place the route passed before, in the same or the opposite
direction; a look-alike pass is one through a copy of a place seen elsewhere (campus layout).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from services.common.errors import ConfigError
from services.source.spec import add_world_arguments, open_source, parse_world_flags


def register(subparsers) -> None:
    parser = subparsers.add_parser("world", help="describe a synthetic world: layout, route, revisits, look-alikes",
                                   description=__doc__.strip().splitlines()[0])
    parser.add_argument("--source", default="synthetic:0", metavar="synthetic:SEED", help="the world (default synthetic:0)")
    parser.add_argument("--preset", default="synthetic", help="source preset or preset file (default synthetic; campus)")
    add_world_arguments(parser)
    parser.add_argument("--min-length", type=float, default=2.0, metavar="M", help="shortest revisit listed (default 2 m)")
    parser.add_argument("--plot", type=Path, metavar="PNG", help="draw the layout and the route")
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the figures and the revisits as JSON")
    parser.set_defaults(func=run)


def run(args) -> int:
    from services.source.synthetic import SyntheticWorld, revisits

    world = open_source(args.source, preset=args.preset, mono=True, world=parse_world_flags(args.world, args.laps))
    if not isinstance(world, SyntheticWorld):
        raise ConfigError(f"gridslam world describes synthetic worlds, not {args.source}")
    found = revisits(world, min_length=args.min_length)
    summary = {
        "layout": world.config.layout, "route_m": round(world.route.length, 2), "laps": world.config.laps,
        "frames": len(world), "frames_per_lap": world.frames_per_lap, "speed_m_per_frame": round(world.speed, 4),
        "wall_segments": len(world.segments), "lamps": len(world.lamps),
        "lookalikes": [{"region": twin.region, "offset": twin.offset} for twin in (world.layout.twins if world.layout else ())],
    }
    for key, value in summary.items():
        if key != "lookalikes":
            print(f"{key:18} {value}")
    for twin in summary["lookalikes"]:
        print(f"look-alike         x {twin['region'][0]:g}…{twin['region'][1]:g}, y {twin['region'][2]:g}…{twin['region'][3]:g} "
              f"copied by ({twin['offset'][0]:g}, {twin['offset'][1]:g})")
    print("\n| frames | earlier frames | length (m) | direction | kind | distance (m) |")
    print("|---|---|---:|---|---|---:|")
    for r in found:
        print(f"| {r.frames[0]}–{r.frames[1]} | {r.earlier[0]}–{r.earlier[1]} | {r.length:.1f} | {r.direction} | "
              f"{'look-alike' if r.lookalike else 'revisit'} | {r.distance:.2f} |")
    print()
    for kind in (False, True):
        for direction in ("same", "opposite"):
            chosen = [r for r in found if r.lookalike == kind and r.direction == direction]
            print(f"{'look-alikes' if kind else 'revisits':11} {direction:8}: {len(chosen)} stretches, {sum(r.length for r in chosen):.0f} m, "
                  f"{sum(r.length > 20 for r in chosen)} longer than 20 m")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**summary, "revisits": [dataclasses.asdict(r) for r in found]}, indent=1))
        print(f"wrote {args.json}")
    if args.plot:
        from services.evaluation.plots import plot_layout
        from services.source import campus

        regions = {}
        if world.layout is not None:
            regions = {"look-alike (original)": [t.region for t in world.layout.twins],
                       "look-alike (copy)": [t.moved() for t in world.layout.twins]}
        labels = campus.NODES if world.config.layout == "campus" else {}
        plot_layout(args.plot, world.segments, world.poses[:, :2], regions, labels,
                    title=f"{args.source} ({world.config.layout}): {world.route.length:.0f} m per lap, {len(world)} frames")
        print(f"wrote {args.plot}")
    return 0
