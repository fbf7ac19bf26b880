"""Bad input on every subscribed key of every service (issue 7), real processes on loopback.

Each service runs alone under a robot name of its own, so the test is the only publisher on its
keys and every counter it reports can be checked exactly. Every key gets random bytes, valid
msgpack of the wrong shape, other messages (under their own kind and under this key's kind),
foreign encodings, truncated payloads, NaN and infinity in every float field, out-of-range
integers, images whose size does not match their bytes, then valid messages that are extreme
(huge and tiny images, NaN pixels, values near the float limit) and duplicated or out-of-order
seq. Afterwards: no service died, every message sent is accounted for in its status
(received + decode errors + drops), duplicates are counted as stale, `gridslam health` shows the
counters, and each service still does its work on ordinary messages.
"""

from __future__ import annotations

import json
import math
import random
import time
import urllib.request

import msgpack
import numpy as np
import pytest
import zenoh

from schemas import (
    CameraFrame, CameraInfo, EgoMotion, GridPose, Header, LoopClosure, MapPose, PlanarIncrement, Time, ViewTemplate,
)
from services.common import codec, topics
from services.common.convert import image_to_msg, planar_pose
from services.source.service import frame_message
from services.source.spec import open_source
from tests.messages import sample_messages
from tests.netutil import client_session, endpoint, free_port, start, start_router, stop, wait_for

SAMPLES = {type(message).KIND: message for message in sample_messages(3)}
FRAME = 10_000   # seq of the first ordinary message after the fuzz: newer than anything fuzzed


def robot_of(name: str) -> str:
    return f"fuzz-{name}"


def stamp(seq: int) -> Time:
    return Time.from_seconds(100.0 + 0.1 * seq)


def header(seq: int, robot: str) -> Header:
    return Header(seq=seq, stamp=stamp(seq), frame_id="fuzz", robot=robot)


# ----------------------------------------------------------------------------- payloads
def float_paths(value, path=()):
    """Paths of every float leaf of a model_dump()."""
    if isinstance(value, float):
        yield path
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from float_paths(item, path + (key,))
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            yield from float_paths(item, path + (index,))


def replaced(dump, path, new):
    """A deep copy of `dump` with the leaf at `path` replaced."""
    if not path:
        return new
    copy = list(dump) if isinstance(dump, (list, tuple)) else dict(dump)
    copy[path[0]] = replaced(dump[path[0]], path[1:], new)
    return copy


def bad_payloads(kind: str, rng: random.Random) -> list[tuple[bytes, str]]:
    """(payload, encoding) pairs that must each fail to decode as `kind` (checked locally too)."""
    encoding = codec.ENCODING_PREFIX + kind
    sample = SAMPLES[kind]
    dump = sample.model_dump()
    payloads = [(bytes(rng.getrandbits(8) for _ in range(n)), encoding) for n in (0, 1, 7, 100, 3000)]
    payloads += [(msgpack.packb(shape), encoding) for shape in ([1, 2], 5, "x", None, {}, {"header": 1}, {"a": {"b": [1]}})]
    payloads += [(codec.encode(sample)[:-5], encoding)]                                   # truncated
    for other in SAMPLES.values():
        if other.KIND != kind:
            payloads.append((codec.encode(other), codec.encoding_of(other)))              # wrong kind
            payloads.append((codec.encode(other), encoding))                             # wrong shape for this kind
    for foreign in ("text/plain", "application/json", codec.ENCODING_PREFIX + "Nonexistent", ""):
        payloads.append((codec.encode(sample), foreign))
    for path in float_paths(dump):                                                       # NaN and infinities
        for value in (math.nan, math.inf, -math.inf):
            payloads.append((msgpack.packb(replaced(dump, path, value), use_bin_type=True), encoding))
    for seq in (-1, 1.5, "x"):                                                          # integers out of range or not integers
        payloads.append((msgpack.packb(replaced(dump, ("header", "seq"), seq), use_bin_type=True), encoding))
    if kind == "CameraFrame":   # images whose declared size does not match their bytes
        for width, height in ((16384, 16384), (100_000, 1), (33, 24)):
            image = {**dump["left"], "width": width, "height": height, "step": width}
            payloads.append((msgpack.packb({**dump, "left": image}, use_bin_type=True), encoding))
        payloads.append((msgpack.packb({**dump, "left": {**dump["left"], "encoding": "yuv422"}}, use_bin_type=True), encoding))
    for payload, enc in payloads:
        with pytest.raises(codec.CodecError):
            codec.decode(payload, type(sample), enc)
    return payloads


