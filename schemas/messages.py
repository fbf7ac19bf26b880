"""One model per wire message (DESIGN.md, "Messages"). Each is frozen, forbids unknown
fields and NaN/infinity, carries `schema_version` and a `Header` with `seq` and the source
timestamp, and describes every field so that the exported JSON Schema documents the wire."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from schemas.base import Header, Image, Message, Model, PlanarIncrement, Point, Pose, Twist, PlanarCovariance, covariance_field
from schemas.fleet import FleetClosures, FleetPlaces, FleetPose, FleetSnapshot, FleetUpdate


class CameraInfo(Model):
    """Pinhole intrinsics of a rectified camera (a subset of sensor_msgs/CameraInfo)."""

    fx: float = Field(gt=0, description="Focal length along x, pixels.")
    fy: float = Field(gt=0, description="Focal length along y, pixels.")
    cx: float = Field(description="Principal point x, pixels.")
    cy: float = Field(description="Principal point y, pixels.")
    baseline: float = Field(0.0, ge=0, description="Stereo baseline in metres; 0 for a monocular camera.")


class CameraFrame(Message):
    """`camera/frame`: one mono or stereo frame from a source, with ground truth or odometry when known."""

    header: Header = Field(description="Frame index, source timestamp, frame_id 'camera'.")
    left: Image = Field(description="Left (or only) image.")
    right: Image | None = Field(None, description="Right image of a rectified stereo pair, absent for monocular sources.")
    camera_info: CameraInfo | None = Field(None, description="Intrinsics, when the source knows them.")
    ground_truth: Pose | None = Field(
        None, description="Ground-truth camera pose in the first camera's frame (x right, y down, z forward), when known."
    )
    odometry: PlanarIncrement | None = Field(None, description="Wheel or other odometry since the previous frame, when known.")


class EgoMotion(Message):
    """`egomotion`: the camera's motion since the previous frame, in the body frame."""

    header: Header = Field(description="Index and timestamp of the frame that ends this increment.")
    previous_seq: int | None = Field(
        None, ge=0,
        description="Index of the frame the increment starts from (the one before it in the estimator's run); absent "
                    "for a run's first frame. Several egomotion instances publish out of order: a consumer puts the "
                    "increments back in order by this link (docs/pipeline.md, sharded ego-motion).")
    increment: PlanarIncrement = Field(description="Planar body-frame motion over the frame: forward, left (m), yaw (rad).")
    transform: list[float] | None = Field(
        None, min_length=16, max_length=16,
        description="Full 6-DoF transform, previous camera to current camera, row-major 4×4, when the estimator knows it.",
    )
    quality: float = Field(ge=0.0, le=1.0, description="Figure of merit from 0 (no usable estimate) to 1.")
    inliers: int = Field(0, ge=0, description="Feature inliers supporting the estimate (0 for scanline and passthrough).")
    match_cost: float = Field(0.0, ge=0.0, description="Residual of the match (profile difference or reprojection error).")
    scaled: bool = Field(True, description="False when the translation has no metric scale (monocular without a scale cue).")
    estimator: str = Field(description="Estimator that produced it: scanline, stereo, mono or passthrough.")
    covariance: PlanarCovariance | None = covariance_field("the increment's error, from the estimator's noise model")


class GridPose(Message):
    """`grid/pose`: the path integrator's pose (nav_msgs/Odometry layout plus the lattice readout)."""

    header: Header = Field(description="Frame index and timestamp; frame_id 'odom'.")
    child_frame_id: str = Field("base_link", description="Frame whose pose is given.")
    pose: Pose = Field(description="Integrated pose in the odometry frame (planar: z = 0, yaw about z).")
    twist: Twist = Field(default_factory=Twist, description="Velocity over the last frame, body frame.")
    heading: float = Field(description="Heading from the head-direction integration, radians, counter-clockwise from x.")
    lattice_shift: tuple[float, float] = Field(description="Flow of the activity lattice over the last frame, neurons (columns, rows).")
    step_length: float = Field(ge=0.0, description="Distance credited to the last frame, metres (paper eq. 5).")
    saturated: bool = Field(False, description="True when the lattice shift reached the decoder's search limit.")
    integrator: str = Field(description="Integrator that produced it: grid (the attractor network) or deadreckoning.")
    increment_covariance: PlanarCovariance | None = covariance_field(
        "the error of this frame's integrated increment (the ego-motion's, plus the lattice's direction noise)")
    decoder: str | None = Field(
        None, description="Lattice flow decoder (paper, fft, subpixel or calibrated); absent for dead reckoning.")
    step_source: Literal["odometry", "lattice"] = Field(
        "odometry", description="Where the step length came from: the ego-motion (paper eq. 5) or the calibrated lattice flow.")
    heading_model: Literal["sum", "ring"] = Field(
        "sum", description="Heading model: summed yaw (the paper's) or a head-direction ring attractor.")
    modules: int = Field(1, ge=0, description="Grid modules whose flow was combined (0 for dead reckoning).")


