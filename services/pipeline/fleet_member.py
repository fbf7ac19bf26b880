"""One robot of a fleet run (services/pipeline/fleet.py): `python -m services.pipeline.fleet_member
CONFIG.json OUT [--park]` runs the whole stack for the robot the RunConfig in CONFIG.json
describes, into its results folder OUT, and prints its table. Its own process, so that each
robot's recorder has the one Zenoh session of its process. With `--park`, a robot that has
finished its frames says so (`gridslam robot: parked`) and keeps its stack on the network, its
places there for the robots still driving, until SIGTERM."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

from services.common.errors import GridslamError

PARKED = "parked"   # what a parked member announces (services/pipeline/fleet.py waits for it)


def main(argv: list[str]) -> int:
    from services.evaluation.results import format_table
    from services.pipeline.report import summary_rows
    from services.pipeline.runner import RunConfig, run_pipeline

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    park = argv[2:] == ["--park"]
    if len(argv) != 2 + park:
        print("usage: python -m services.pipeline.fleet_member CONFIG.json OUT [--park]", file=sys.stderr)
        return 2
    stop = threading.Event()   # the fleet run stops its robots with SIGTERM: the run stops its services
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def parked() -> None:
        print(f"gridslam robot: {PARKED}", flush=True)
        stop.wait()

    try:
        config = RunConfig.model_validate_json(Path(argv[0]).read_text())
        result = run_pipeline(config, Path(argv[1]), stop_event=stop, park=parked if park else None)
    except GridslamError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(format_table(summary_rows(result.metrics)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