# ----------------------------------------------------------------------------- ordinary and extreme messages
def world_frames(count: int) -> list:
    """The synthetic world's first frames (stereo 320×240 with calibration, odometry and ground truth)."""
    return list(open_source("synthetic:0", preset="synthetic", stop=count))


def camera_frame(frame, seq: int, robot: str) -> CameraFrame:
    return frame_message(frame, header(seq, robot))


def extreme_frames(frame, robot: str, first_seq: int) -> list[CameraFrame]:
    """Valid frames no ordinary source sends: tiny, huge, mismatched stereo, NaN pixels, other encodings."""
    rng = np.random.default_rng(0)
    base = camera_frame(frame, 0, robot)
    grey = lambda h, w: image_to_msg(rng.integers(0, 256, (h, w), dtype=np.uint8))  # noqa: E731
    variants = [
        dict(left=grey(1, 1), right=grey(1, 1)),
        dict(left=grey(4096, 4096), right=None),                          # 16 MiB of pixels: within the limits
        dict(left=grey(16384, 8), right=grey(16384, 8)),
        dict(right=grey(100, 50)),                                        # stereo pair of different sizes
        dict(right=None),                                                 # mono
        dict(left=image_to_msg(np.full((240, 320), np.nan, np.float32)), right=image_to_msg(np.full((240, 320), np.inf, np.float32))),
        dict(left=image_to_msg(rng.integers(0, 65535, (240, 320), dtype=np.uint16)), right=None),
        dict(left=image_to_msg(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), "rgb8"), right=None),
        dict(camera_info=None, odometry=None, ground_truth=None),
        dict(camera_info=CameraInfo(fx=1e-300, fy=1e300, cx=-1e300, cy=1e300, baseline=1e300)),
        dict(odometry=PlanarIncrement(forward=1e308, left=-1e308, yaw=1e308)),
    ]
    return [base.model_copy(update={"header": header(first_seq + i, robot), **variant}) for i, variant in enumerate(variants)]


def egomotion(seq: int, robot: str, forward: float, left: float = 0.0, yaw: float = 0.0) -> EgoMotion:
    return EgoMotion(header=header(seq, robot), increment=PlanarIncrement(forward=forward, left=left, yaw=yaw),
                     quality=0.5, estimator="fuzz")


def grid_pose(seq: int, robot: str, x: float, y: float, heading: float) -> GridPose:
    return GridPose(header=header(seq, robot), pose=planar_pose(x, y, heading), heading=heading, lattice_shift=(0.0, 0.0),
                    step_length=0.0, integrator="fuzz")


def view(seq: int, robot: str, template: int, new: bool, matched: int, closure: bool = False) -> ViewTemplate:
    return ViewTemplate(header=header(seq, robot), template_id=template, is_new=new, distance=0.1, relative_angle=0.0,
                        matched_frame=matched, template_count=template + 1, loop_closure=closure)


# ----------------------------------------------------------------------------- the services under test
class Target:
    """One service process alone on its robot, what it is sent, and how to see it still works."""

    def __init__(self, name: str, service: str, flags: list[str], topics_: list[str]):
        self.name, self.service, self.flags, self.topics = name, service, flags, topics_
        self.robot = robot_of(name)
        self.valid: list[tuple[str, object]] = []     # (topic, message) in sending order
        self.stale = 0                                 # how many of them repeat or precede an earlier seq
        self.stale_races = 0                           # ... and how many more a race between keys may make stale
        self.rejected: int | None = None               # how many the service must refuse (None: at least one)
        self.check: list[tuple[str, object]] = []     # ordinary messages sent last
        self.output = ""                               # topic whose message for seq FRAME+ shows it works
        self.sent = 0
        self.bad = 0
        self.process = None
        self.drops = False   # newest-only subscriptions drop some samples undecoded, by design


