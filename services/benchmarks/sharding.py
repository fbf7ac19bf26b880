"""`gridslam bench sharding`: one egomotion instance against several on the same source (by
default NuBot's 640×480 stereo sequence, every service on the nubot preset): throughput and
latency from frame to map/pose, and each service's CPU time per frame in its handlers, medians
over repeated runs that take turns (docs/pipeline.md, "Several egomotion instances")."""

from __future__ import annotations

import os
import statistics
import tempfile
from pathlib import Path

from services.benchmarks.pipeline import free_port
from services.common.settings import CommandParser
from services.common.stages import INTEGRATORS
from services.evaluation.results import format_table
from services.pipeline.runner import RunConfig, run_pipeline

NUBOT = Path("../shared/data/nubot_scene1")


def run_once(config: RunConfig, folder: Path) -> dict[str, float]:
    """Throughput, latency p50/p99 to map/pose (grid/pose without mapping), `cpu <service>`: ms of
    handler CPU per frame, and `process <service>`: ms of the whole process's CPU per frame while
    serving (every thread: the frames' decoding, Zenoh's and OpenCV's threads)."""
    result = run_pipeline(config.model_copy(update={"listen": f"tcp/127.0.0.1:{free_port()}"}), folder)
    stage = result.metrics["stages"]["map_online" if config.mapping else "gridcells"]
    frames = max(stage["frames"], 1)
    return {"fps": stage["throughput_fps"], "p50": stage["latency_ms"]["p50"], "p99": stage["latency_ms"]["p99"],
            **{f"{label} {name}": 1000 * status["extra"][key] / frames
               for name, status in result.metrics["services"].items()
               for label, key in (("cpu", "busy_cpu_s"), ("process", "serving_cpu_s")) if key in status.get("extra", {})}}


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench sharding", description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=f"stereo:{NUBOT}", help=f"source spec (default stereo:{NUBOT})")
    parser.add_argument("--preset", default="nubot", help="preset of every service (default nubot)")
    parser.add_argument("--egomotion", default="stereo", help="estimator (default stereo)")
    parser.add_argument("--instances", default="1,2", help="egomotion instance counts to compare (default 1,2)")
    parser.add_argument("--integrator", choices=INTEGRATORS, default="grid", help="path integrator (default grid)")
    parser.add_argument("--no-mapping", action="store_true", help="skip loop closure and the experience map")
    parser.add_argument("--frames", type=int, help="frames per run (default: the whole source)")
    parser.add_argument("--repeats", type=int, default=5, help="runs per instance count (default 5)")
    args = parser.parse_args(argv)
    counts = [int(count) for count in args.instances.split(",")]
    source = args.source if not args.source.startswith("stereo:") else f"stereo:{os.path.abspath(args.source[7:])}"
    config = RunConfig(source=source, preset=args.preset, egomotion=args.egomotion, n_frames=args.frames,
                       integrator=args.integrator, mapping=not args.no_mapping)
    runs: dict[int, list[dict[str, float]]] = {count: [] for count in counts}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):   # the counts take turns: a machine whose load changes meets them alike
            for count in counts:
                runs[count].append(run_once(config.model_copy(update={"egomotion_instances": count}),
                                            Path(tmp) / f"{count}-{repeat}"))
    rows = []
    for count, found in runs.items():
        label = f"{count} egomotion instance{'s' if count > 1 else ''}"
        median = {name: statistics.median(run.get(name, 0.0) for run in found) for name in found[0]}
        rows += [(f"{label}: throughput", median["fps"], "frames/s"),
                 (f"{label}: throughput, each run", " ".join(f"{run['fps']:.1f}" for run in found), "frames/s"),
                 (f"{label}: latency frame→pose p50", median["p50"], "ms"),
                 (f"{label}: latency frame→pose p99", median["p99"], "ms")]
        for prefix, title in (("cpu ", "CPU per frame"), ("process ", "process CPU per frame")):
            rows += [(f"{label}: {title}, {name.removeprefix(prefix)}", value, "ms")
                     for name, value in median.items() if name.startswith(prefix)]
        services = sum(value for name, value in median.items() if name.startswith("process "))
        rows += [(f"{label}: process CPU per frame, all services (not the router, the recorder)", services, "ms"),
                 (f"{label}: throughput the cores allow ({os.cpu_count()} × 1000 / all services)",
                  os.cpu_count() * 1000 / services, "frames/s")]
    if 1 in runs and len(counts) > 1:
        one = statistics.median(run["fps"] for run in runs[1])
        rows += [(f"throughput, {count} instances / 1", statistics.median(run["fps"] for run in runs[count]) / one, "")
                 for count in counts if count != 1]
    stages = f"{args.integrator} integrator{', no mapping' if args.no_mapping else ''}"
    print(f"{config.source}, {args.egomotion}, preset {args.preset}, {stages}: medians of {args.repeats} runs per count, taking turns")
    print(format_table(rows))
    return 0
