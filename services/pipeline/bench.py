"""`gridslam bench pipeline`: end-to-end throughput and latency from frame to the last stage's
pose, for the demo configuration and for a 1241×376 stereo sequence (the synthetic world
rendered with KITTI's image size and calibration), medians over repeated runs."""

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


def measure(config: RunConfig, repeats: int, folder: Path) -> dict[str, float]:
    throughputs, p50s, p99s = [], [], []
    last = "map" if config.mapping else "gridcells"
    for repeat in range(repeats):
        run_config = config.model_copy(update={"listen": f"tcp/127.0.0.1:{free_port()}"})
        result = run_pipeline(run_config, folder / f"{last}-{repeat}-{len(list(folder.iterdir()))}")
        stage = result.metrics["stages"][last]
        throughputs.append(stage["throughput_fps"])
        p50s.append(stage["latency_ms"]["p50"])
        p99s.append(stage["latency_ms"]["p99"])
    return {"fps": statistics.median(throughputs), "p50": statistics.median(p50s), "p99": statistics.median(p99s)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gridslam bench pipeline", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames per run (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration (default 3)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        calibration = folder / "kitti_1241x376.toml"
        write_calibration(calibration, KITTI_CAMERA)
        demo = RunConfig(source="synthetic:0", preset="synthetic", n_frames=args.frames)
        cases = {
            "demo (synthetic 320×240 stereo, stereo VO, grid cells, map)": demo,
            "1241×376 stereo (synthetic, stereo VO, grid cells, map)": demo.model_copy(update={"calibration": calibration}),
        }
        rows = []
        for label, config in cases.items():
            result = measure(config, args.repeats, folder)
            rows += [(f"{label}: throughput", result["fps"], "frames/s"),
                     (f"{label}: latency frame→pose p50", result["p50"], "ms"),
                     (f"{label}: latency frame→pose p99", result["p99"], "ms")]
    print(f"medians of {args.repeats} runs of {args.frames} frames each")
    print(format_table(rows))
    return 0
