"""`gridslam integrate INPUT`: run the grid-cell integrator offline on motion-only data and
score it against dead reckoning (and the ground truth when the input is a trajectory)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.common.settings import add_renamed_flag
from services.common.stages import DECODERS, HEADING_MODELS, STEP_SOURCES
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


def add_network_flags(parser: argparse.ArgumentParser) -> None:
    """Flags shared by `integrate` and `simulate`."""
    parser.add_argument("--velocity-scale", type=velocity_scale, default="auto", metavar="S|auto",
                        help="network input units per metre; auto (default) puts the 95th-percentile speed at a lattice shift "
                             "of 3 neurons per frame (docs/gridcells.md)")
    parser.add_argument("--noise-trans", type=float, default=0.0, metavar="FRACTION",
                        help="Gaussian translation noise per frame, standard deviation as a fraction of the step (0.02 = 2%%)")
    parser.add_argument("--noise-rot", type=float, default=0.0, metavar="DEG",
                        help="Gaussian rotation noise per frame, standard deviation in degrees")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the noise (and of the simulated walk)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="results folder (default: results/<timestamp>/, with results/latest)")
    add_renamed_flag(parser, "--step", "--step-source", dest="step", choices=STEP_SOURCES)
    parser.add_argument("--step-source", dest="step", choices=STEP_SOURCES, default="odometry",
                        help="step length from the input (default; paper eq. 5) or from the calibrated lattice flow "
                             "(needs --decoder calibrated)")
    parser.add_argument("--modules", type=int, default=1, metavar="N",
                        help="grid modules of different spacings, combined by precision (default 1; more need --decoder calibrated)")
    parser.add_argument("--heading", choices=HEADING_MODELS, default="sum",
                        help="heading model: summed yaw (default, the paper's) or a head-direction ring attractor")


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
    parser.add_argument("--format", dest="fmt", metavar="|".join(FORMATS),
                        help="input format (default: from the extension, then the content)")
    parser.add_argument("--decoder", choices=DECODERS, default="calibrated", help="how the lattice flow is read (default calibrated)")
    parser.add_argument("--n-frames", type=int, metavar="N", help="only the first N rows")
    parser.add_argument("--network-rotation", type=float, default=0.0, metavar="DEG",
                        help="turn the world frame the network runs in by DEG (results are turned back): shows how much a "
                             "result owes to the route's alignment with the lattice directions")
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
