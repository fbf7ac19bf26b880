"""`gridslam world`: describe a synthetic world: its layout, route, revisits and look-alike places.

The revisits come from the ground truth (services/source/world/revisits.py): each is a
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
    parser.add_argument("--closures", type=Path, metavar="CSV",
                        help="a run's loop_closures.csv on this world: score its closures against the ground truth "
                             "and say which revisits got an accepted closure")
    parser.set_defaults(func=run)


def run(args) -> int:
    from services.source.synthetic import SyntheticWorld
    from services.source.world.revisits import revisits

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
    if args.closures:
        print()
        for line in score_closures(world, found, args.closures):
            print(line)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**summary, "revisits": [dataclasses.asdict(r) for r in found]}, indent=1))
        print(f"wrote {args.json}")
    if args.plot:
        from services.evaluation.plots import plot_layout
        from services.source.world import campus

        regions = {}
        if world.layout is not None:
            regions = {"look-alike (original)": [t.region for t in world.layout.twins],
                       "look-alike (copy)": [t.moved() for t in world.layout.twins]}
        labels = campus.NODES if world.config.layout == "campus" else {}
        plot_layout(args.plot, world.segments, world.poses[:, :2], regions, labels,
                    title=f"{args.source} ({world.config.layout}): {world.route.length:.0f} m per lap, {len(world)} frames")
        print(f"wrote {args.plot}")
    return 0


def score_closures(world, found: list, path: Path) -> list[str]:
    """Lines scoring a run's loop_closures.csv on this world: confirmed, accepted, rejected and
    unmeasured closures, true and false by the ground truth (the two frames within TRUE_CLOSURE_M), and for
    each kind of revisit longer than 20 m how many got at least one accepted closure."""
    import csv

    from services.evaluation.revisits import same_place

    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as error:
        raise ConfigError(f"{path}: cannot read ({error.strerror or error})") from None
    if rows and not {"frame", "matched_frame", "accepted"} <= set(rows[0]):
        raise ConfigError(f"{path}: not a loop_closures.csv (no frame, matched_frame, accepted columns)")
    poses = world.poses
    fates = {}
    for row in rows:
        frame, matched = int(row["frame"]), int(row["matched_frame"])
        if max(frame, matched) >= len(poses):
            raise ConfigError(f"{path}: frame {max(frame, matched)} is beyond this world's {len(poses)} frames")
        fate = "accepted" if row["accepted"] == "true" else "unmeasured" if row.get("measurement") == "none" else "rejected"
        true = same_place(poses[frame, :2], poses[matched, :2])
        fates.setdefault(fate, []).append((frame, matched, true))
    lines = ["| closures | count | true | false |", "|---|---:|---:|---:|",
             f"| confirmed | {len(rows)} | {sum(t for v in fates.values() for *_, t in v)} | "
             f"{sum(not t for v in fates.values() for *_, t in v)} |"]
    for fate in ("accepted", "rejected", "unmeasured"):
        chosen = fates.get(fate, [])
        lines.append(f"| {fate} | {len(chosen)} | {sum(t for *_, t in chosen)} | {sum(not t for *_, t in chosen)} |")
    lines.append("")
    for lookalike, direction in ((False, "same"), (False, "opposite"), (True, "same"), (True, "opposite")):
        long = [r for r in found if r.lookalike == lookalike and r.direction == direction and r.length > 20]
        kind = "look-alike passes" if lookalike else "revisits"
        hit = [r for r in long if _closing(r, fates.get("accepted", []))]
        lines.append(f"{kind} ({direction} direction) longer than 20 m with an accepted closure: {len(hit)} of {len(long)}")
        for r in long:
            if r not in hit:
                confirmed = sum(len(_closing(r, fates.get(fate, []))) for fate in ("rejected", "unmeasured"))
                lines.append(f"  without: frames {r.frames[0]}–{r.frames[1]} ({r.length:.0f} m) over {r.earlier[0]}–{r.earlier[1]}: "
                             f"{confirmed} true closure(s) confirmed there, none accepted")
    return lines


def _closing(revisit, closures: list) -> list:
    """The true closures (frame, matched, true) made during this revisit: to its earlier pass or to
    any pass before it of the same place (a template is stored when a place is first seen)."""
    return [c for c in closures if revisit.frames[0] <= c[0] <= revisit.frames[1] and c[2]]
