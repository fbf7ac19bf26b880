"""Wire messages of a fleet (docs/fleet.md): robots that recognise each other's places and one
map over all of them. A robot's loop closure publishes its new places (features, never images)
and its confirmed inter-robot closures under its own key; the fleet map (`gridslam/@v1/fleet/...`)
publishes each robot's pose in the fleet frame, its updates and its snapshot."""

from __future__ import annotations

from pydantic import Field

from schemas.base import Header, Message, Model, PlanarCovariance, PlanarIncrement, Pose, covariance_field


class PlaceRecord(Model):
    """One stored place of a robot, as other robots need it to recognise it and measure a closure to it."""

    place: int = Field(ge=0, description="The robot's place (view template) id, dense from 0.")
    frame: int = Field(ge=0, description="The frame of the robot at which the place was stored (its map's numbering).")
    keyframe: bytes = Field(description="The place's keyframe: ORB keypoints, descriptors and stereo disparities, the "
                                        "camera (services/loopclosure/geometry.py, Keyframe.to_bytes); no image.")


class FleetPlaces(Message):
    """`<robot>/fleet/place`: a robot's new place (one record); also the reply of its queryable
    `<robot>/fleet/places?from=N` (the places from id N on, in order, at most a batch)."""

    header: Header = Field(description="The frame that stored the (last) place; robot: whose places they are.")
    places: list[PlaceRecord] = Field(description="The places, by increasing id.")
    place_count: int = Field(ge=0, description="Places the robot has stored so far.")


class FleetClosureRecord(Model):
    """An inter-robot loop closure a robot confirmed: its frame revisits another robot's place."""

    index: int = Field(ge=0, description="The robot's inter-robot closures, numbered from 0 in the order confirmed.")
    frame: int = Field(ge=0, description="The robot's frame that revisits the place (its map's numbering).")
    matched_robot: str = Field(description="The robot whose place it recognised.")
    matched_place: int = Field(ge=0, description="That robot's place id.")
    matched_frame: int = Field(ge=0, description="That robot's frame at which the place was stored.")
    votes: int = Field(ge=1, description="Consistent possible closures within the window that confirmed it.")
    measurement: str = Field(description="How the relative pose was measured: stereo, mono, or none (the geometry failed).")
    relative_pose: PlanarIncrement | None = Field(
        None, description="The revisiting frame's pose in the matched frame's body frame; absent when not measured.")
    covariance: PlanarCovariance | None = covariance_field("the relative pose")
    inliers: int = Field(0, ge=0, description="Feature matches supporting the relative pose.")
    geometry_error: str = Field("", description="Why the geometry failed (measurement none).")


class FleetClosures(Message):
    """`<robot>/fleet/closure`: the inter-robot closures a frame confirmed; also the reply of the
    queryable `<robot>/fleet/closures?from=N` (the closures from index N on)."""

    header: Header = Field(description="The frame that confirmed them; robot: the robot that confirmed them.")
    closures: list[FleetClosureRecord] = Field(description="The closures, by increasing index.")
    closure_count: int = Field(ge=0, description="Inter-robot closures the robot has confirmed so far.")


class FleetPose(Message):
    """`fleet/<robot>/pose`: a robot's pose in the fleet frame (the first robot's map frame)."""

    header: Header = Field(description="The robot's frame index and timestamp; robot: whose pose; frame_id 'map'.")
    pose: Pose = Field(description="The pose in the fleet frame.")
    heading: float = Field(description="Heading in the fleet frame, radians.")
    experience_id: int = Field(ge=0, description="The robot's experience it is at.")
    joined: bool = Field(description="True once the robot's map is joined to the fleet frame; before, the pose is in "
                                     "the frame of the robot's own part of the fleet map.")


class FleetRobot(Model):
    """A robot of the fleet map."""

    name: str = Field(description="Robot name.")
    joined: bool = Field(description="Its map is in the fleet frame.")
    joined_at: int | None = Field(None, description="The robot's frame at which it joined (none: not joined, or the "
                                                    "fleet frame's own robot).")
    part: str = Field(description="The robot whose frame its part of the fleet map is in.")
    experiences: int = Field(ge=0, description="Its experiences in the fleet map.")


class FleetExperience(Model):
    """An experience of one robot's map placed in the fleet frame."""

    robot: str = Field(description="Whose experience.")
    id: int = Field(ge=0, description="The experience's id in that robot's map.")
    x: float = Field(description="Position x in its part's frame (the fleet frame once joined), metres.")
    y: float = Field(description="Position y, metres.")
    heading: float = Field(description="Heading, radians.")


class FleetLink(Model):
    """An inter-robot closure as the fleet map decided it."""

    robot: str = Field(description="The robot whose frame revisits the place.")
    index: int = Field(ge=0, description="That robot's closure index.")
    experience: int = Field(ge=0, description="Its experience.")
    matched_robot: str = Field(description="The robot whose place it is.")
    matched_experience: int = Field(ge=0, description="That robot's experience at the place.")
    fate: str = Field(description="accepted (in the graph), rejected (kept as evidence), pending (waiting for "
                                  "consistent closures to join the two maps) or unmeasured.")


class FleetUpdate(Message):
    """`fleet/update`: what changed in the fleet map: experiences made or moved, closures decided, the robots."""

    header: Header = Field(description="The robot's frame that caused it; robot: that robot; frame_id 'map'.")
    robots: list[FleetRobot] = Field(description="Every robot of the fleet map and whether it is joined.")
    experiences: list[FleetExperience] = Field(description="Experiences created or moved.")
    links: list[FleetLink] = Field(description="Inter-robot closures decided or changed.")


class FleetSnapshot(Message):
    """Reply of the `fleet/snapshot` queryable: the whole fleet map."""

    header: Header = Field(description="frame_id 'map'; robot 'fleet'.")
    robots: list[FleetRobot] = Field(description="Every robot and whether it is joined.")
    experiences: list[FleetExperience] = Field(description="Every experience of every robot.")
    links: list[FleetLink] = Field(description="Every inter-robot closure.")
