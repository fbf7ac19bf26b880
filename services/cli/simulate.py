"""`gridslam simulate`: the paper's simulation (an agent in a circle of radius 2 m at up to
2.5 m/s): drift of every decoder beside dead reckoning, and a firing map with its gridness."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from services.cli.integrate import add_network_flags, grid_options
from services.common.settings import add_flag, setting
from services.common.stages import DECODERS
from services.evaluation.results import format_table
from services.gridcells.simulation import WalkParams


def decoder_list(text: str) -> tuple[str, ...]:
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = [name for name in names if name not in DECODERS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown decoder {unknown[0] if unknown else text!r}: choose from {', '.join(DECODERS)}")
    return names


@dataclass(frozen=True)
class SimulateParams:
    """`gridslam simulate`'s own settings (command line only), beside NetworkRunParams."""

    n_frames: int = setting(3500, ge=1, help="frames of the drift run (3500: the paper's)")
    decoders: tuple[str, ...] = setting(("paper", "fft", "subpixel"),
                                        help=f"comma-separated decoders to run, of {','.join(DECODERS)}; --step-source "
                                             f"and --modules apply to calibrated")
    firing_frames: int = setting(30000, ge=0, help="frames of the firing-map run (30000 = 10 minutes at 50 Hz; 0 skips it)")
    frame_period: float = setting(WalkParams.frame_period_s, gt=0.0, help="seconds per frame")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate", help="the paper's simulation: drift per decoder, firing map and gridness",
        description="A seeded random walk in a circle of radius 2 m at up to 2.5 m/s (one frame every 20 ms); each decoder "
                    "and dead reckoning integrate its odometry; the walk continued drives the network for the firing map "
                    "of neuron (0, 0) and its gridness score.",
    )
    add_flag(parser, SimulateParams, "n_frames", metavar="N", standalone=True)
    add_flag(parser, SimulateParams, "decoders", type=decoder_list, metavar="LIST", standalone=True)
    add_flag(parser, SimulateParams, "firing_frames", metavar="N", standalone=True)
    add_flag(parser, SimulateParams, "frame_period", metavar="S", standalone=True)
    add_network_flags(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    from services.offline.integration import simulate, simulation_table  # numpy/matplotlib work: loaded only when run

    result = simulate(
        n_frames=args.n_frames, seed=args.seed, decoders=args.decoders, noise_trans=args.noise_trans,
        noise_rot_deg=args.noise_rot, velocity_scale=args.velocity_scale, firing_frames=args.firing_frames,
        walk_params=WalkParams(frame_period_s=args.frame_period), out=args.out, options=grid_options(args),
    )
    print(format_table(simulation_table(result)))
    print(f"results: {result.out_dir}")
    return 0
