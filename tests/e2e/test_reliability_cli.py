"""Every command line and config input that is wrong (issue 7): an unknown preset, a file that is
missing, unreadable or not TOML, a config value of the wrong type, an unknown source kind or
estimator, a malformed endpoint... Each must end with one line on stderr naming what is wrong,
and exit code 1, before it starts anything (no router, no service). Flags argparse itself
refuses (an invalid choice) end with exit code 2 and the error on the last line, under the
usage, as argparse does.

The table runs `gridslam`'s main() in this process (a process per case would cost a second and a
half of imports each); a few cases run as real processes to show the same line and exit code
come out of one."""

from __future__ import annotations

import contextlib
import io
import subprocess
import threading
from pathlib import Path

import pytest

import services.pipeline.runner  # noqa: F401  imported here: a case times its command, not the stack's first import
from services import cli
from tests.netutil import GRIDSLAM, REPO, endpoint, free_port

SOURCE = ["--source", "synthetic:0", "--preset", "synthetic"]


def files(folder: Path) -> dict[str, Path]:
    """Input files, each wrong in one way."""
    written = {
        "not_toml": "[[[ not toml",
        "run_wrong_type": "[run]\nn_frames = \"many\"\n",
        "run_unknown_key": "[run]\nframes = 3\n",
        "run_section_not_table": "run = 3\n",
        "runtime_wrong_type": "[runtime]\nmulticast_scouting = \"sometimes\"\n",
        "gridcells_wrong_type": "[gridcells]\nneurons = \"many\"\n",
        "loopclosure_wrong_type": "[loopclosure]\nwidth = \"wide\"\n",
        "egomotion_unknown": "[egomotion]\nwarp = 9\n",
        "egomotion_bad_estimator": "[egomotion]\nestimator = \"telepathy\"\n",
        "odometry_bad_estimator": "estimator = \"telepathy\"\n",
        "source_wrong_type": "[source]\nwindow = \"wide\"\n",
        "calibration_wrong_type": "fx = \"long\"\nfy = 1.0\ncx = 1.0\ncy = 1.0\n",
        "motion.csv": "forward,left,yaw\n0.1,0.0,0.0\nfast,0.0,0.0\n",
        "zenoh.json5": "{ this is: not json5 ]",
        "results/metrics.json": "{ not json",
    }
    paths = {}
    for name, text in written.items():
        path = folder / (name if "." in name else f"{name}.toml")
        path.parent.mkdir(exist_ok=True)
        path.write_text(text)
        paths[name] = path
    return paths


