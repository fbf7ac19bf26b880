"""The settings of a whole-stack run (`gridslam run` and `demo`), declared once: the keys of the
config file's `[run]` table (the runner's RunConfig, services/pipeline/runner.py) and the flags of
the command (services/cli/run.py) are derived from these (`config_fields`, `add_flag`). The
settings the run passes on to a service are declared with that service (GridStageParams,
MapParams, GraphParams, ...); the ones here are the run's own. Standard library only, beside
the router's default endpoint."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.common.runtime import DEFAULT_ROUTER
from services.common.settings import REQUIRED, setting
from services.common.stages import ESTIMATORS

VIEW_ADDRESS = "127.0.0.1:8080"   # --view with no address
FOXGLOVE_PORT = 8765              # --foxglove with no port


@dataclass(frozen=True)
class RunParams:
    """A run's own settings (table `[run]`, flags of `gridslam run`)."""

    LABEL = "run"

    source: str = setting(REQUIRED, help="source spec: kitti:PATH, stereo:PATH (NuBot layout), images:PATH, video:FILE, "
                                         "camera:N, synthetic:SEED, rosbag:PATH or ros2:TOPIC")
    preset: str | None = setting(None, help="dataset preset for every service that has one (listed at the end of "
                                            "gridslam run --help), or a preset file (a base preset and per-service tables, "
                                            "docs/sources.md)")
    calibration: Path | None = setting(None, help="calibration TOML file for the source (its keys: at the end of "
                                                  "gridslam run --help; default: the dataset's own, or the preset's)")
    camera_height: float | None = setting(None, gt=0.0, help="camera height above the ground, m: a metric scale for "
                                                             "the mono estimator (ground plane)")
    config_file: Path | None = setting(None, help="gridslam TOML config file: [run] and one table per service, over "
                                                  "the preset (passed to every service)")
    start: int = setting(0, ge=0, help="first frame index")
    n_frames: int | None = setting(None, ge=1, help="process only this many frames (default: all)")
    step: int = setting(1, ge=1, help="take every N-th frame")
    egomotion: str | None = setting(None, choices=ESTIMATORS,
                                    help="ego-motion estimator (default: the preset's, else scanline; what each needs: "
                                         "at the end of gridslam run --help)")
    egomotion_instances: int = setting(1, ge=1, le=16,
                                       help="ego-motion processes sharing the frames: 1 runs the estimator frame after "
                                            "frame, more run it in blocks, with the same results whatever their number, "
                                            "and at least N + 1 blocks of frames are kept in flight (docs/pipeline.md)")
    mapping: bool = setting(True, help="run loop closure and the experience map (the map stage)")
    mcap: bool = setting(True, help="write run.mcap: ROS 2 messages with the camera images, for Foxglove and ros2 bag "
                                    "play (extra `ros`)")
    view: str | None = setting(None, help=f"also run the viewer, serving HTTP on HOST:PORT ({VIEW_ADDRESS} when no "
                                          f"address is given); a run that ends by itself is served on until Ctrl-C")
    foxglove: int | None = setting(None, ge=0, le=65535,
                                   help=f"also serve the run live to Foxglove, ws://127.0.0.1:PORT ({FOXGLOVE_PORT} when "
                                        f"no port is given; extra `foxglove`); a run that ends by itself is served on "
                                        f"until Ctrl-C")
    listen: str = setting(DEFAULT_ROUTER, help="the run's router endpoint (outside clients connect here)")
    connect: str | None = setting(None, help="use the router at ENDPOINT instead of starting one (e.g. several robots "
                                             "on one network)")
    robot: str = setting("robot0", help="robot name, the <robot> chunk of every key")
    ros2: bool = setting(False, help="also run the ros2 service: the run as the node gridslam of a ROS 2 graph over "
                                     "Zenoh (rmw_zenoh; docs/ecosystem.md)")
    window: int = setting(8, ge=1, help="frames in flight between the source and the last stage")
    stall_timeout: float = setting(60.0, gt=0.0, help="fail when no frame completes for this many seconds")


@dataclass(frozen=True)
class RunOutputParams:
    """Where a run writes (command line only: no config key)."""

    out: Path | None = setting(None, help="results folder (default results/<timestamp>/ with a latest link)")
    overwrite: bool = setting(False, help="replace an earlier run in --out (a folder that holds one is refused "
                                          "otherwise)")
