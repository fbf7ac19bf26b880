"""`gridslam export mcap RESULTS_DIR`: write a run's results folder again as `run.mcap`, ROS 2
messages for Foxglove and `ros2 bag play` (docs/ecosystem.md); `gridslam export table RESULTS_DIR`:
print its Metric | Value | Unit table again from its metrics.json."""

from __future__ import annotations

from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser("export", help="export a run's results folder for other tools (mcap, table)")
    formats = parser.add_subparsers(dest="export_format", metavar="FORMAT", required=True)
    mcap = formats.add_parser("mcap", help="write RESULTS_DIR/run.mcap again: ROS 2 messages for Foxglove and ros2 bag play",
                              description="Write the poses of every stage, the experience map (replayed from its journal), "
                                          "the loop closures and the camera images (read again from the run's source) "
                                          "as ROS 2 messages in an MCAP file.")
    mcap.add_argument("folder", type=Path, metavar="RESULTS_DIR", help="a results folder of `gridslam run` or `demo`")
    mcap.add_argument("--out", type=Path, help="the MCAP file to write (default RESULTS_DIR/run.mcap)")
    mcap.add_argument("--no-images", dest="images", action="store_false",
                      help="leave the camera images out (they are read again from the run's source)")
    mcap.set_defaults(func=run)
    table = formats.add_parser("table", help="print the Metric | Value | Unit table of RESULTS_DIR/metrics.json",
                               description="Print the table `gridslam run` and `demo` print at their end again, from "
                                           "the results folder's metrics.json (Markdown, as README.md shows it).")
    table.add_argument("folder", type=Path, metavar="RESULTS_DIR", help="a results folder of `gridslam run` or `demo`")
    table.set_defaults(func=run_table)


def run(args) -> int:
    from services.pipeline.results_mcap import export_mcap

    path, counts = export_mcap(args.folder, args.out, args.images)
    for topic, number in sorted(counts.items()):
        print(f"{number:8d}  {topic}")
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return 0


def run_table(args) -> int:
    from services.evaluation.results import format_table
    from services.pipeline.report import read_metrics, summary_rows

    print(format_table(summary_rows(read_metrics(args.folder))))
    return 0