def cases(folder: Path) -> list[tuple[str, list[str], str]]:
    """(case id, gridslam arguments, text the error line must contain)."""
    f = files(folder)
    missing = folder / "absent"
    port = endpoint(free_port())   # nothing listens there
    run = ["run", "--listen", port]
    return [
        # gridslam run (and demo, its preset form)
        ("run: unknown preset", [*run, "--source", "synthetic:0", "--preset", "atlantis"], "atlantis"),
        ("run: unknown source kind", [*run, "--source", "floppy:/dev/fd0"], "floppy"),
        ("run: source without a target", [*run, "--source", "kitti"], "KIND:TARGET"),
        ("run: missing dataset", [*run, "--source", f"kitti:{missing}"], str(missing)),
        ("run: synthetic seed not a number", [*run, "--source", "synthetic:abc"], "seed"),
        ("run: missing config file", [*run, *SOURCE, "-c", str(missing)], str(missing)),
        ("run: config is a folder", [*run, *SOURCE, "-c", str(folder)], str(folder)),
        ("run: config not TOML", [*run, *SOURCE, "-c", str(f["not_toml"])], "not valid TOML"),
        ("run: config value of the wrong type", [*run, *SOURCE, "-c", str(f["run_wrong_type"])], "n_frames"),
        ("run: config unknown key", [*run, *SOURCE, "-c", str(f["run_unknown_key"])], "frames"),
        ("run: config section not a table", [*run, *SOURCE, "-c", str(f["run_section_not_table"])], "[run]"),
        ("run: missing calibration", [*run, *SOURCE, "--calibration", str(missing)], str(missing)),
        ("run: calibration of the wrong type", [*run, *SOURCE, "--calibration", str(f["calibration_wrong_type"])], "fx"),
        ("run: zero frames", [*run, *SOURCE, "--n-frames", "0"], "n_frames"),
        ("run: a bad flag value names the flag", [*run, *SOURCE, "--n-frames", "-3"], "--n-frames: "),
        ("run: a bad stride names its flag (not its [run] key, step)", [*run, *SOURCE, "--stride", "0"], "--stride: "),
        ("run: malformed listen endpoint", ["run", *SOURCE, "--listen", "nowhere"], "nowhere"),
        ("demo: unknown preset", ["demo", "--listen", port, "--preset", "atlantis"], "atlantis"),
        ("demo: config value of the wrong type", ["demo", "--listen", port, "-c", str(f["run_wrong_type"])], "n_frames"),
        # gridslam odometry and integrate (one process, no Zenoh)
        ("odometry: unknown estimator", ["odometry", *SOURCE, "--estimator", "telepathy"], "telepathy"),
        ("odometry: unknown preset", ["odometry", "--source", "synthetic:0", "--preset", "atlantis"], "atlantis"),
        ("odometry: missing dataset", ["odometry", "--source", f"images:{missing}", "--estimator", "scanline"], str(missing)),
        ("odometry: missing config", ["odometry", *SOURCE, "--config", str(missing)], str(missing)),
        ("odometry: config of an unknown estimator", ["odometry", *SOURCE, "--config", str(f["odometry_bad_estimator"])],
         "telepathy"),
        ("odometry: missing reference", ["odometry", *SOURCE, "--n-frames", "3", "--reference", str(missing),
                                         "--out", str(folder / "odometry")], str(missing)),
        ("integrate: missing input", ["integrate", str(missing)], str(missing)),
        ("integrate: a column not a number", ["integrate", str(f["motion.csv"])], "motion.csv"),
        ("integrate: unknown format", ["integrate", str(f["motion.csv"]), "--format", "xls"], "xls"),
        ("export table: not a results folder", ["export", "table", str(missing)], "metrics.json"),
        ("export table: metrics not JSON", ["export", "table", str(f["results/metrics.json"].parent)], "metrics.json: not readable JSON"),
        # gridslam service NAME: every service refuses bad settings before it looks for a router
        ("source: no source", ["service", "source", "-e", port], "source"),
        ("source: unknown source kind", ["service", "source", "-e", port, "--source", "floppy:0"], "floppy"),
        ("source: config value of the wrong type", ["service", "source", "-e", port, *SOURCE, "-c",
                                                    str(f["source_wrong_type"])], "window"),
        ("source: negative window", ["service", "source", "-e", port, *SOURCE, "--window", "-1"], "window"),
        ("egomotion: unknown preset", ["service", "egomotion", "-e", port, "--preset", "atlantis"], "atlantis"),
        ("egomotion: config unknown key", ["service", "egomotion", "-e", port, "-c", str(f["egomotion_unknown"])], "warp"),
        ("egomotion: config of an unknown estimator", ["service", "egomotion", "-e", port, "-c",
                                                       str(f["egomotion_bad_estimator"])], "telepathy"),
        ("gridcells: unknown preset", ["service", "gridcells", "-e", port, "--preset", "atlantis"], "atlantis"),
        ("gridcells: config value of the wrong type", ["service", "gridcells", "-e", port, "-c",
                                                       str(f["gridcells_wrong_type"])], "neurons"),
        ("gridcells: velocity scale not a number", ["service", "gridcells", "-e", port, "--velocity-scale", "fast"],
         "velocity_scale"),
        ("loopclosure: config value of the wrong type", ["service", "loopclosure", "-e", port, "-c",
                                                         str(f["loopclosure_wrong_type"])], "width"),
        ("expmap: map log in a folder that cannot exist", ["service", "expmap", "-e", port, "--store",
                                                           str(f["not_toml"] / "map.log")], "not_toml.toml"),
        ("expmap: map log not a journal", ["service", "expmap", "-e", port, "--store", str(f["not_toml"])], "not_toml.toml"),
        ("viewer: malformed HTTP address", ["service", "viewer", "-e", port, "--http", "here"], "here"),
        # the flags every process shares
        ("runtime: --cfg without a value", ["service", "gridcells", "-e", port, "--cfg", "lease"], "KEY:VALUE"),
        ("runtime: --cfg value Zenoh refuses", ["service", "gridcells", "-e", port, "--cfg", "transport/link/tx/lease:\"x\""],
         "Zenoh"),
        ("runtime: missing Zenoh config", ["service", "gridcells", "-e", port, "--zenoh-config", str(missing)], str(missing)),
        ("runtime: Zenoh config not JSON5", ["service", "gridcells", "-e", port, "--zenoh-config", str(f["zenoh.json5"])],
         "Zenoh"),
        ("runtime: robot name with a slash", ["service", "gridcells", "-e", port, "--robot", "a/b"], "robot"),
        ("runtime: config value of the wrong type", ["service", "gridcells", "-e", port, "-c", str(f["runtime_wrong_type"])],
         "multicast_scouting"),
        ("health: no router there", ["health", "-e", port, "--timeout", "1"], port),
        ("echo: no router there", ["echo", "-e", port, "grid/pose"], port),
        ("map export: missing map log", ["map", "export", str(missing)], str(missing)),
    ]


