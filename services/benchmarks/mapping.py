"""`gridslam bench mapping --sizes 1000,10000,100000 [--json FILE]`: cost per frame of template
matching and of the map update as the map grows, and the memory it takes.

For each size N, in a fresh process (so that its resident memory is its own):

- **matching**: N places of the place recognition (`--place-recognition`, default the
  loopclosure's) stored, then `--frames` frames observed, half of them revisits, half new views;
  each frame's matching is timed (services/benchmarks/matching.py says what is stored and timed
  for each), and the memory the places take is given per 1000.
- **map**: an ExperienceMap (the defaults: gtsam pose graph, metric closures) grown to N
  experiences by a robot driving laps of a 1 km circuit (one experience per frame, odometry with
  noise), with a closure to the experience one lap back every `--build-closure-every` frames;
  then `--frames` more frames timed, in which revisits confirm a closure on `--closure-frames`
  consecutive frames of every 100 (a closure burst, as a revisit gives).

- **restart**: the same map built again as the expmap service builds it (each frame journaled,
  checkpoints as its CheckpointPolicy decides, services/expmap/store.py), then restored from
  that journal `--restarts` times as a restarted service restores it: the journal read, the
  checkpoint loaded, the frames after it replayed. With `--replay`, also timed once: the whole
  journal replayed without checkpoints (what a restart cost before them).

The JSON (`--json`) is a list of objects with the keys size, match_ms_p50, match_ms_p99,
map_ms_p50, map_ms_p99 (every timed frame), closure_ms_p50 (the median of the timed frames that
carry a closure), rss_mib, junctions (the experiences in the solver, optimizers.PoseGraph),
restart_ms_p50 (journal_ms_p50 of it reading the journal),
tail_frames, build_s (the map built with its checkpoints), replay_s (with `--replay`).
`--restart-only` skips templates and timed frames.

`--journal FILE --frames-list 1000,2000,...` measures the restart on the first N frames of a
recorded map journal instead (re-journaled with checkpoints as the service would have written
them), e.g. one of the looping docker-compose stack.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from services.common.settings import CommandParser
from services.loopclosure.places import DEFAULT_PLACE_RECOGNITION, PLACE_RECOGNITIONS

CIRCUIT_M = 1000.0   # one lap: 1000 experiences 1 m apart


def rss_mib() -> float:
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def circuit_pose(k: int) -> tuple[float, float, float]:
    """The true pose of frame k on the circuit (a circle, counter-clockwise, 1 m per frame)."""
    radius = CIRCUIT_M / (2 * math.pi)
    angle = k / radius
    return radius * math.sin(angle), radius * (1 - math.cos(angle)), angle


def map_stream(size: int, frames: int, build_every: int, burst: int, seed: int):
    """(frame, odometry pose, template, closure or None, timed?) for `size` + `frames` frames."""
    from services.common.geometry import between, compose
    from services.expmap.links import ClosureInput

    rng = np.random.default_rng(seed)
    lap = int(CIRCUIT_M)
    odometry = (0.0, 0.0, 0.0)
    covariance = tuple(np.diag([0.02 ** 2, 0.02 ** 2, 0.002 ** 2]).ravel())
    for k in range(size + frames):
        if k:
            step = between(circuit_pose(k - 1), circuit_pose(k))
            odometry = compose(odometry, (step[0] + rng.normal(0, 0.01), step[1] + rng.normal(0, 0.01),
                                          step[2] + rng.normal(0, 0.001)))
        timed = k >= size
        closing = k >= lap and ((timed and (k - size) % 100 < burst) or (not timed and k % build_every == 0))
        closure = None
        if closing:   # the place of one lap ago, measured within 2 cm and 0.1°
            z = between(circuit_pose(k - lap), circuit_pose(k))
            closure = ClosureInput(k - lap, k - lap, "stereo", z[0] + rng.normal(0, 0.02), z[1] + rng.normal(0, 0.02),
                                   z[2] + rng.normal(0, 0.002), covariance)
        yield k, odometry, k, closure, timed


def measure(size: int, frames: int, build_every: int, burst: int, seed: int, place_recognition: str) -> dict:
    """One size, in this process."""
    from services.benchmarks.matching import measure_matching
    from services.expmap.graph import ExperienceMap, MapParams

    matching = measure_matching(place_recognition, size, frames, np.random.default_rng(seed))

    experience_map = ExperienceMap(MapParams())
    map_ms, closure_ms = [], []
    for frame, odometry, template, closure, timed in map_stream(size, frames, build_every, burst, seed):
        started = time.perf_counter()
        experience_map.step(frame, odometry, template, closure)
        if timed:
            elapsed = 1e3 * (time.perf_counter() - started)
            map_ms.append(elapsed)
            if closure is not None:
                closure_ms.append(elapsed)
    return {"size": size, "place_recognition": place_recognition, **matching,
            "map_ms_p50": float(np.median(map_ms)), "map_ms_p99": float(np.percentile(map_ms, 99)),
            "closure_ms_p50": float(np.median(closure_ms)) if closure_ms else None, "rss_mib": rss_mib(),
            "experiences": len(experience_map), "closures_accepted": experience_map.closures["accepted"],
            "junctions": len(experience_map.state()["junctions"])}


def measure_restart(steps: list, params, restarts: int, whole: bool) -> dict:
    """Journal `steps` as the service does, then restart from the journal `restarts` times (and,
    with `whole`, replay all its steps without checkpoints once)."""
    from services.expmap.graph import ExperienceMap
    from services.expmap.store import MapStore, replay

    with tempfile.TemporaryDirectory(prefix="gridslam-restart-") as folder:
        path = Path(folder) / "experience_map.log"
        store, experience_map = MapStore(path, params), ExperienceMap(params)
        started = time.perf_counter()
        for step in steps:
            store.append(step)
            step.apply(experience_map)
            if store.checkpoint_due(experience_map):
                store.write_checkpoint(*store.checkpoint(experience_map), {})
        build_s = time.perf_counter() - started
        store.close()
        journal_ms, restart_ms = [], []
        for _ in range(restarts):
            started = time.perf_counter()
            store = MapStore(path, params)
            opened = time.perf_counter()
            store.rebuild()
            restart_ms.append(1e3 * (time.perf_counter() - started))
            journal_ms.append(1e3 * (opened - started))
            store.close()
        checkpoints = store.checkpoints
        started = time.perf_counter()
        if whole:
            replay(ExperienceMap(params), steps, [])
        replay_s = time.perf_counter() - started if whole else None
    return {"frames": len(steps), "experiences": len(experience_map), "links": len(experience_map.links),
            "checkpoints": len(checkpoints), "tail_frames": len(steps) - (checkpoints[-1] if checkpoints else 0),
            "build_s": build_s, "journal_ms_p50": float(np.median(journal_ms)),
            "restart_ms_p50": float(np.median(restart_ms)), "restart_ms_max": float(np.max(restart_ms)), "replay_s": replay_s}


def stream_steps(size: int, build_every: int, seed: int) -> list:
    """The benchmark's map of `size` experiences as journal steps."""
    from services.expmap.store import Step

    return [Step(frame, 0.05 * frame, odometry, template, closure)
            for frame, odometry, template, closure, _ in map_stream(size, 0, build_every, 0, seed)]


