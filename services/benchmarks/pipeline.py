"""`gridslam bench pipeline`: end-to-end throughput and latency from frame to the last stage's
pose, for the demo configuration, for the NuBot 640×480 stereo sequence and for a 1241×376
stereo sequence (the synthetic world rendered once with KITTI's image size and calibration into
a stereo folder of PNG files, read back as a dataset is, so that the renderer does not set the
pace), medians over repeated runs."""

from __future__ import annotations

import os
import socket
import statistics
import tempfile
from pathlib import Path

from services.common.frames import Camera
from services.common.settings import CommandParser
from services.evaluation.results import format_table
from services.pipeline.runner import RunConfig, run_pipeline
from services.source.calibration import write_calibration
from services.source.spec import open_source

# KITTI odometry sequence 00's left camera (P0) and stereo baseline, at its 1241×376 image size.
KITTI_CAMERA = Camera(fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, baseline=0.5371, width=1241, height=376)
NUBOT = Path("../shared/data/nubot_scene1")


def write_stereo_folder(spec: str, preset: str, camera: Camera, frames: int, folder: Path) -> Path:
    """Frames 0..frames-1 of ``spec`` as a stereo folder (``left/``, ``right/`` PNG and
    ``calibration.toml``), the layout ``stereo:FOLDER`` reads."""
    import cv2

    for side in ("left", "right"):
        (folder / side).mkdir(parents=True, exist_ok=True)
    write_calibration(folder / "calibration.toml", camera)
    with open_source(spec, preset=preset, calibration=camera, stop=frames) as source:
        for frame in source:
            for side, image in (("left", frame.left), ("right", frame.right)):
                if not cv2.imwrite(str(folder / side / f"{frame.seq:06d}.png"), image):
                    raise OSError(f"{folder / side}: cannot write frame {frame.seq}")
    return folder


def free_port() -> int:
    """A loopback port for one run's router (each run gets its own)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def measure(config: RunConfig, repeats: int, folder: Path) -> dict[str, float]:
    throughputs, p50s, p99s = [], [], []
    last = "map_online" if config.mapping else "gridcells"
    for repeat in range(repeats):
        run_config = config.model_copy(update={"listen": f"tcp/127.0.0.1:{free_port()}"})
        result = run_pipeline(run_config, folder / f"{last}-{repeat}-{len(list(folder.iterdir()))}")
        stage = result.metrics["stages"][last]
        throughputs.append(stage["throughput_fps"])
        p50s.append(stage["latency_ms"]["p50"])
        p99s.append(stage["latency_ms"]["p99"])
    return {"fps": statistics.median(throughputs), "p50": statistics.median(p50s), "p99": statistics.median(p99s)}


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench pipeline", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames per run (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration (default 3)")
    parser.add_argument("--nubot", type=Path, default=NUBOT, metavar="DIR",
                        help=f"the NuBot stereo sequence (default {NUBOT}; left out when missing)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        demo = RunConfig(source="synthetic:0", preset="synthetic", n_frames=args.frames)
        kitti_size = write_stereo_folder("synthetic:0", "synthetic", KITTI_CAMERA, args.frames, folder / "kitti_size")
        cases = {"demo (synthetic 320×240 stereo, stereo VO, grid cells, map)": demo}
        if args.nubot.is_dir():
            cases["NuBot 640×480 stereo (stereo VO, grid cells, map)"] = RunConfig(
                source=f"stereo:{os.path.abspath(args.nubot)}", preset="nubot")
        else:
            print(f"{args.nubot}: not found; the NuBot case is left out")
        # A stereo folder is a user's dataset: every service on its defaults, as a user's run is.
        cases["1241×376 stereo (synthetic frames read from PNG files; defaults)"] = RunConfig(
            source=f"stereo:{kitti_size}", egomotion="stereo")
        runs = folder / "runs"
        runs.mkdir()
        rows = []
        for label, config in cases.items():
            result = measure(config, args.repeats, runs)
            rows += [(f"{label}: throughput", result["fps"], "frames/s"),
                     (f"{label}: latency frame→pose p50", result["p50"], "ms"),
                     (f"{label}: latency frame→pose p99", result["p99"], "ms")]
    print(f"medians of {args.repeats} runs of {args.frames} frames each")
    print(format_table(rows))
    return 0