def targets(tmp_path, world, http_port: int) -> list[Target]:
    result = []
    for estimator in ("scanline", "stereo", "mono", "passthrough"):
        target = Target(f"egomotion-{estimator}", "egomotion", ["--estimator", estimator, "--preset", "synthetic"],
                        ["camera/frame"])
        robot = target.robot
        target.valid = [("camera/frame", camera_frame(world[0], 1, robot)), ("camera/frame", camera_frame(world[1], 2, robot))]
        target.valid += [("camera/frame", frame) for frame in extreme_frames(world[2], robot, 3)]
        target.valid += [("camera/frame", camera_frame(world[1], 2, robot)), ("camera/frame", camera_frame(world[0], 1, robot))]
        target.stale = 2
        target.check = [("camera/frame", camera_frame(world[2], FRAME, robot)), ("camera/frame", camera_frame(world[3], FRAME + 1, robot))]
        target.output = "egomotion"
        result.append(target)
    for integrator in ("grid", "deadreckoning"):
        target = Target(f"gridcells-{integrator}", "gridcells", ["--integrator", integrator], ["egomotion"])
        robot = target.robot
        increments = [(0.1, 0.0, 0.01), (1e308, 0.0, 0.0), (0.0, 0.0, 1e308), (-1e308, 1e308, -1e308), (1e308, 1e308, 1e308),
                      (5e-324, -5e-324, 5e-324), (-5.0, 0.0, 0.0), (0.1, 0.0, 0.0)]
        target.valid = [("egomotion", egomotion(seq, robot, *inc)) for seq, inc in enumerate(increments, start=1)]
        target.valid += [("egomotion", egomotion(3, robot, 0.1)), ("egomotion", egomotion(8, robot, 0.1))]
        target.stale = 2
        target.rejected = 4   # the increments beyond 100 m or half a turn per frame
        target.check = [("egomotion", egomotion(FRAME, robot, 0.1, 0.0, 0.01))]
        target.output = "grid/pose"
        result.append(target)
    target = Target("loopclosure", "loopclosure", ["--preset", "synthetic", "--store", str(tmp_path / "templates.log")],
                    ["camera/frame"])
    robot = target.robot
    target.valid = [("camera/frame", camera_frame(world[0], 1, robot))]
    target.valid += [("camera/frame", frame) for frame in extreme_frames(world[1], robot, 2)]
    target.valid += [("camera/frame", camera_frame(world[0], 1, robot))]
    target.stale = 1
    target.rejected = 1   # the frame of NaN pixels
    target.check = [("camera/frame", camera_frame(world[2], FRAME, robot))]
    target.output = "view/template"
    result.append(target)

    target = Target("expmap", "expmap", ["--preset", "synthetic", "--store", str(tmp_path / "map.log")],
                    ["grid/pose", "view/template", "loop/closure"])
    robot = target.robot
    target.valid = [
        ("grid/pose", grid_pose(1, robot, 0.0, 0.0, 0.0)), ("view/template", view(1, robot, 0, True, 1)),
        ("grid/pose", grid_pose(2, robot, 1e308, -1e308, 1e300)), ("view/template", view(2, robot, 10**9, False, 10**9)),
        ("grid/pose", grid_pose(3, robot, -1e308, 1e308, -1e300)), ("view/template", view(3, robot, 5, False, 0, closure=True)),
        ("loop/closure", LoopClosure(header=header(3, robot), frame=3, matched_frame=10**12, matched_template=10**12, votes=1)),
        ("view/template", view(4, robot, 2**62, True, 2**62)), ("grid/pose", grid_pose(4, robot, 1.0, 1.0, 0.1)),
        ("grid/pose", grid_pose(6, robot, 2.0, 1.0, 0.1)),             # a pose whose view never comes
        ("view/template", view(7, robot, 1, True, 7)),                 # a view whose pose never comes
        ("grid/pose", grid_pose(2, robot, 0.0, 0.0, 0.0)), ("view/template", view(1, robot, 0, True, 1)),
        ("loop/closure", LoopClosure(header=header(3, robot), frame=3, matched_frame=0, matched_template=0, votes=9)),
    ]
    target.stale = 3
    # Zenoh orders samples per key only; on a loaded machine about one run in two counts one more
    # of these inputs stale (4): which one, and why, is not pinned down yet (docs/reliability.md).
    target.stale_races = 1
    target.rejected = 2   # the poses near the float limit
    target.check = [("grid/pose", grid_pose(FRAME, robot, 3.0, 1.0, 0.2)), ("view/template", view(FRAME, robot, 2, True, FRAME))]
    target.output = "map/pose"
    result.append(target)

    target = Target("source", "source", ["--source", "synthetic:0", "--preset", "synthetic", "--window", "4", "--ack-topic",
                                         "map/pose", "--resend-after", "600", "--stop", "1000"], ["map/pose"])
    robot = target.robot
    ack = lambda seq: MapPose(header=header(seq, robot), pose=planar_pose(0, 0, 0), heading=0.0, experience_id=0)  # noqa: E731
    target.valid = [("map/pose", ack(seq)) for seq in (0, 0, 2**62, 1, 3)]
    target.rejected = 0
    target.output = "camera/frame"
    result.append(target)

    target = Target("viewer", "viewer", ["--http", f"127.0.0.1:{http_port}"],
                    ["egomotion", "grid/pose", "map/pose", "map/update", "loop/closure", "camera/frame", "grid/activity",
                     "view/template", "status/expmap/fuzz"])
    robot = target.robot
    target.drops = True
    target.valid = [("camera/frame", frame) for frame in extreme_frames(world[0], robot, 1)]
    target.valid += [("grid/pose", grid_pose(seq, robot, 1e308, -1e308, 1e300)) for seq in (1, 1, 0)]
    target.valid += [("egomotion", egomotion(1, robot, 1e308, -1e308, 1e308)), ("map/pose", MapPose(
        header=header(1, robot), pose=planar_pose(-1e308, 1e308, 0.0), heading=1e300, experience_id=2**62))]
    activity = SAMPLES["GridActivity"]
    for image in (image_to_msg(np.zeros((1, 1), np.uint8)), image_to_msg(np.full((64, 64), np.nan, np.float32)),
                  image_to_msg(np.zeros((2048, 2048, 3), np.uint8))):
        target.valid.append(("grid/activity", activity.model_copy(update={"header": header(1, robot), "image": image})))
    update = SAMPLES["MapUpdate"]
    target.valid.append(("map/update", update.model_copy(update={"header": header(1, robot), "experience_count": 2**62})))
    target.valid.append(("loop/closure", LoopClosure(header=header(1, robot), frame=2**62, matched_frame=0,
                                                     matched_template=2**62, votes=2**31)))
    target.valid.append(("view/template", view(1, robot, 2**62, True, 2**62)))
    result.append(target)
    return result


