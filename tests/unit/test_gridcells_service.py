"""The gridcells adapter without a network session: EgoMotion in, GridPose out."""

import math

import pytest

from schemas import EgoMotion, Header, PlanarIncrement, Time
from services.common.config import load_config
from services.common.runtime import RuntimeConfig
from services.evaluation.trajectory import integrate_increments
from services.gridcells.config import GridCellsConfig
from services.gridcells.service import GridCellsService


def poses_of(config: GridCellsConfig, increments):
    service = GridCellsService(RuntimeConfig(), config, "test")
    published = []
    service.publish = lambda topic, message: published.append((topic, message))
    for seq, (forward, left, yaw) in enumerate(increments):
        service.on_egomotion(EgoMotion(header=Header(seq=seq, stamp=Time.from_seconds(0.1 * seq)),
                                       increment=PlanarIncrement(forward=forward, left=left, yaw=yaw), quality=1.0,
                                       estimator="passthrough"))
    return [message for topic, message in published if topic == "grid/pose"]


def test_poses_follow_the_egomotion_composition_and_say_how_they_were_made():
    increments = [(0.1, 0.0, 0.0)] + [(0.1, 0.002, math.radians(4))] * 20
    truth = integrate_increments(*zip(*increments))
    dead = poses_of(GridCellsConfig(integrator="deadreckoning"), increments)
    assert (dead[-1].pose.position.x, dead[-1].pose.position.y) == pytest.approx(tuple(truth.positions[-1, :2]), abs=1e-12)
    assert (dead[-1].decoder, dead[-1].modules) == (None, 0)
    grid = poses_of(GridCellsConfig(typical_speed=0.1, heading="ring"), increments)
    last = grid[-1]
    assert (last.integrator, last.decoder, last.step_source, last.heading_model, last.modules) == ("grid", "calibrated", "odometry", "ring", 1)
    # Turning 4° per frame: the grid's path stays on the composed one (a turn-first mix-up
    # would put every step 4° off).
    assert math.hypot(last.pose.position.x - truth.positions[-1, 0], last.pose.position.y - truth.positions[-1, 1]) < 0.01


def test_options_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("GRIDSLAM_GRIDCELLS_DECODER", "subpixel")
    monkeypatch.setenv("GRIDSLAM_GRIDCELLS_STEP", "lattice")
    monkeypatch.setenv("GRIDSLAM_GRIDCELLS_MODULES", "3")
    monkeypatch.setenv("GRIDSLAM_GRIDCELLS_HEADING", "ring")
    config = load_config(GridCellsConfig, "gridcells")
    assert (config.decoder, config.step, config.modules, config.heading) == ("subpixel", "lattice", 3, "ring")


@pytest.mark.parametrize("decoder, sigma", [("calibrated", 0.002), ("subpixel", 0.005), ("paper", 0.1)])
def test_the_sideways_noise_added_to_the_covariance_is_the_decoders_unless_set(decoder, sigma):
    covariance = [1e-6 if i in (0, 4, 8) else 0.0 for i in range(9)]
    service = GridCellsService(RuntimeConfig(), GridCellsConfig(decoder=decoder), "test")
    added = service.increment_covariance(covariance, 0.1)
    assert added[4] == pytest.approx(1e-6 + (0.1 * sigma) ** 2)
    assert [added[i] for i in range(9) if i != 4] == [covariance[i] for i in range(9) if i != 4]
    fixed = GridCellsService(RuntimeConfig(), GridCellsConfig(decoder=decoder, direction_sigma=0.0), "test")
    assert fixed.increment_covariance(covariance, 0.1) == covariance


def test_run_flags_reach_the_gridcells_service(tmp_path):
    """`gridslam run --decoder calibrated --step-source lattice --modules 3 --heading ring`: every
    option reaches the gridcells service's command line; the old spellings `--step lattice` and
    `--step 2` (the frame stride) still work."""
    import argparse

    from services.cli.run import add_run_arguments, run_flags
    from services.pipeline.runner import RunConfig, service_args

    parser = argparse.ArgumentParser()
    add_run_arguments(parser, source_required=False)
    args = parser.parse_args(["--source", "synthetic:0", "--decoder", "calibrated", "--step", "lattice", "--step", "2",
                              "--modules", "3", "--heading", "ring"])
    flags = {key: value for key, value in run_flags(args).items() if value is not None}
    config = RunConfig(**flags)
    assert config.step == 2 and config.step_source == "lattice"
    command = service_args(config, "gridcells", tmp_path)
    for option in (["--decoder", "calibrated"], ["--step-source", "lattice"], ["--modules", "3"], ["--heading", "ring"]):
        index = command.index(option[0])
        assert command[index:index + 2] == option
    with pytest.raises(SystemExit):
        parser.parse_args(["--step", "sideways"])


def test_a_restart_publishes_the_checkpointed_frame_again_when_it_comes_again(tmp_path):
    # A kill between the checkpoint and the pose leaving must not lose the frame's pose: the
    # restored service publishes it again for the re-sent frame instead of taking it as done.
    config = GridCellsConfig(typical_speed=0.1, checkpoint=tmp_path / "gridcells.checkpoint.npz")
    first = poses_of(config, [(0.1, 0.0, 0.0), (0.1, 0.0, 0.02), (0.1, 0.001, 0.02)])
    restarted = GridCellsService(RuntimeConfig(), config, "test")
    assert restarted.resumed_at == 2
    sent = []
    restarted._send = lambda topic, message: sent.append((topic, message))
    assert restarted.replay_outputs(1) == 0
    assert restarted.replay_outputs(2) == 1
    assert sent == [("grid/pose", first[-1])]
