"""Configuration of the gridcells service (table `[gridcells]`, env `GRIDSLAM_GRIDCELLS_*`,
presets in services/gridcells/presets/)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from services.common.settings import config_fields
from services.common.stages import GridStageParams


# Per-frame noise of the direction of travel each decoder reads from the lattice, radians: the rms
# against its input on `gridslam demo` (docs/gridcells.md), for calibrated the largest of the
# demo, the simulated walk and KITTI 06 (0.0016), rounded up.
DIRECTION_SIGMA = {"paper": 0.1, "fft": 0.11, "subpixel": 0.005, "calibrated": 0.002}


class _GridCellsFields(BaseModel):
    """Configuration of the gridcells service (table `[gridcells]`, env `GRIDSLAM_GRIDCELLS_*`,
    presets): the stage's choices are GridStageParams' (services/common/stages.py)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    velocity_scale: float | Literal["auto"] = Field(
        "auto", description="Network input units per metre; auto derives it from typical_speed.")
    typical_speed: float = Field(
        0.5, gt=0, description="Typical distance travelled per frame in metres, used by velocity_scale = auto.")
    neurons: int = Field(128, ge=16, le=512, description="Side n of the n×n network.")
    direction_sigma: float | None = Field(
        None, ge=0, description="Standard deviation of the direction of travel read from the lattice, radians per frame: "
                                "added (as sideways error of the step) to the ego-motion's covariance in grid/pose; "
                                "default: the decoder's measured noise (paper 0.1, fft 0.11, subpixel 0.005, "
                                "calibrated 0.002; docs/gridcells.md).")
    activity_every: int = Field(5, ge=0, description="Publish grid/activity every this many frames (0: never).")
    activity_size: int = Field(64, ge=8, le=512, description="Side of the downsampled activity image.")
    checkpoint: Path | None = Field(
        None, description="File the integrator's state is written to after every frame; a restarted service resumes from it.")

    @property
    def direction_noise(self) -> float:
        """direction_sigma, or the decoder's measured noise when it is not set."""
        return DIRECTION_SIGMA[self.decoder] if self.direction_sigma is None else self.direction_sigma


GridCellsConfig = create_model("GridCellsConfig", __base__=_GridCellsFields, __doc__=_GridCellsFields.__doc__,
                               **config_fields(GridStageParams))