def live_robots(session) -> set[str]:
    return {topics.parse_health_key(str(reply.ok.key_expr))[0]
            for reply in session.liveliness().get(f"{topics.PREFIX}/*/health/**", timeout=2) if reply.ok is not None}


def status_of(session, robot: str):
    for reply in session.get(f"{topics.PREFIX}/{robot}/status/**", timeout=2):
        if reply.ok is not None:
            return codec.decode(reply.ok.payload.to_bytes(), encoding=str(reply.ok.encoding))
    return None


def accounted(status) -> int:
    extra = status.extra
    return (status.received + status.decode_errors + int(extra.get("dropped_newest_only", 0))
            + int(extra.get("dropped_busy", 0)))


def settled_status(session, target: Target, timeout: float = 60.0):
    """The target's status once it has handled everything sent to it; fails with its log if it died."""
    deadline = time.monotonic() + timeout
    status = None
    while time.monotonic() < deadline:
        assert target.process.poll() is None, f"{target.name} died: {stop(target.process)[2][-3000:]}"
        status = status_of(session, target.robot)
        if status is not None and accounted(status) >= target.sent:
            return status
        time.sleep(0.1)
    raise AssertionError(f"{target.name}: {target.sent} sent, status after {timeout:.0f} s: {status}")


def strict_json(data: bytes):
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")
    return json.loads(data, parse_constant=refuse)


