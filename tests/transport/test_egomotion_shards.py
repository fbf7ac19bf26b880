"""Sharded egomotion services on real in-process sessions, real NuBot stereo pairs: two instances
take turns by blocks, and when one leaves, the frames sent again are estimated by the other to
the same increments, bit for bit."""

import threading

import pytest
import zenoh

from schemas import CameraFrame, EgoMotion, Header, Time
from services.common import codec, topics
from services.common.runtime import RuntimeConfig
from services.egomotion import load_estimator_config
from services.egomotion.service import EgomotionService
from services.source.service import frame_message
from services.source.spec import open_source
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for

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
    params = load_estimator_config("nubot")[1]["stereo"]
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
                                             encoding=zenoh.Encoding(codec.encoding_of(CameraFrame)))
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
