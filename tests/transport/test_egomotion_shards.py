"""Sharded egomotion services on real in-process sessions, real NuBot stereo pairs: two instances
take turns by blocks, and when one leaves, the frames sent again are estimated by the other to
the same increments, bit for bit; an instance restarted mid-block rebuilds the block from the
acknowledged frames the source sends again before the frames in flight."""

import threading

import pytest
import zenoh

from schemas import CameraFrame, EgoMotion, Header, Time
from services.common import codec, topics
from services.common.runtime import RuntimeConfig
from services.egomotion import egomotion_config, estimator_params
from services.egomotion.service import EgomotionService
from services.source.service import frame_message
from services.source.spec import open_source
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for

pytestmark = pytest.mark.serial   # which instance takes which block depends on their pace

FIRST, COUNT, BLOCK = 140, 16, 4   # NuBot frames 140..155: four blocks


@pytest.fixture(scope="module")
def frames(shared_data):
    with open_source(f"stereo:{shared_data / 'nubot_scene1'}", start=FIRST, stop=FIRST + COUNT, preset="nubot") as source:
        return [codec.encode(frame_message(frame, Header(seq=frame.seq, stamp=Time.from_seconds(frame.stamp),
                                                          frame_id="camera", robot="robot0")))
                for frame in source]


def test_instances_share_blocks_and_one_takes_over_what_the_other_estimated(frames):
    port = free_port()
    router = router_session(port)
    runtime = RuntimeConfig(connect=[endpoint(port)])
    params = estimator_params(egomotion_config("nubot", environ={}), "stereo")
    services = {name: EgomotionService(runtime, "stereo", params, instance=name, shard_block=BLOCK) for name in ("a", "b")}
    threads = {name: threading.Thread(target=service.run) for name, service in services.items()}
    client = client_session(port)
    published: list[EgoMotion] = []
    lock = threading.Lock()

    def on_egomotion(sample: zenoh.Sample) -> None:
        with lock:
            published.append(codec.decode(sample.payload.to_bytes(), EgoMotion, str(sample.encoding)))

    subscriber = client.declare_subscriber(topics.key("robot0", "egomotion"), on_egomotion)
    try:
        for thread in threads.values():
            thread.start()
        for name in services:
            wait_for(lambda: any(r.ok for r in client.liveliness().get(topics.health_key("robot0", "egomotion", name),
                                                                       timeout=1)), timeout=30)
        publisher = client.declare_publisher(topics.key("robot0", "camera/frame"),
                                             encoding=zenoh.Encoding(codec.encoding_of(CameraFrame)),
                                             congestion_control=zenoh.CongestionControl.BLOCK,
                                             reliability=zenoh.Reliability.RELIABLE)
        wait_for(lambda: publisher.matching_status.matching)   # the subscribers are known: no frame is dropped

        def by_seq() -> dict[int, list[EgoMotion]]:
            with lock:
                found: dict[int, list[EgoMotion]] = {}
                for message in published:
                    found.setdefault(message.header.seq, []).append(message)
            return found

        for payload in frames[:3]:   # both announce their share at the third frame
            publisher.put(payload)
        wait_for(lambda: all(service.history.since is not None for service in services.values()), timeout=30)
        wait_for(lambda: all(service.extra_counters()["shard_members"] == 2 for service in services.values()), timeout=10)
        for payload in frames[3:]:
            publisher.put(payload)
        wait_for(lambda: set(by_seq()) == set(range(FIRST, FIRST + COUNT)), timeout=60)
        first = by_seq()
        # Both announce since = 142: blocks 36 and 38 (frames 144–147, 152–155) are a's, 37 is b's,
        # and so is 35 (140–143, before 142: the smallest `since`, in turn), which a may also have
        # estimated before it saw b's token: identically.
        for seq, messages in first.items():
            assert len({m.model_dump_json() for m in messages}) == 1, seq
        assert services["a"].estimated >= 8 and services["b"].estimated >= 8
        assert [first[seq][0].previous_seq for seq in range(FIRST + 1, FIRST + COUNT)] == list(range(FIRST, FIRST + COUNT - 1))

        # b leaves; the source would send the frames in flight again: a estimates b's now.
        services["b"].stop()
        threads["b"].join(timeout=10)
        wait_for(lambda: services["a"].extra_counters()["shard_members"] == 1, timeout=10)
        with lock:
            published.clear()
        estimated, replayed = services["a"].estimated, services["a"].counters.replayed
        for payload in frames[4:]:
            publisher.put(payload)
        wait_for(lambda: set(by_seq()) == set(range(FIRST + 4, FIRST + COUNT)), timeout=60)
        again = by_seq()
        for seq, messages in again.items():   # a's own are published again, b's estimated anew: the same
            assert [m.model_dump_json() for m in messages] == [first[seq][0].model_dump_json()], seq
        assert services["a"].estimated - estimated == 4   # b's block 37, run from its primer
        assert services["a"].counters.replayed - replayed == 8   # its own blocks 36 and 38, published again
    finally:
        subscriber.undeclare()
        for service in services.values():
            service.stop()
        for thread in threads.values():
            thread.join(timeout=10)
        client.close()
        router.close()