def journal_restarts(journal: Path, frames: list[int], restarts: int, whole: bool) -> int:
    """The restart figures of the first N frames of a recorded journal, one N per row."""
    from services.expmap.export import read_log

    log = read_log(journal)
    print(f"{journal}: restarts from the first N of its {len(log.steps)} frames, re-journaled with checkpoints; "
          f"medians of {restarts}")
    print()
    print("| frames | experiences, links | map built, with checkpoints (s) | checkpoints | frames after the last "
          "| restart p50 (ms) | max | of which the journal | whole journal replayed, no checkpoints (s) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for count in frames:
        row = measure_restart(log.steps[:count], log.params, restarts, whole)
        print(f"| {row['frames']:,} | {row['experiences']:,}, {row['links']:,} | {row['build_s']:.1f} | {row['checkpoints']} "
              f"| {row['tail_frames']} | {row['restart_ms_p50']:.0f} | {row['restart_ms_max']:.0f} "
              f"| {row['journal_ms_p50']:.0f} | {replayed(row)} |", flush=True)
    return 0


def replayed(row: dict) -> str:
    return "—" if row["replay_s"] is None else f"{row['replay_s']:.1f}"


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench mapping", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1000,10000,100000", help="comma-separated map sizes (templates and experiences)")
    parser.add_argument("--frames", type=int, default=400, help="frames timed per size")
    parser.add_argument("--closure-frames", type=int, default=10, help="frames of every 100 timed that confirm a closure")
    parser.add_argument("--build-closure-every", type=int, default=2000, help="a closure every this many frames while growing")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--restarts", type=int, default=5, help="restarts timed per size (medians)")
    parser.add_argument("--replay", action="store_true", help="also time the whole journal replayed without checkpoints")
    parser.add_argument("--restart-only", action="store_true", help="time restarts only (no templates, no timed frames)")
    parser.add_argument("--json", type=Path, help="write the results as a JSON list to this file")
    parser.add_argument("--journal", type=Path, help="time restarts from this recorded map journal instead")
    parser.add_argument("--frames-list", default="1000,2000,4000,8000",
                        help="with --journal: comma-separated numbers of its first frames to restart from")
    parser.add_argument("--place-recognition", choices=PLACE_RECOGNITIONS, default=DEFAULT_PLACE_RECOGNITION,
                        help=f"the place recognition whose matching is timed (default {DEFAULT_PLACE_RECOGNITION})")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)   # internal: measure one size here, print JSON
    args = parser.parse_args(argv)
    if args.journal is not None:
        return journal_restarts(args.journal, [int(v) for v in args.frames_list.split(",") if v.strip()], args.restarts,
                                args.replay)
    if args.one is not None:
        from services.expmap.graph import MapParams

        row = {} if args.restart_only else measure(args.one, args.frames, args.build_closure_every, args.closure_frames,
                                                   args.seed, args.place_recognition)
        restart = measure_restart(stream_steps(args.one, args.build_closure_every, args.seed), MapParams(), args.restarts,
                                  args.replay)
        print(json.dumps({"size": args.one, **row, **restart}))
        return 0
    sizes = [int(v) for v in args.sizes.split(",") if v.strip()]
    results = []
    if args.restart_only:
        print(f"restarts: medians of {args.restarts}")
        print()
        print("| size | frames, experiences, links | map built, with checkpoints (s) | checkpoints | frames after the last "
              "| restart p50 (ms) | max | of which the journal | whole journal replayed, no checkpoints (s) |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    else:
        print(f"{args.frames} frames timed per size; place recognition {args.place_recognition}; closures on "
              f"{args.closure_frames} of every 100; medians and p99 in ms")
        print()
        print("| size | match p50 | match p99 | places MiB per 1k | map p50 | map p99 | closure p50 | RSS MiB "
              "| restart p50 (of which the journal) | frames after the checkpoint |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for size in sizes:
        command = [sys.executable, "-m", "services.cli", "bench", "mapping", "--one", str(size), "--frames", str(args.frames),
                   "--closure-frames", str(args.closure_frames), "--build-closure-every", str(args.build_closure_every),
                   "--seed", str(args.seed), "--restarts", str(args.restarts),
                   "--place-recognition", args.place_recognition] + \
            ["--replay"] * args.replay + ["--restart-only"] * args.restart_only
        row = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
        results.append(row)
        if args.restart_only:
            print(f"| {size:,} | {row['frames']:,}, {row['experiences']:,}, {row['links']:,} | {row['build_s']:.1f} "
                  f"| {row['checkpoints']} | {row['tail_frames']} | {row['restart_ms_p50']:.0f} | {row['restart_ms_max']:.0f} "
                  f"| {row['journal_ms_p50']:.0f} | {replayed(row)} |", flush=True)
            continue
        print(f"| {size:,} | {row['match_ms_p50']:.2f} | {row['match_ms_p99']:.2f} | {row['places_mib_per_1k']:.2f} "
              f"| {row['map_ms_p50']:.2f} "
              f"| {row['map_ms_p99']:.2f} | {row['closure_ms_p50'] or 0:.2f} | {row['rss_mib']:.0f} "
              f"| {row['restart_ms_p50']:.0f} ({row['journal_ms_p50']:.0f}) | {row['tail_frames']} |", flush=True)
    if len(results) > 1 and not args.restart_only:
        first, last = results[0], results[-1]
        print()
        print(f"{last['size']:,} vs {first['size']:,}: matching ×{last['match_ms_p50'] / first['match_ms_p50']:.2f}, "
              f"map update ×{last['map_ms_p50'] / first['map_ms_p50']:.2f}, closure frames "
              f"×{(last['closure_ms_p50'] or 0) / (first['closure_ms_p50'] or 1):.2f} (medians); the places take "
              f"{last['places_mib_per_1k']:.2f} MiB per 1k")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0
