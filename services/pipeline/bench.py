"""`gridslam bench pipeline`: end-to-end throughput and latency from frame to the last stage's
pose, for the demo configuration and for a 1241×376 stereo sequence (the synthetic world
rendered with KITTI's image size and calibration), or for a source given with --source, medians
over repeated runs; with --egomotion-instances 1,2 one egomotion instance against two."""

from __future__ import annotations

import argparse
import socket
import statistics
import tempfile
from pathlib import Path

from services.evaluation.results import format_table
from services.pipeline.runner import RunConfig, run_pipeline
from services.source.calibration import write_calibration
from services.source.frames import Camera

# KITTI odometry sequence 00's left camera (P0) and stereo baseline, at its 1241×376 image size.
KITTI_CAMERA = Camera(fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, baseline=0.5371, width=1241, height=376)


def free_port() -> int:
    """A loopback port for one run's router (each run gets its own)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def measure(configs: dict[str, RunConfig], repeats: int, folder: Path) -> dict[str, dict]:
    """Medians over `repeats` runs of each config, the configs taking turns (so that a machine
    whose load changes meets them alike): throughput and latency to the last stage's pose, and
    each service's CPU time per frame in its handlers (`busy_cpu_s`, docs/pipeline.md)."""
    runs: dict[str, list[dict]] = {key: [] for key in configs}
    for repeat in range(repeats):
        for key, config in configs.items():
            last = "map" if config.mapping else "gridcells"
            run_config = config.model_copy(update={"listen": f"tcp/127.0.0.1:{free_port()}"})
            result = run_pipeline(run_config, folder / f"{last}-{repeat}-{len(list(folder.iterdir()))}")
            stage = result.metrics["stages"][last]
            frames = max(stage["frames"], 1)
            runs[key].append({"fps": stage["throughput_fps"], "p50": stage["latency_ms"]["p50"], "p99": stage["latency_ms"]["p99"],
                              **{f"cpu {name}": 1000 * status["extra"]["busy_cpu_s"] / frames
                                 for name, status in result.metrics["services"].items()
                                 if "busy_cpu_s" in status.get("extra", {})}})
    return {key: {name: statistics.median(run[name] for run in found if name in run) for name in found[0]}
            for key, found in runs.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gridslam bench pipeline", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames per run (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration (default 3)")
    parser.add_argument("--source", help="measure this source instead of the two built-in cases (e.g. "
                                         "stereo:../shared/data/nubot_scene1 with --preset nubot --egomotion stereo)")
    parser.add_argument("--preset", help="preset of --source")
    parser.add_argument("--egomotion", help="estimator of --source (default: the preset's)")
    parser.add_argument("--egomotion-instances", default="1", help="egomotion instances, or several counts to compare, "
                                                                   "comma separated (e.g. 1,2); the runs take turns")
    parser.add_argument("--stage-cpu", action="store_true", help="also each service's CPU time per frame in its handlers")
    args = parser.parse_args(argv)
    counts = [int(count) for count in args.egomotion_instances.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if args.source:
            cases = {args.source: RunConfig(source=args.source, preset=args.preset, egomotion=args.egomotion,
                                            n_frames=args.frames)}
        else:
            calibration = folder / "kitti_1241x376.toml"
            write_calibration(calibration, KITTI_CAMERA)
            demo = RunConfig(source="synthetic:0", preset="synthetic", n_frames=args.frames)
            cases = {
                "demo (synthetic 320×240 stereo, stereo VO, grid cells, map)": demo,
                "1241×376 stereo (synthetic, stereo VO, grid cells, map)": demo.model_copy(update={"calibration": calibration}),
            }
        rows = []
        for label, config in cases.items():
            configs = {(f"{label}, {count} egomotion instance{'s' if count > 1 else ''}" if counts != [1] else label):
                       config.model_copy(update={"egomotion_instances": count}) for count in counts}
            for name, result in measure(configs, args.repeats, folder).items():
                rows += [(f"{name}: throughput", result["fps"], "frames/s"),
                         (f"{name}: latency frame→pose p50", result["p50"], "ms"),
                         (f"{name}: latency frame→pose p99", result["p99"], "ms")]
                rows += [(f"{name}: CPU per frame, {key.removeprefix('cpu ')}", value, "ms")
                         for key, value in result.items() if args.stage_cpu and key.startswith("cpu ")]
    print(f"medians of {args.repeats} runs of {args.frames} frames each")
    print(format_table(rows))
    return 0