class GridActivity(Message):
    """`grid/activity`: a downsampled snapshot of the network's activity (the paper's Fig. 1)."""

    header: Header = Field(description="Frame index and timestamp of the snapshot.")
    image: Image = Field(description="Activity scaled to 0..255, mono8, downsampled from the n×n sheet.")
    neurons: int = Field(ge=1, description="Side of the full network sheet, n.")
    max_rate: float = Field(ge=0.0, description="Firing rate that maps to 255.")
    lattice_shift: tuple[float, float] = Field(description="Lattice flow decoded for this frame, neurons (columns, rows).")


class ViewTemplate(Message):
    """`view/template`: which stored view template the current frame matched (RatSLAM local view cells)."""

    header: Header = Field(description="Frame index and timestamp.")
    template_id: int = Field(ge=0, description="Id of the matched or newly stored template.")
    is_new: bool = Field(description="True when no stored template was close enough and this view was stored.")
    distance: float = Field(ge=0.0, description="Match distance to the best stored template (normalised mean absolute difference).")
    relative_angle: float = Field(description="Rotation between the view and the template from the best shift, radians.")
    matched_frame: int = Field(ge=0, description="Frame at which the matched template was first stored.")
    template_count: int = Field(ge=0, description="Templates stored so far.")
    loop_closure: bool = Field(
        False, description="True when this frame confirmed a loop closure, published on loop/closure just before.")
    loop_closures: int = Field(
        0, ge=0, description="How many loop closures this frame confirmed (its own and those of the earlier frames of "
                             "the run of votes it completed), each a loop/closure message with this frame's seq just before.")


class LoopClosure(Message):
    """`loop/closure`: a loop closure confirmed by the paper's consistency rule."""

    header: Header = Field(description="Index and timestamp of the frame that confirmed it.")
    frame: int = Field(ge=0, description="The frame that revisits the place: the confirming frame, or an earlier frame of "
                                         "the run of consistent votes it completed.")
    matched_frame: int = Field(ge=0, description="Earlier frame of the place recognised.")
    matched_template: int = Field(ge=0, description="Template id of the place recognised.")
    votes: int = Field(ge=1, description="Consistent possible closures within the window that confirmed it.")
    measurement: Literal["stereo", "mono", "scanline", "none"] = Field(
        "none", description="How the relative pose was measured: stereo (PnP on the matched keyframe's triangulated "
                            "features), mono (essential matrix: rotation and direction), scanline (the view templates' "
                            "relative angle, the robot taken to be at the matched place), none (the geometry failed).")
    relative_pose: PlanarIncrement | None = Field(
        None, description="Pose of `frame` in the matched frame's body frame (for mono, forward/left is a unit "
                          "direction); absent when the measurement is none.")
    covariance: PlanarCovariance | None = covariance_field("the relative pose")
    inliers: int = Field(0, ge=0, description="Feature matches supporting the relative pose.")
    geometry_error: str = Field("", description="Why the geometry failed (measurement none), e.g. 'too few inliers (7 < 20)'.")


class FramePlacement(Model):
    """Where the map puts one frame: at an experience, and the offset from it."""

    frame: int = Field(ge=0, description="The frame (the map's numbering).")
    experience: int = Field(ge=0, description="The experience the robot was at.")
    dx: float = Field(description="Forward offset of the frame's pose in the experience's frame, metres.")
    dy: float = Field(description="Leftward offset, metres.")
    dheading: float = Field(description="Heading of the frame minus the experience's, radians.")


class MapPose(Message):
    """`map/pose`: the map-corrected robot pose (geometry_msgs/PoseStamped plus the experience)."""

    header: Header = Field(description="Frame index and timestamp; frame_id 'map'.")
    pose: Pose = Field(description="Corrected pose in the map frame.")
    heading: float = Field(description="Corrected heading, radians, counter-clockwise from x.")
    experience_id: int = Field(ge=0, description="Experience the robot is at.")
    localized: bool = Field(
        True, description="The pose is in the map's frame. False while a localisation on a saved map is not placed yet (or "
                          "lost), and while a later session of a map is not joined to it: the pose is then the odometry's.")
    placement: FramePlacement | None = Field(
        None, description="Where the map puts this frame: its experience and the offset from it, as `map/frames` answers. "
                          "Whoever places the experience elsewhere (the fleet map) places the robot by it, whatever pose "
                          "of the experience it heard last. None: no experience of its own (a localisation).")


