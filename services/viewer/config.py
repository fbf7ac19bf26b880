"""Configuration of the viewer service (table `[viewer]`, env `GRIDSLAM_VIEWER_*`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, create_model, field_validator

from services.common.runtime import is_loopback
from services.common.settings import config_fields, params_of
from services.viewer.fleet import FleetViewParams
from services.viewer.state import ViewerParams


def split_address(address: str) -> tuple[str, int]:
    """(host, port) of 'HOST:PORT' or '[IPv6]:PORT'; ValueError naming what is wrong."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{address!r} is not HOST:PORT (e.g. 127.0.0.1:8080)")
    return host.removeprefix("[").removesuffix("]"), int(port)


class _ViewerFields(BaseModel):
    """Configuration of the viewer service (table `[viewer]`, env `GRIDSLAM_VIEWER_*`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # allow_remote comes first: the check of `http` reads it.

    allow_remote: bool = Field(
        False, description="Allow a non-loopback HOST in `http`. The page has no authentication: anyone who can reach "
                           "the port sees the run.")
    http: str = Field("127.0.0.1:8080", description="HOST:PORT the page is served on (port 0: any free port).")
    rate_hz: float = Field(10.0, ge=0.5, le=30.0, description="State updates pushed to each browser per second, at most.")
    map_rate_hz: float = Field(2.0, ge=0.1, le=30.0, description="Experience-map redraws pushed per second, at most.")
    image_rate_hz: float = Field(4.0, ge=0.1, le=30.0, description="Camera and lattice images offered per second, at most.")
    max_points: int = Field(4000, ge=100, le=100000, description="Drawn points per trajectory; longer paths are thinned.")
    camera_width: int = Field(320, ge=32, le=1920, description="Camera frames are downsampled to at most this width, pixels.")
    max_clients: int = Field(16, ge=1, le=256, description="Browsers streaming at once; more are answered 503.")

    @field_validator("http")
    @classmethod
    def _address(cls, value: str, info: ValidationInfo) -> str:
        host, _ = split_address(value)
        if not info.data.get("allow_remote") and not is_loopback(host):
            raise ValueError(f"{value} is not a loopback address; the viewer has no authentication, so serving "
                             "other machines needs --allow-remote (allow_remote = true)")
        return value

    @property
    def address(self) -> tuple[str, int]:
        return split_address(self.http)

    def params(self) -> ViewerParams:
        return ViewerParams(max_points=self.max_points, camera_width=self.camera_width)

    def fleet_params(self) -> FleetViewParams:
        return params_of(FleetViewParams, self)


ViewerConfig = create_model("ViewerConfig", __base__=_ViewerFields, __doc__=_ViewerFields.__doc__,
                            **config_fields(FleetViewParams))
