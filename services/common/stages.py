"""The stages' choices, named once: what the command line, the run's configuration, the
services' config models and the cores accept. Standard library only: the command line imports
it before any stage's numpy, OpenCV or scipy."""

from __future__ import annotations

from dataclasses import dataclass

from services.common.settings import setting

ESTIMATORS = ("scanline", "stereo", "mono", "passthrough")   # services/egomotion (ESTIMATORS: the classes)
INTEGRATORS = ("grid", "deadreckoning")
DECODERS = ("paper", "fft", "subpixel", "calibrated")         # services/gridcells/decoders.py and calibration.py
STEP_SOURCES = ("odometry", "lattice")
HEADING_MODELS = ("sum", "ring")
CLOSURES = ("metric", "ratslam")   # what a closure asserts (loopclosure measures it, expmap weighs it)
MAP_OPTIMIZERS = ("gtsam", "ratslam")   # what places the experiences (services/expmap/optimizers.py)


@dataclass(frozen=True)
class GridStageParams:
    """The grid-cell stage's choices (table `[gridcells]`; `gridslam run` passes its flags on):
    the gridcells service's config, its flags and the run's are derived from these."""

    integrator: str = setting("grid", choices=INTEGRATORS,
                              help="path integrator: grid (the periodic attractor network) or deadreckoning (plain "
                                   "integration of the increments, a baseline)")
    decoder: str = setting("calibrated", choices=DECODERS,
                           help="how the lattice flow is read between frames; calibrated: subpixel's shift through the "
                                "inverse of the flow measured once per parameter set (cached on disk)")
    step: str = setting("odometry", choices=STEP_SOURCES,
                        help="where the step length comes from: the ego-motion (odometry, paper eq. 5) or the "
                             "calibrated lattice flow (lattice; needs decoder calibrated)")
    modules: int = setting(1, ge=1, le=4, help="grid modules of different spacings (ratio ~1.4), run batched and "
                                                "combined by precision (more than 1 needs decoder calibrated)")
    heading: str = setting("sum", choices=HEADING_MODELS,
                           help="heading model: sum (integrated yaw, the paper's) or ring (a head-direction ring attractor)")
