"""`gridslam calibrate`: measure the lattice flow tables of the calibrated decoder (one per grid
module) into the cache, or into a folder (the tables shipped for the default network)."""

from __future__ import annotations

from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="measure the lattice flow tables of the calibrated grid-cell decoder",
        description="Measure how the lattice of each grid module flows for every input direction and speed (the calibrated "
                    "decoder inverts it; docs/gridcells.md). Tables are found by a hash of the network parameters, so a "
                    "changed parameter makes a new one.",
    )
    parser.add_argument("--modules", type=int, default=1, metavar="N", help="grid modules (default 1; up to 4)")
    parser.add_argument("--neurons", type=int, default=128, metavar="n", help="network side n (default 128)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="folder for the tables (default: the cache, $GRIDSLAM_CACHE or ~/.cache/gridslam)")
    parser.add_argument("--force", action="store_true", help="measure again even when a table is already there")
    parser.set_defaults(func=run)


def run(args) -> int:
    from services.evaluation.results import format_table
    from services.gridcells.calibration import cache_dir, flow_table_path, measure_flow
    from services.gridcells.integrator import module_params
    from services.gridcells.network import NetworkParams

    folder = args.out or cache_dir()
    rows = []
    for k, params in enumerate(module_params(NetworkParams(n=args.neurons), args.modules)):
        path = flow_table_path(folder, params)
        if path.exists() and not args.force:
            rows.append((f"module {k} (α={params.alpha:.4g})", "kept", str(path)))
            continue
        table = measure_flow(params)
        table.save(path)
        rows += [(f"module {k} (α={params.alpha:.4g})", f"{table.seconds:.1f}", f"s, {path}"),
                 (f"module {k} search / lag / noise", f"±{table.search} / {table.lag:.4f} / {table.noise:.3g}",
                  "neurons / fraction / network units per frame")]
    print(format_table(rows))
    return 0
