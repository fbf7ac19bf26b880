"""The grid-cell integrator (DESIGN.md, "The grid-cell integrator"; issues 3 and 13): a pure
numpy/scipy core of the Burak & Fiete periodic network as Lu et al. (ROBIO 2016) use it (and
a fast batched form of it for grid modules), decoders of its lattice flow (the calibrated one
inverts the flow measured per parameter set), a head-direction ring attractor, the grid code,
and the path integrator built on them."""

from services.gridcells.decoders import DECODERS, decode_fft, decode_paper, decode_subpixel
from services.gridcells.integrator import (
    DeadReckoning,
    GridCellIntegrator,
    GridStep,
    Pose2D,
    auto_velocity_scale,
)
from services.gridcells.calibration import FlowTable, flow_table
from services.gridcells.heading import RingHeading
from services.gridcells.network import GridCellError, GridNetwork, NetworkParams, NetworkStack

__all__ = [
    "DECODERS",
    "DeadReckoning",
    "FlowTable",
    "GridCellError",
    "GridCellIntegrator",
    "GridNetwork",
    "GridStep",
    "NetworkParams",
    "NetworkStack",
    "Pose2D",
    "RingHeading",
    "auto_velocity_scale",
    "decode_fft",
    "decode_paper",
    "decode_subpixel",
    "flow_table",
]
