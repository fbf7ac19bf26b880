"""The command line's flags: every flag spelling that existed before a rename still parses (the
old ones noted), no parser reads an abbreviation, a bad value names its flag, and
`gridslam --version` answers."""

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import build_parser
from services.cli.service import SERVICES, service_parser
from services.common.errors import ConfigError
from services.common.settings import renamed_flags

REPO = Path(__file__).resolve().parents[2]

# Every flag of every command and service as it was before the renames (COMMAND or "service NAME"
# → flags; SUB:--flag for a command's sub-commands). A flag renamed since keeps this spelling.
FLAGS = {
    'demo': (
        '--calibration --camera-height --camera-info-topic --closure --config --connect --decoder '
        '--egomotion --egomotion-instances --fov --foxglove --heading --image-topic --integrator --laps '
        '--listen --localize --map --map-optimizer --modules --n-frames --no-mapping --no-mcap '
        '--odom-topic --out --overwrite --place-recognition --preset --right-image-topic --robot '
        '--ros-distro --ros-domain-id --ros-namespace --ros2 --ros2-keys --source --start --step '
        '--stereo-tolerance --view --world -c -e -l'),
    'run': (
        '--calibration --camera-height --camera-info-topic --closure --config --connect --decoder '
        '--egomotion --egomotion-instances --fov --foxglove --heading --image-topic --integrator --laps '
        '--listen --localize --map --map-optimizer --modules --n-frames --no-mapping --no-mcap '
        '--odom-topic --out --overwrite --place-recognition --preset --right-image-topic --robot '
        '--ros-distro --ros-domain-id --ros-namespace --ros2 --ros2-keys --source --start --step '
        '--stereo-tolerance --view --world -c -e -l'),
    'router': (
        '--cfg --config --connect --listen --mode --multicast-scouting --no-multicast-scouting --robot '
        '--zenoh-config -c -e -l'),
    'echo': (
        '--cfg --config --connect --count --listen --mode --multicast-scouting --no-multicast-scouting '
        '--robot --zenoh-config -c -e -l -n'),
    'health': (
        '--all-robots --cfg --config --connect --listen --mode --multicast-scouting '
        '--no-multicast-scouting --robot --timeout --zenoh-config -c -e -l'),
    'schemas': (
        'export:--out'),
    'integrate': (
        '--decoder --format --heading --modules --n-frames --network-rotation --noise-rot --noise-trans '
        '--out --seed --step --velocity-scale'),
    'simulate': (
        '--decoders --firing-frames --frame-period --heading --modules --n-frames --noise-rot '
        '--noise-trans --out --seed --step --velocity-scale'),
    'calibrate': (
        '--force --modules --neurons --out'),
    'odometry': (
        '--calibration --camera-info-topic --config --estimator --image-topic --laps --n-frames '
        '--odom-topic --out --preset --reference --right-image-topic --shard-block --source --start '
        '--step --stereo-tolerance --stop --world'),
    'map': (
        'build:--closure build:--config build:--images build:--integrator build:--map-optimizer '
        'build:--match-threshold build:--n-frames build:--noise-rot-deg build:--noise-trans '
        'build:--odometry build:--out build:--place-recognition build:--preset build:--same-place-radius '
        'build:--seed build:--source build:--title build:--tolerance build:-c export:--config '
        'export:--graph export:--plot export:--preset export:--reference export:--tum export:-c '
        'route:--from route:--map route:--out route:--reference route:--to sweep:--config sweep:--images '
        'sweep:--integrator sweep:--n-frames sweep:--noise-rot-deg sweep:--noise-trans sweep:--odometry '
        'sweep:--place-recognition sweep:--preset sweep:--same-place-radius sweep:--seed sweep:--source '
        'sweep:--thresholds sweep:--tolerances sweep:-c'),
    'world': (
        '--closures --json --laps --min-length --plot --preset --source --world'),
    'export': (
        'mcap:--no-images mcap:--out'),
    'vocabulary': (
        '--branching --depth --out --source'),
    'service source': (
        '--ack-topic --adaptive-window --calibration --camera-info-topic --cfg --config --connect --fov '
        '--image-topic --instance --laps --listen --live-window --loop --mode --mono --multicast-scouting '
        '--no-adaptive-window --no-multicast-scouting --odom-topic --origin --preset --rate '
        '--resend-acknowledged --resend-after --resume --right-image-topic --robot --ros-distro '
        '--ros-domain-id --ros-namespace --ros2-keys --source --start --step --stereo-tolerance --stop '
        '--wait-for --window --world --zenoh-config -c -e -l'),
    'service egomotion': (
        '--camera-height --cfg --config --connect --estimator --instance --listen --mode '
        '--multicast-scouting --no-multicast-scouting --preset --robot --shard-block --zenoh-config -c -e '
        '-l'),
    'service gridcells': (
        '--cfg --checkpoint --config --connect --decoder --heading --instance --integrator --listen '
        '--mode --modules --multicast-scouting --no-multicast-scouting --preset --robot --step '
        '--velocity-scale --zenoh-config -c -e -l'),
    'service loopclosure': (
        '--cfg --closure --config --connect --instance --listen --localize --map --match-threshold --mode '
        '--multicast-scouting --no-multicast-scouting --place-recognition --preset --robot --store '
        '--zenoh-config -c -e -l'),
    'service expmap': (
        '--cfg --closure --config --connect --instance --listen --localize --map --map-optimizer --mode '
        '--multicast-scouting --no-multicast-scouting --out --preset --robot --store --zenoh-config -c -e '
        '-l'),
    'service viewer': (
        '--allow-remote --cfg --config --connect --http --instance --listen --mode --multicast-scouting '
        '--no-multicast-scouting --rate --robot --zenoh-config -c -e -l'),
    'service foxglove': (
        '--allow-remote --cfg --config --connect --host --instance --listen --mode --multicast-scouting '
        '--no-multicast-scouting --port --robot --zenoh-config -c -e -l'),
    'service ros2': (
        '--cfg --config --connect --instance --listen --mode --multicast-scouting --no-multicast-scouting '
        '--robot --ros-distro --ros-domain-id --ros-namespace --ros2-keys --zenoh-config -c -e -l'),
}


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    found = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found |= {f"{name}:{flag}" for name, sub in action.choices.items() for flag in option_strings(sub)}
        else:
            found |= set(action.option_strings)
    return found