def test_every_key_of_every_service_survives_bad_input(tmp_path):
    world = world_frames(4)
    port, http_port = free_port(), free_port()
    router = start_router(port)
    plan = targets(tmp_path, world, http_port)
    for target in plan:
        target.process = start(["service", target.service, "-e", endpoint(port), "--robot", target.robot,
                                "--instance", "fuzz", *target.flags])
    session = client_session(port)
    outputs: dict[str, list] = {target.name: [] for target in plan}
    subscribers = [session.declare_subscriber(
        topics.key(target.robot, target.output),
        lambda sample, name=target.name: outputs[name].append(
            codec.decode(sample.payload.to_bytes(), encoding=str(sample.encoding)).header.seq))
        for target in plan if target.output]
    rng = random.Random(7)
    entities = []

    def put(target: Target, topic: str, message_or_payload, encoding: str | None = None) -> None:
        if encoding is None:
            message_or_payload, encoding = codec.encode(message_or_payload), codec.encoding_of(message_or_payload)
        session.put(topics.key(target.robot, topic), message_or_payload, encoding=encoding,
                    congestion_control=zenoh.CongestionControl.BLOCK)
        target.sent += 1

    try:
        wait_for(lambda: {t.robot for t in plan} <= live_robots(session), timeout=120)
        # The viewer also reads health tokens and queries the map: a token with a malformed key,
        # and a fake expmap whose snapshot replies are garbage (each one a decode error).
        viewer = next(t for t in plan if t.name == "viewer")
        snapshot_key = topics.key(viewer.robot, "map/snapshot")

        snapshot_replies = []

        def garbage_snapshot(query: zenoh.Query) -> None:
            viewer.sent += 1
            snapshot_replies.append(query.key_expr)
            query.reply(snapshot_key, b"\xc1 not a map", encoding=codec.ENCODING_PREFIX + "MapSnapshot")

        entities = [session.declare_queryable(snapshot_key, garbage_snapshot),
                    session.liveliness().declare_token(f"{topics.PREFIX}/{viewer.robot}/health/a/b/c/d"),
                    session.liveliness().declare_token(topics.health_key(viewer.robot, "expmap", "fake"))]
        for target in plan:
            for topic in target.topics:
                for payload, encoding in bad_payloads(topics.model_of(topic).KIND, rng):
                    put(target, topic, payload, encoding)
                    target.bad += 1
            for topic, message in target.valid:
                put(target, topic, message)

        wait_for(lambda: snapshot_replies, timeout=30)
        # Every message sent is accounted for: decoded (then handled, rejected or stale) or counted
        # as a decode error (or, on newest-only subscriptions, dropped unread by design).
        for target in plan:
            status = settled_status(session, target)
            assert accounted(status) == target.sent, (target.name, target.sent, status)
            if target.drops:
                assert status.received <= len(target.valid) and status.decode_errors <= target.bad, (target.name, status)
            else:
                assert status.received == len(target.valid) and status.decode_errors == target.bad, (target.name, status)
            assert target.stale <= status.stale <= target.stale + target.stale_races, (target.name, status)
            print(f"{target.name}: sent {target.sent} ({target.bad} bad): received {status.received}, decode errors "
                  f"{status.decode_errors}, stale {status.stale}, {status.extra}")
            refused = status.extra.get("rejected", 0) + status.extra.get("handler_errors", 0)
            if not target.drops:   # (the viewer may drop a bad frame unread before it is refused)
                assert refused == target.rejected if target.rejected is not None else refused >= 1, (target.name, status)

        # `gridslam health` shows the counters of a service that was fuzzed.
        gridcells = next(t for t in plan if t.name == "gridcells-grid")
        listing = start(["health", "-e", endpoint(port), "--robot", gridcells.robot])
        out, err = listing.communicate(timeout=30)
        assert listing.returncode == 0, err
        row = next(line.split() for line in out.splitlines() if line.startswith(gridcells.robot))
        assert row[1:4] == ["gridcells", "fuzz", "running"] and int(row[6]) == gridcells.bad and int(row[8]) == gridcells.stale

        # Each service still does its work on ordinary input.
        for target in plan:
            for topic, message in target.check:
                put(target, topic, message)
        for target in plan:
            if target.output and target.name != "source":
                wait_for(lambda: max(outputs[target.name], default=-1) >= FRAME, timeout=30)
        source = next(t for t in plan if t.name == "source")
        newest = max(outputs["source"])
        put(source, "map/pose", MapPose(header=header(newest, source.robot), pose=planar_pose(0, 0, 0), heading=0.0,
                                        experience_id=0))
        wait_for(lambda: max(outputs["source"]) > newest, timeout=30)   # the window moved on
        for path in ("/state.json", "/camera.jpg", "/lattice.png"):
            with urllib.request.urlopen(f"http://127.0.0.1:{http_port}{path}", timeout=10) as response:
                body = response.read()
                assert response.status == 200 and body, path
                if path == "/state.json":
                    strict_json(body)
        for target in plan:
            assert target.process.poll() is None, (target.name, stop(target.process)[2][-3000:])
    finally:
        for entity in subscribers + entities:
            entity.undeclare()
        session.close()
        for target in plan:
            if target.process is not None:
                stop(target.process)
        stop(router)