ARGPARSE_CASES = [   # refused by argparse: exit code 2, the error on the last line
    ("unknown command", ["teleport"], "invalid choice"),
    ("unknown service", ["service", "teleporter"], "invalid choice"),
    ("unknown estimator flag value", ["run", "--source", "synthetic:0", "--egomotion", "telepathy"], "invalid choice"),
    ("frames not a number", ["run", "--source", "synthetic:0", "--n-frames", "many"], "invalid int value"),
    ("velocity scale not a number", ["integrate", "motion.csv", "--velocity-scale", "fast"], "fast"),
    ("unknown benchmark", ["bench", "everything"], "invalid choice"),
]


def gridslam(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(GRIDSLAM + args, cwd=REPO, capture_output=True, text=True, timeout=60)


def in_process(args: list[str], timeout: float = 30.0) -> tuple[int | None, str]:
    """(exit code, stderr) of `gridslam ARGS` run by main() here; exit code None if it hangs
    (a service that took a bad setting would wait for its router), "raised ..." if an exception
    escaped main()."""
    outcome: list = [None, ""]

    def target() -> None:
        stderr = io.StringIO()
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            try:
                outcome[0] = cli.main(args)
            except SystemExit as exit_:
                outcome[0] = exit_.code
            except Exception as error:   # not a known error's one line: what escaped main() is the failure
                outcome[0] = f"raised {error!r}"
        outcome[1] = stderr.getvalue()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    return (None, "hung") if thread.is_alive() else (outcome[0], outcome[1])


def one_line_error(code, stderr: str, command: str, expected: str) -> bool:
    lines = stderr.strip().splitlines()
    return (code == 1 and len(lines) == 1 and lines[0].startswith(f"gridslam {command}: error: ")
            and expected in lines[0])


# Run as processes: a sample of the table, and echo (it sets signal handlers: main thread only).
REAL_PROCESS_CASES = ["run: config value of the wrong type", "gridcells: unknown preset", "integrate: missing input",
                      "echo: no router there"]


def test_every_bad_input_is_one_line_and_a_non_zero_exit(tmp_path):
    failures = []
    for name, args, expected in cases(tmp_path):
        if name.startswith("echo"):
            continue
        code, stderr = in_process(args)
        if not one_line_error(code, stderr, args[0], expected):
            failures.append(f"{name}: exit {code}, stderr: {stderr.strip()[-600:]!r}")
        if code is None:   # it hangs, holding the process's stderr: the cases after it cannot be read
            break
    assert not failures, "\n".join(failures)




@pytest.mark.parametrize("case", REAL_PROCESS_CASES)
def test_a_real_process_prints_the_same_line(tmp_path, case):
    name, args, expected = next(c for c in cases(tmp_path) if c[0] == case)
    done = gridslam(args)
    assert one_line_error(done.returncode, done.stderr, args[0], expected), done.stderr


@pytest.mark.parametrize("name, args, expected", ARGPARSE_CASES, ids=[case[0] for case in ARGPARSE_CASES])
def test_flags_argparse_refuses(name, args, expected):
    code, stderr = in_process(args)
    lines = stderr.strip().splitlines()
    assert code == 2 and lines[-1].startswith("gridslam") and expected in lines[-1], stderr
