"""One robot of a fleet run (services/pipeline/fleet.py): `python -m services.pipeline.fleet_member
CONFIG.json OUT` runs the whole stack for the robot the RunConfig in CONFIG.json describes, into
its results folder OUT, and prints its table. Its own process, so that each robot's recorder has
the one Zenoh session of its process."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

from services.common.errors import GridslamError


def main(argv: list[str]) -> int:
    from services.evaluation.results import format_table
    from services.pipeline.report import summary_rows
    from services.pipeline.runner import RunConfig, run_pipeline

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if len(argv) != 2:
        print("usage: python -m services.pipeline.fleet_member CONFIG.json OUT", file=sys.stderr)
        return 2
    stop = threading.Event()   # the fleet run stops its robots with SIGTERM: the run stops its services
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        config = RunConfig.model_validate_json(Path(argv[0]).read_text())
        result = run_pipeline(config, Path(argv[1]), stop_event=stop)
    except GridslamError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(format_table(summary_rows(result.metrics)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