def test_a_restarted_instance_rebuilds_its_block_from_the_acknowledged_frames_sent_again(frames):
    """The source's resend after an egomotion restart: the last acknowledged frames (the block in
    hand and its primers), then the frames in flight. The restarted instance's increments for
    those equal an uninterrupted run's; given only the last acknowledged frame they do not."""
    port = free_port()
    router = router_session(port)
    runtime = RuntimeConfig(connect=[endpoint(port)])
    params = estimator_params(egomotion_config("nubot", environ={}), "stereo")
    client = client_session(port)
    published: dict[int, list[EgoMotion]] = {}
    lock = threading.Lock()

    def on_egomotion(sample: zenoh.Sample) -> None:
        message = codec.decode(sample.payload.to_bytes(), EgoMotion, str(sample.encoding))
        with lock:
            published.setdefault(message.header.seq, []).append(message)

    def run(payloads: list[bytes]) -> dict[int, EgoMotion]:
        """A fresh instance (a restart) given `payloads`: its increment per seq."""
        with lock:
            published.clear()
        # The previous instance's subscription gone first: frames put while it still matched would be lost.
        wait_for(lambda: not publisher.matching_status.matching)
        service = EgomotionService(runtime, "stereo", params, instance="a", shard_block=BLOCK)
        thread = threading.Thread(target=service.run)
        thread.start()
        try:
            wait_for(lambda: service.state == "running", timeout=30)
            wait_for(lambda: publisher.matching_status.matching)
            for payload in payloads:
                publisher.put(payload)
            wait_for(lambda: len(published) == len(payloads), timeout=60)
        finally:
            service.stop()
            thread.join(timeout=10)
        with lock:
            return {seq: messages[-1] for seq, messages in published.items()}

    subscriber = client.declare_subscriber(topics.key("robot0", "egomotion"), on_egomotion)
    # As the source sends them: reliable, and blocking rather than dropping while the instance is busy.
    publisher = client.declare_publisher(topics.key("robot0", "camera/frame"),
                                         encoding=zenoh.Encoding(codec.encoding_of(CameraFrame)),
                                         congestion_control=zenoh.CongestionControl.BLOCK,
                                         reliability=zenoh.Reliability.RELIABLE)
    try:
        uninterrupted = run(frames)
        # Acknowledged up to frame 149 when egomotion died: 150–155 were in flight. 150 is the
        # third frame of block 37 (148–151), primed by 146 and 147.
        in_flight = [FIRST + k for k in range(10, COUNT)]
        rebuilt = run(frames[5:])   # 145–149 (the 5 acknowledged frames a stereo block needs), then 150–155
        primed = run(frames[9:])    # 149 alone (a single primer, as the source sent before)
    finally:
        subscriber.undeclare()
        client.close()
        router.close()
    for seq in in_flight:
        assert rebuilt[seq].model_dump_json() == uninterrupted[seq].model_dump_json(), seq
    # Without the block's start, 150 and 151 come out differently (the next block starts afresh).
    assert primed[150].model_dump_json() != uninterrupted[150].model_dump_json()
    assert primed[152].model_dump_json() == uninterrupted[152].model_dump_json()
