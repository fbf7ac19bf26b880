"""Golden results: the figures of the demo and of NuBot that every run of them is held to, and
that README.md states. Counts (frames, templates, experiences, closures and the map's decisions)
must be equal; accuracy figures (ATE, endpoint error) within GOLDEN_TOLERANCE of the golden value.
Figures that depend on the machine's load (wall time, latency, throughput) are not held.

Written from a results folder of the run the golden file names (`command`):

    gridslam demo --out results/demo
    python -m tests.golden demo results/demo            # writes tests/golden/demo.json
    gridslam run --source images:../shared/data/nubot_scene1/left --out results/nubot
    python -m tests.golden nubot results/nubot          # writes tests/golden/nubot.json

and `gridslam export table results/demo` prints the README's table from the same folder."""

from __future__ import annotations

import json
import sys
from importlib import metadata
from pathlib import Path

from services.evaluation import metrics
from services.evaluation.revisits import RevisitRanges
from services.evaluation.trajectory import read_tum
from services.pipeline.report import read_metrics, summary_rows

FOLDER = Path(__file__).resolve().parent
GOLDEN_TOLERANCE = 0.02
# Rows of the run's table that depend on the load, not on what the run computed.
LOAD_UNITS = ("ms", "frames/s", "s")
COMMANDS = {
    "demo": "gridslam demo",
    "nubot": "gridslam run --source images:../shared/data/nubot_scene1/left",
}
# NuBot has no ground truth: its loop (frames 180-204 back where frames up to 40 were, as README.md
# says) and LIBVISO2's path, which the paper compares against.
NUBOT_LOOP = "180-204:0-40"
NUBOT_REVISITS = range(180, 205)
LIBVISO2 = Path("nubot_scene1") / "libviso2_egomotion.csv"
# The libraries whose release changes the figures (rendering, features, matching, the solvers):
# a golden file records their versions (constraints.txt pins them for make and CI).
COMPUTING = ("opencv-python-headless", "numpy", "scipy", "gtsam", "chroma-hnswlib")


def versions() -> dict[str, str]:
    return {name: metadata.version(name) for name in COMPUTING}


def figures(name: str, folder: Path, shared_data: Path | None = None) -> dict:
    """The held figures of the run `name` in the results folder `folder`: the load-independent
    rows of its table, and for NuBot the loop's closures and the ATE against LIBVISO2's path."""
    result = read_metrics(folder)
    held = {metric: value for metric, value, unit in summary_rows(result) if unit not in LOAD_UNITS and value is not None}
    if name == "nubot":
        loop = RevisitRanges.parse(NUBOT_LOOP)
        closures = [(c["frame"], c["matched_frame"]) for c in result["summary"]["loop_closures"]]
        held["revisit frames joined by a confirmed closure"] = len({f for f, m in closures if loop.is_true(f, m)})
        held["closures between frames the loop does not mark"] = sum(not loop.is_true(f, m) for f, m in closures)
        if shared_data is not None:
            from services.offline.odometry import load_reference

            reference = load_reference(shared_data / LIBVISO2)
            for stage in ("egomotion", "map"):
                estimate = read_tum(Path(folder) / f"{stage}.tum")
                held[f"{stage}: ATE RMSE (Sim(3)) against LIBVISO2"] = metrics.ate(
                    estimate, reference.select(list(range(len(estimate)))), align="sim3")["rmse"]
    return held


def load(name: str) -> dict:
    return json.loads((FOLDER / f"{name}.json").read_text())


def differences(golden: dict, found: dict) -> list[str]:
    """Each held figure that differs: a count that is not equal, an accuracy figure off by more
    than GOLDEN_TOLERANCE of the golden value, a figure missing on either side."""
    problems = []
    for metric in sorted(golden.keys() | found.keys()):
        if metric not in found or metric not in golden:
            problems.append(f"{metric}: golden {golden.get(metric, '—')}, this run {found.get(metric, '—')}")
            continue
        want, got = golden[metric], found[metric]
        if isinstance(want, float) and isinstance(got, (int, float)):
            if abs(got - want) > GOLDEN_TOLERANCE * abs(want):
                problems.append(f"{metric}: golden {want:.6g}, this run {got:.6g} ({100 * (got - want) / want:+.1f} %)")
        elif got != want:
            problems.append(f"{metric}: golden {want}, this run {got} (counts must be equal)")
    return problems


def check(name: str, folder: Path, shared_data: Path | None = None) -> dict:
    """Assert the run in `folder` reproduces the golden figures of `name`; its figures."""
    found = figures(name, folder, shared_data)
    golden = load(name)
    problems = differences(golden["figures"], found)
    recorded, installed = golden.get("versions", {}), versions()
    if problems and recorded != installed:
        problems.append(f"recorded with {recorded}, this run has {installed}: install with -c constraints.txt")
    assert not problems, f"{COMMANDS[name]} differs from tests/golden/{name}.json:\n" + "\n".join(problems)
    return found


def readme_rows(text: str) -> dict[str, str]:
    """Metric → value of every `| metric | value | unit |` row of a Markdown text."""
    rows = {}
    for line in text.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 3:
            rows.setdefault(cells[0], cells[1])
    return rows


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in COMMANDS:
        print(f"usage: python -m tests.golden {{{','.join(COMMANDS)}}} RESULTS_DIR", file=sys.stderr)
        return 2
    name, folder = argv[0], Path(argv[1])
    from tests.conftest import SHARED_DATA

    golden = {"command": COMMANDS[name], "figures": figures(name, folder, SHARED_DATA if name == "nubot" else None),
              "versions": versions()}
    path = FOLDER / f"{name}.json"
    path.write_text(json.dumps(golden, indent=2, sort_keys=True) + "\n")
    print(f"wrote {path}")
    return 0
