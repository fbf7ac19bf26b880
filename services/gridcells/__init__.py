"""The grid-cell integrator (DESIGN.md, "The grid-cell integrator"; issue 3): a pure
numpy/scipy core of the Burak & Fiete periodic network as Lu et al. (ROBIO 2016) use it,
three decoders of its lattice flow, and the path integrator built on them."""

from services.gridcells.decoders import DECODERS, decode_fft, decode_paper, decode_subpixel
from services.gridcells.integrator import (
    DeadReckoning,
    GridCellIntegrator,
    GridStep,
    Pose2D,
    auto_velocity_scale,
)
from services.gridcells.network import GridCellError, GridNetwork, NetworkParams

__all__ = [
    "DECODERS",
    "DeadReckoning",
    "GridCellError",
    "GridCellIntegrator",
    "GridNetwork",
    "GridStep",
    "NetworkParams",
    "Pose2D",
    "auto_velocity_scale",
    "decode_fft",
    "decode_paper",
    "decode_subpixel",
]
