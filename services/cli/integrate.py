"""`gridslam integrate INPUT`: run the grid-cell integrator offline on motion-only data and
score it against dead reckoning (and the ground truth when the input is a trajectory)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from services.common.settings import add_flag, add_renamed_flag, setting
from services.common.stages import STEP_SOURCES, GridStageParams
from services.evaluation.results import format_table
from services.evaluation.motion_io import FORMATS



def velocity_scale(text: str) -> float | str:
    """`auto` or a positive number of network units per metre."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a positive number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected 'auto' or a positive number, got {text!r}")
    return value


@dataclass(frozen=True)
class NetworkRunParams:
    """The settings `integrate` and `simulate` share (command line only), declared once: their
    flags are derived from these (with the grid-cell stage's choices, GridStageParams)."""

    velocity_scale: float | str = setting("auto", help="network input units per metre; auto puts the 95th-percentile "
                                                       "speed at a lattice shift of 3 neurons per frame "
                                                       "(docs/gridcells.md)")
    noise_trans: float = setting(0.0, ge=0.0, help="Gaussian translation noise per frame, standard deviation as a "
                                                   "fraction of the step (0.02 = 2%)")
    noise_rot: float = setting(0.0, ge=0.0, help="Gaussian rotation noise per frame, standard deviation in degrees")
    seed: int = setting(0, ge=0, help="random seed of the noise (and of the simulated walk)")
    out: Path | None = setting(None, help="results folder (default: results/<timestamp>/, with results/latest)")


@dataclass(frozen=True)
class IntegrateParams:
    """`gridslam integrate`'s own settings (command line only)."""

    fmt: str | None = setting(None, help="input format (default: from the extension, then the content)")
    n_frames: int | None = setting(None, ge=1, help="only the first N rows")
    network_rotation: float = setting(0.0, help="turn the world frame the network runs in by DEG (results are turned "
                                                "back): shows how much a result owes to the route's alignment with "
                                                "the lattice directions")


def add_network_flags(parser: argparse.ArgumentParser) -> None:
    """Flags shared by `integrate` and `simulate`."""
    add_flag(parser, NetworkRunParams, "velocity_scale", type=velocity_scale, metavar="S|auto", standalone=True)
    add_flag(parser, NetworkRunParams, "noise_trans", metavar="FRACTION", standalone=True)
    add_flag(parser, NetworkRunParams, "noise_rot", metavar="DEG", standalone=True)
    add_flag(parser, NetworkRunParams, "seed", standalone=True)
    add_flag(parser, NetworkRunParams, "out", metavar="DIR", standalone=True)
    add_renamed_flag(parser, "--step", "--step-source", dest="step", choices=STEP_SOURCES)
    add_flag(parser, GridStageParams, "step", flag="--step-source", standalone=True)
    add_flag(parser, GridStageParams, "modules", metavar="N", standalone=True)
    add_flag(parser, GridStageParams, "heading", standalone=True)


def grid_options(args):
    from services.offline.integration import GridOptions

    return GridOptions(step=args.step, modules=args.modules, heading=args.heading)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "integrate", help="integrate a motion file (CSV, KITTI, TUM, rat .npz) with the grid cells offline",
        description="Integrate per-frame motion with the grid-cell network and with dead reckoning; write trajectory.tum, "
                    "deadreckoning.tum, groundtruth.tum (when known), metrics.json and plots; print a metric table.",
    )
    parser.add_argument("input", type=Path, metavar="INPUT",
                        help="CSV (forward,left,yaw | vx,vy[,heading] | LIBVISO2 columns), KITTI poses, TUM trajectory or rat .npz")
    add_flag(parser, IntegrateParams, "fmt", flag="--format", metavar="|".join(FORMATS), standalone=True)
    add_flag(parser, GridStageParams, "decoder", standalone=True)
    add_flag(parser, IntegrateParams, "n_frames", metavar="N", standalone=True)
    add_flag(parser, IntegrateParams, "network_rotation", metavar="DEG", standalone=True)
    add_network_flags(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    from services.offline.integration import integrate, integration_table  # numpy/matplotlib work: loaded only when run

    result = integrate(
        args.input, fmt=args.fmt, decoder=args.decoder, velocity_scale=args.velocity_scale, n_frames=args.n_frames,
        noise_trans=args.noise_trans, noise_rot_deg=args.noise_rot, seed=args.seed,
        network_rotation_deg=args.network_rotation, out=args.out, options=grid_options(args),
    )
    print(format_table(integration_table(result)))
    print(f"results: {result.out_dir}")
    return 0