class Experience(Model):
    """A node of the experience map."""

    id: int = Field(ge=0, description="Experience id, dense from 0.")
    x: float = Field(description="Position x in the map frame, metres.")
    y: float = Field(description="Position y in the map frame, metres.")
    heading: float = Field(description="Heading, radians.")
    template_id: int = Field(ge=0, description="View template seen when the experience was created.")
    frame: int = Field(ge=0, description="Frame at which it was created.")


class Link(Model):
    """An edge of the experience map: the odometric transform from one experience to another."""

    source: int = Field(ge=0, description="Experience the link starts at.")
    target: int = Field(ge=0, description="Experience the link ends at.")
    dx: float = Field(description="Forward offset of the target in the source's frame, metres.")
    dy: float = Field(description="Leftward offset of the target in the source's frame, metres.")
    dheading: float = Field(description="Heading of the target minus the source's, radians.")
    frame: int = Field(ge=0, description="Frame at which the link was made.")
    loop_closure: bool = Field(False, description="True for a link made by a confirmed loop closure.")
    accepted: bool = Field(True, description="False for a closure the map refused (its odometry contradicts it): kept as "
                                             "evidence, not used to place the experiences.")
    covariance: PlanarCovariance | None = Field(
        None, description="The link's covariance in the pose graph (x m, y m, heading rad of the target in the source's "
                          "frame, right-hand tangent), 3×3 row-major; absent when the map has none (RatSLAM's relaxation).")


class MapUpdate(Message):
    """`map/update`: what changed in the experience map at this frame."""

    header: Header = Field(description="Frame index and timestamp.")
    experiences: list[Experience] = Field(description="Experiences created or moved by relaxation at this frame.")
    links: list[Link] = Field(description="Links created at this frame.")
    experience_count: int = Field(ge=0, description="Experiences in the map.")
    link_count: int = Field(ge=0, description="Links in the map.")


class MapSnapshot(Message):
    """Reply of the `map/snapshot` queryable: the whole experience map."""

    header: Header = Field(description="Last frame applied to the map and its timestamp.")
    experiences: list[Experience] = Field(description="Every experience.")
    links: list[Link] = Field(description="Every link.")


class MapFrames(Message):
    """Reply of the `map/frames?from=F;to=T` queryable: where the map puts each of those frames
    (the fleet map's way to place a closure of a frame whose map/pose it missed)."""

    header: Header = Field(description="Last frame applied to the map; frame_id 'map'.")
    frames: list[FramePlacement] = Field(description="The frames from F to T the map has, in order.")


class MapRoute(Message):
    """`map/route`: the shortest path over the experience map between the experiences nearest two
    points (reply of the queryable, and published for the viewer); nav_msgs/Path's layout."""

    header: Header = Field(description="Last frame applied to the map when the route was planned; frame_id 'map'.")
    start: Point = Field(description="The point asked to start from, map frame (z 0).")
    goal: Point = Field(description="The point asked to go to, map frame (z 0).")
    experiences: list[int] = Field(description="The experiences of the route, in order.")
    poses: list[Pose] = Field(description="Their poses in the map frame, in order.")
    length: float = Field(ge=0, description="The route's length over the links' lengths, m.")
    found: bool = Field(description="False when the two experiences are in parts of the map no link joins.")


class ServiceStatus(Message):
    """`status/<service>/<instance>`: counters of a running service, published periodically and on query."""

    header: Header = Field(description="Last frame handled (seq 0 before any) and the wall-clock time.")
    service: str = Field(description="Service name, e.g. gridcells.")
    instance: str = Field(description="Instance name, unique per process.")
    state: Literal["starting", "running", "stopping"] = Field(description="Life-cycle state.")
    received: int = Field(ge=0, description="Messages received and decoded.")
    published: int = Field(ge=0, description="Messages published.")
    decode_errors: int = Field(ge=0, description="Messages dropped because they failed to decode or validate.")
    gaps: int = Field(ge=0, description="Frames missing between consecutive received seq numbers.")
    stale: int = Field(ge=0, description="Messages dropped because their seq was not newer than the last one (duplicates, out of order).")
    uptime: float = Field(ge=0.0, description="Seconds since the service started.")
    extra: dict[str, float] = Field(
        default_factory=dict,
        description="Service-specific counters, e.g. frames_dropped (live camera), templates, experiences, restarts.")

    @field_validator("service", "instance")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value or any(c in value for c in "/*$?# "):
            raise ValueError(f"{value!r} is not a valid key chunk")
        return value


MESSAGES: tuple[type[Message], ...] = (
    CameraFrame, EgoMotion, GridPose, GridActivity, ViewTemplate, LoopClosure,
    MapPose, MapUpdate, MapSnapshot, MapRoute, MapFrames, ServiceStatus,
    FleetPlaces, FleetClosures, FleetPose, FleetUpdate, FleetSnapshot,
)