def parsers() -> dict[str, argparse.ArgumentParser]:
    """Every command's and every service's parser, by name."""
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    return {**commands, **{f"service {name}": service_parser(name)[0] for name in SERVICES}}


def all_parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from all_parsers(sub)


def test_every_flag_that_existed_still_exists():
    now = parsers()
    missing = {name: sorted(set(flags.split()) - option_strings(now[name])) for name, flags in FLAGS.items()}
    assert {name: flags for name, flags in missing.items() if flags} == {}


def test_no_parser_reads_an_abbreviation():
    for name, parser in parsers().items():
        for each in all_parsers(parser):
            assert each.allow_abbrev is False, (name, each.prog)
    # The bench programs build their parsers when they run: none builds its own.
    for path in (REPO / "services").rglob("*.py"):
        text = path.read_text()
        assert "argparse.ArgumentParser(" not in text, path
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "--source", "synthetic:0", "--map-opt", "gtsam"])
    args = build_parser().parse_args(["run", "--source", "synthetic:0", "--map", "results/earlier"])
    assert str(args.map) == "results/earlier" and args.map_optimizer is None


def test_the_old_spellings_read_as_the_new_ones_with_a_note():
    parse = build_parser().parse_args
    old = parse(["run", "--source", "synthetic:0", "--step", "3", "--step", "lattice"])
    new = parse(["run", "--source", "synthetic:0", "--stride", "3", "--step-source", "lattice"])
    assert (old.stride, old.step_source) == (new.stride, new.step_source) == (3, "lattice")
    assert renamed_flags(old) and not renamed_flags(new)
    assert any("--stride 3" in note for note in renamed_flags(old))
    with pytest.raises(SystemExit):   # one flag, two meanings: the same meaning twice is refused
        parse(["run", "--source", "synthetic:0", "--step", "odometry", "--step", "3", "--step", "lattice"])
    assert parse(["odometry", "--source", "s", "--step", "2"]).step == parse(["odometry", "--source", "s", "--stride", "2"]).step == 2
    assert parse(["integrate", "m.csv", "--step", "lattice"]).step == "lattice"
    assert parse(["integrate", "m.csv"]).step == "odometry"
    for name, old_flag, new_flag, value in (("source", "--step", "--stride", "2"), ("gridcells", "--step", "--step-source", "lattice")):
        parser = service_parser(name)[0]
        assert parser.parse_args([old_flag, value]).step == parser.parse_args([new_flag, value]).step
        assert renamed_flags(parser.parse_args([old_flag, value]))


def test_a_bad_flag_value_names_the_flag():
    from services.cli.run import execute

    args = build_parser().parse_args(["run", "--source", "synthetic:0", "--n-frames", "-3"])
    with pytest.raises(ConfigError, match=r"^--n-frames: .*got -3"):
        execute(args)
    args = build_parser().parse_args(["run", "--source", "synthetic:0", "--stride", "0"])
    with pytest.raises(ConfigError, match=r"^--stride: "):
        execute(args)


def test_version():
    done = subprocess.run([sys.executable, "-m", "services.cli", "--version"], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and done.stdout.startswith("gridslam ") and done.stdout.split()[1][0].isdigit()


def test_run_help_lists_every_preset_and_the_calibration_keys():
    from services.common.config import preset_services, presets

    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    for name in {name for service in preset_services() for name in presets(service)}:
        assert name in text, name
    for key in ("fx", "fy", "cx", "cy", "baseline"):
        assert key in text
    for group in ("input:", "stages:", "mapping:", "outputs:", "ROS bag:", "synthetic world:", "ROS 2:", "map reuse:",
                  "place recognition:", "examples:"):
        assert group in text, group


def test_flags_derived_from_a_config_model_take_its_type_choices_and_default():
    from services.common.settings import CommandParser, add_field_flag
    from services.loopclosure.service import LoopClosureConfig
    from services.ros.foxglove import FoxgloveConfig

    parser = CommandParser(prog="test")
    add_field_flag(parser, FoxgloveConfig, "port")
    add_field_flag(parser, FoxgloveConfig, "allow_remote")
    add_field_flag(parser, LoopClosureConfig, "closure")
    assert vars(parser.parse_args([])) == {"port": None, "allow_remote": None, "closure": None}   # not given
    args = parser.parse_args(["--port", "9000", "--allow-remote", "--closure", "ratslam"])
    assert (args.port, args.allow_remote, args.closure) == (9000, True, "ratslam")
    with pytest.raises(SystemExit):
        parser.parse_args(["--closure", "snap"])
    assert "(default 8765)" in parser.format_help()


def test_the_progress_line_goes_to_the_stderr_of_the_run_not_of_the_import():
    import contextlib
    import io

    from services.cli.run import Progress

    stream = io.StringIO()
    with contextlib.redirect_stderr(stream):   # as a test or a caller that captures stderr does
        progress = Progress()
        progress(5, 10)
        progress.close()
    assert "5/10 frames" in stream.getvalue()
