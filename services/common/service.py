"""The base of every service adapter (DESIGN.md, "Runtime").

A service opens one Zenoh session, declares its liveliness token
`gridslam/@v1/<robot>/health/<service>/<instance>`, and handles every incoming sample on its
own main thread, in arrival order: Zenoh callbacks only hand raw bytes to a bounded inbox
(so a slow service pushes back on its publishers instead of growing a queue), and the main
thread decodes, checks `seq`, and calls the handler. A sample that fails to decode is logged
with its key, counted and dropped. SIGTERM/SIGINT stop the loop; the session is closed in
`finally` (a session left open with callback subscribers hangs interpreter exit).
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta
from typing import ClassVar

import zenoh
import zenoh.ext

from schemas import Header, ServiceStatus, Time
from schemas.base import Message
from services.common import codec, topics
from services.common.errors import ConfigError, GridslamError, PersistenceError
from services.common.recovery import REPLAY_FRAMES, OutputMemory, RouterLink
from services.common.runtime import RuntimeConfig, ServiceStopped, open_session
from services.common.sequencing import Delivery, Sequencer, SequencerParams
from services.common.settings import setting

log = logging.getLogger(__name__)

INBOX_SIZE = 16          # samples waiting for the main thread; beyond this, publishers are pushed back
STATUS_PERIOD_S = 1.0    # how often the status message is published
LOG_EVERY = 1000         # after the first 10, one log line per this many decode errors, gaps, rejections
# Samples lost on the way (with a router that died, or with a lease that expired) are recovered
# by Zenoh's advanced publisher and subscriber (docs/reliability.md): each publisher of a pipeline
# topic numbers its samples and keeps its last CACHE_SAMPLES; a subscriber that sees a number
# missing holds what follows, asks the publisher's cache for the missing ones and delivers the
# publisher's samples in their order. Every RECOVERY_QUERY_S it also asks for any it has not had
# (the publisher's heartbeat cannot tell it: Zenoh ignores heartbeats on a key with a verbatim
# chunk such as @v1), so that the last samples lost are recovered with nothing after them.
CACHE_SAMPLES = 64
RECOVERY_QUERY_S = 0.5
# camera/frame is not recovered so (the source watches its matching status, which an advanced
# publisher does not offer, and re-sends its frames in flight itself, services/source/replay.py):
# after the link to the router came back, a frame of it that skips ahead of the last one handled
# waits this long for the ones before it (lost with the router, sent again by the source), so
# that frames are still handled in order. A gap that is real (a skipped file, a live camera's
# drops) ends the wait.
RECOVERY_S = 5.0
MAX_HELD = 256           # frames waiting per subscription, beyond which the wait ends early
# A message that names the one it follows (EgoMotion.previous_seq: several egomotion instances
# publish out of order) waits for it this long; longer than the source takes to send a lost frame
# again (resend_after) after an instance that died has left the network (its lease).
ORDER_WAIT_S = 20.0
ORDER_WAIT_FIRST_S = 2.0   # ... before the first message was handled (a service started mid-run)


@dataclass
class Counters:
    """What a service has seen; published as ServiceStatus and shown by `gridslam health`."""

    received: int = 0
    published: int = 0
    decode_errors: int = 0
    gaps: int = 0
    stale: int = 0
    replayed: int = 0
    rejected: int = 0
    handler_errors: int = 0
    dropped_newest_only: int = 0
    dropped_busy: int = 0


@dataclass
class Subscription:
    topic: str
    model: type[Message]
    handler: Callable[[Message], None]
    newest_only: bool
    drop_stale: bool
    sparse: bool
    stream: int = 0                                          # its stream in the service's Sequencer
    pending: tuple[str, bytes, str] | None = None   # newest_only: the one sample kept
    lock: threading.Lock = field(default_factory=threading.Lock)
    follows: Callable[[Message], int | None] | None = None   # the seq a message comes after (None: none)
    on_stale: Callable[[Message], None] | None = None       # called for a stale message instead of the replay

    @property
    def ordered(self) -> bool:
        """Every frame is expected, in order (not a sparse, newest-only or replay-accepting topic),
        and one lost on the way is sent again by its sender, not recovered by Zenoh: after a
        reconnection, frames that skip ahead wait for it."""
        return self.drop_stale and not self.sparse and not recovers(self.topic)


def recovers(topic: str) -> bool:
    """Whether samples of `topic` lost on the way are recovered by Zenoh's advanced publisher and
    subscriber (CACHE_SAMPLES): the pipeline's topics but camera/frame."""
    return topic in topics.TOPICS and topic != "camera/frame"


def declare_publisher(session: zenoh.Session, robot: str, topic: str):
    """The publisher of `topic` for `robot`: congestion control BLOCK (offline replay loses
    nothing), reliable; where `recovers(topic)`, numbered and cached, so that a subscriber that
    missed a sample asks for it again."""
    key, encoding = topics.key(robot, topic), zenoh.Encoding(codec.encoding_of(topics.model_of(topic)))
    if recovers(topic):
        return zenoh.ext.declare_advanced_publisher(
            session, key, encoding=encoding, congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE, cache=zenoh.ext.CacheConfig(CACHE_SAMPLES),
            sample_miss_detection=zenoh.ext.MissDetectionConfig())
    return session.declare_publisher(key, encoding=encoding, congestion_control=zenoh.CongestionControl.BLOCK,
                                     reliability=zenoh.Reliability.RELIABLE)


def declare_subscriber(session: zenoh.Session, key: str, on_sample: Callable[[zenoh.Sample], None], recovered: bool):
    """A subscriber of `key`; if `recovered`, one that asks the publishers' caches for the
    samples it missed and delivers each publisher's samples in their order."""
    if not recovered:
        return session.declare_subscriber(key, on_sample)
    return zenoh.ext.declare_advanced_subscriber(
        session, key, on_sample,
        recovery=zenoh.ext.RecoveryConfig(periodic_queries=timedelta(seconds=RECOVERY_QUERY_S)))


@dataclass(frozen=True)
class ServiceParams:
    """What a service process is told beside its runtime (flag --instance; no config key: each
    process of a robot's service is named on its own command line)."""

    instance: str | None = setting(None, help="instance name in the health key (default: HOST-PID)")


class Service:
    """Subclass, set `name`, declare subscriptions in `setup()`, publish with `publish()`."""

    name: ClassVar[str] = "service"
    idle_timeout: float = 0.1   # seconds the main loop waits for a sample before calling on_idle()
    # An observer (the viewer) must never push back on the pipeline: where a pipeline service
    # blocks Zenoh's delivery on a full inbox, an observer drops the sample and counts it.
    observer: ClassVar[bool] = False
    inbox_size: ClassVar[int] = INBOX_SIZE
    # A stage whose state runs across every frame (gridcells, loopclosure, expmap) cannot be
    # shared by two instances: a second one for the same robot refuses to start.
    exclusive: ClassVar[bool] = False

    def __init__(self, runtime: RuntimeConfig, instance: str | None = None):
        self.runtime = runtime
        self.robot = runtime.robot
        self.instance = instance or f"{socket.gethostname()}-{os.getpid()}".replace(".", "-")
        self.counters = Counters()
        self.session: zenoh.Session | None = None
        self.state = "starting"
        self.last_seq = 0
        self.started = time.monotonic()
        self._stop = threading.Event()
        self._inbox: queue.Queue[tuple[int, tuple[str, bytes, str] | None]] = queue.Queue(maxsize=self.inbox_size)
        self._subscriptions: list[Subscription] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._entities: list = []
        self._last_status = 0.0
        self._current_seq: int | None = None
        self._outputs = OutputMemory(REPLAY_FRAMES)   # to answer a re-sent input frame again
        self._link = RouterLink()                     # Zenoh's threads write it
        self._order = Sequencer(SequencerParams(order_wait=ORDER_WAIT_S, order_wait_first=ORDER_WAIT_FIRST_S,
                                                recovery=RECOVERY_S, max_held=MAX_HELD), name=self.name)
        self._gap_events = 0
        self._busy_s = 0.0   # CPU time of this thread in handlers and on_idle: the service's own work
        self._cpu_when_serving: float | None = None   # the process's CPU time when it began serving

    # ----------------------------------------------------------------- for subclasses
    def setup(self) -> None:
        """Declare subscriptions and queryables; the session is open."""

    def on_idle(self) -> None:
        """Called when no sample arrived within `idle_timeout` (producers do their work here)."""

    def teardown(self) -> None:
        """Flush state before the session closes."""

    def subscribe(self, topic: str, handler: Callable[[Message], None], *, newest_only: bool = False,
                  drop_stale: bool = True, sparse: bool = False, follows: Callable[[Message], int | None] | None = None,
                  on_stale: Callable[[Message], None] | None = None, handled_up_to: int | None = None,
                  robot: str | None = None) -> None:
        """Call `handler(message)` on the main thread for every valid message on `topic`.

        `newest_only` keeps just the latest unhandled sample (a live camera: old frames are
        dropped by design and counted); otherwise every sample is handled, in order, and a full
        inbox blocks Zenoh's delivery, which pushes back on BLOCK publishers. `sparse` topics skip
        frames by design (map/update, loop/closure, grid/activity): no gap is counted on them,
        nor on newest-only subscriptions.

        `follows(message)` names the seq a message comes after (EgoMotion.previous_seq): a
        message whose predecessor has not been handled yet waits for it (up to ORDER_WAIT_S),
        so messages published out of order by several instances are handled in order.
        `on_stale(message)` is called for a stale message (a frame sent again) instead of
        publishing this service's earlier outputs for it again (`replay_outputs`). `handled_up_to`:
        the last seq a previous process of this service handled (it resumed from a checkpoint):
        messages up to it are stale. `robot`: another robot's topic (a key chunk, `*` for every
        robot's: the fleet's), instead of this service's robot's."""
        assert self.session is not None, "subscribe() belongs in setup()"
        index = len(self._subscriptions)
        subscription = Subscription(topic, topics.model_of(topic), handler, newest_only, drop_stale, sparse or newest_only,
                                    stream=index, follows=follows, on_stale=on_stale)
        stream = self._order.stream(topic, ordered=subscription.ordered, follows=follows is not None,
                                    handled_up_to=handled_up_to)
        assert stream == index
        self._subscriptions.append(subscription)

        def on_sample(sample: zenoh.Sample) -> None:
            item = (str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding))
            if not subscription.newest_only:
                self._put((index, item))
                return
            with subscription.lock:
                replaced, subscription.pending = subscription.pending, item
            if replaced is None:
                self._put((index, None))   # the main thread takes whatever is newest then
            else:
                self.counters.dropped_newest_only += 1

        # An observer's or a newest-only subscription wants no old samples: nothing is asked for again.
        recovered = recovers(topic) and not (newest_only or self.observer)
        self._entities.append(declare_subscriber(self.session, topics.key(robot or self.robot, topic), on_sample, recovered))

    def queryable(self, topic: str, answer: Callable[..., Message], parameters: bool = False) -> None:
        """Answer queries on `topic` with `answer()` (called on a Zenoh thread: keep it read-only);
        with `parameters`, `answer(get)`, `get(name)` giving the selector's parameter or None. An
        answer that raises a GridslamError replies with its one line as an error."""
        assert self.session is not None, "queryable() belongs in setup()"
        key = topics.key(self.robot, topic)
        self._entities.append(self.session.declare_queryable(key, lambda query: self._reply(query, key, answer, parameters)))

    def watch(self, key: str, on_change: Callable[[zenoh.Sample], None]) -> None:
        """Call `on_change` (on a Zenoh thread) for every liveliness token under `key`: those alive
        now, and each that comes (SampleKind.PUT) or goes (SampleKind.DELETE) later."""
        assert self.session is not None, "watch() belongs in setup()"
        self._entities.append(self.session.liveliness().declare_subscriber(key, on_change, history=True))

    def publish(self, topic: str, message: Message) -> None:
        """Publish a pipeline message on `topic` (congestion control BLOCK: offline replay loses nothing).

        What a handler publishes is remembered for the last REPLAY_FRAMES input frames: when an
        input frame arrives again (a source re-sending the frames in flight after a downstream
        service was restarted), the same outputs are published again instead of recomputed, so
        the restarted service downstream gets them and this service's state is untouched."""
        self._send(topic, message)
        self.counters.published += 1
        if self._current_seq is not None:
            self.remember_output(self._current_seq, topic, message)

    def remember_output(self, seq: int, topic: str, message: Message) -> None:
        """Publish `message` on `topic` again when input frame `seq` arrives again (`publish` does
        this for what a handler publishes; a service restored from disk, for its last frame)."""
        self._outputs.remember(seq, topic, message)

    def _send(self, topic: str, message: Message) -> None:
        self.publisher(topic).put(codec.encode(message))

    def publisher(self, topic: str) -> zenoh.Publisher:
        """The publisher of `topic`, declared on first use."""
        publisher = self._publishers.get(topic)
        if publisher is None:
            publisher = self._publishers[topic] = declare_publisher(self.session, self.robot, topic)
        return publisher

    def header(self, seq: int, stamp: Time | float, frame_id: str = "") -> Header:
        stamp = stamp if isinstance(stamp, Time) else Time.from_seconds(stamp)
        return Header(seq=seq, stamp=stamp, frame_id=frame_id, robot=self.robot)

    def stop(self) -> None:
        """Ask the main loop to end (thread- and signal-safe)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ----------------------------------------------------------------- the loop
    def run(self) -> int:
        """Open the session, serve until stopped, close everything. Returns the exit code."""
        previous = self._install_signal_handlers()
        try:
            try:
                self.session = open_session(self.runtime, self._stop)
            except ServiceStopped:
                return 0
            if self.exclusive:
                self._refuse_if_running()
            self.setup()
            self._entities.append(self.session.liveliness().declare_token(
                topics.health_key(self.robot, self.name, self.instance)))
            self.queryable(f"status/{self.name}/{self.instance}", self.status)
            self._entities.append(self.session.info.declare_transport_events_listener(self._on_transport_event,
                                                                                      history=True))
            self.state = "running"
            self._cpu_when_serving = time.process_time()
            log.info("%s/%s running on robot %s", self.name, self.instance, self.robot)
            while not self._stop.is_set():
                self._serve_once()
                self._publish_status_if_due()
            self.state = "stopping"
            self.teardown()
            # The counters as they end (a source that finished is gone before anyone asks for them).
            self._send(f"status/{self.name}/{self.instance}", self.status())
            return 0
        finally:
            self._close()
            self._restore_signal_handlers(previous)

    def _refuse_if_running(self) -> None:
        """Exit (ConfigError: one line) when another instance of this service serves the same robot."""
        others = set()
        for reply in self.session.liveliness().get(topics.health_key(self.robot, self.name, "*"), timeout=2.0):
            if reply.ok is not None:
                others.add(topics.parse_health_key(str(reply.ok.key_expr))[2])
        others.discard(self.instance)   # our own earlier process (a restart under the same name) is gone
        if others:
            raise ConfigError(f"{self.name} of robot {self.robot} is already running (instance {sorted(others)[0]}); "
                              f"it keeps state across frames, so one instance serves a robot (docs/pipeline.md)")

    def replay_outputs(self, seq: int) -> int:
        """Publish again what the handler published for frame `seq`, if still remembered; how many."""
        outputs = self._outputs.of(seq)
        for topic, output in outputs:
            self._send(topic, output)
        self.counters.replayed += len(outputs)
        return len(outputs)

    def status(self) -> ServiceStatus:
        c = self.counters
        return ServiceStatus(
            header=self.header(self.last_seq, time.time()), service=self.name, instance=self.instance,
            state=self.state, received=c.received, published=c.published, decode_errors=c.decode_errors,
            gaps=c.gaps, stale=c.stale, uptime=time.monotonic() - self.started, extra=self.extra_counters(),
        )

    def extra_counters(self) -> dict[str, float]:
        """Service-specific counters for the status message (override to add some). Always there:
        `cpu_s`, the process's CPU time so far (every thread, start-up included), `serving_cpu_s`,
        the same since it began serving (start-up excluded: the frames' whole cost, with Zenoh's and
        OpenCV's threads), and `busy_cpu_s`, the main thread's CPU time in handlers and on_idle (the
        work per frame, docs/pipeline.md)."""
        c = self.counters
        counters = {"replayed": c.replayed, "rejected": c.rejected, "handler_errors": c.handler_errors,
                    "dropped_newest_only": c.dropped_newest_only, "dropped_busy": c.dropped_busy}
        cpu = time.process_time()
        serving = {} if self._cpu_when_serving is None else {"serving_cpu_s": round(cpu - self._cpu_when_serving, 3)}
        return {**{name: value for name, value in counters.items() if value},
                "cpu_s": round(cpu, 3), **serving, "busy_cpu_s": round(self._busy_s, 3)}

    def _on_transport_event(self, event) -> None:   # a Zenoh thread
        if event.transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        if event.kind == zenoh.SampleKind.DELETE:
            self._link.closed(str(event.transport.zid))
        else:
            self._link.opened(str(event.transport.zid))

    def _serve_once(self) -> None:
        if self._link.down:
            # No router: what this service would publish now is lost, so its inbox waits.
            self._stop.wait(max(self.idle_timeout, 0.01))
            return
        if self._link.back():   # camera/frame's frames lost with the router come again: those after them wait
            self._order.reconnected(time.monotonic())
        for delivery in self._order.due(time.monotonic()):
            self._deliver(delivery)
        try:
            index, item = self._inbox.get(timeout=self.idle_timeout) if self.idle_timeout > 0 else self._inbox.get_nowait()
        except queue.Empty:
            started = time.thread_time()
            self.on_idle()
            self._busy_s += time.thread_time() - started
            return
        subscription = self._subscriptions[index]
        if item is None:   # newest_only: take the latest sample
            with subscription.lock:
                item, subscription.pending = subscription.pending, None
        self._handle(subscription, *item)

    def _handle(self, subscription: Subscription, key: str, payload: bytes, encoding: str) -> None:
        """Decode a sample, put it in order (services/common/sequencing.py), and handle what is due."""
        try:
            message = codec.decode(payload, subscription.model, encoding)
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            if self.counters.decode_errors <= 10 or self.counters.decode_errors % LOG_EVERY == 0:
                log.warning("%s: dropped message on %s (%d so far): %s", self.name, key, self.counters.decode_errors, error)
            return
        self.counters.received += 1
        previous = subscription.follows(message) if subscription.follows is not None else None
        for delivery in self._order.offer(subscription.stream, message.header.seq, previous, (key, message),
                                          time.monotonic(), key, message.header.stride):
            self._deliver(delivery)

    def _deliver(self, delivery: Delivery) -> None:
        """Call the handler on a message in order (stale: replay the outputs instead; a gap: count it)."""
        subscription = self._subscriptions[delivery.stream]
        (key, message), seq, missing, stale = delivery.item, delivery.seq, delivery.missing, delivery.stale
        if delivery.duplicate:
            self.counters.stale += 1   # it came twice while waiting: once is enough
            return
        handler = subscription.handler
        if stale and subscription.drop_stale:
            self.counters.stale += 1
            if subscription.on_stale is None:
                replayed = self.replay_outputs(seq)
                log.debug("%s: stale seq %d on %s (outputs replayed: %d)", self.name, seq, key, replayed)
                return
            handler = subscription.on_stale
        else:
            if missing and not subscription.sparse:
                self.counters.gaps += missing
                self._gap_events += 1
                if self._gap_events <= 10 or self._gap_events % LOG_EVERY == 0:   # a live camera's drops: one a frame
                    log.warning("%s: %d frame(s) missing before seq %d on %s (%d missing so far)", self.name, missing,
                                seq, key, self.counters.gaps)
            self.last_seq = max(self.last_seq, seq)
        self._current_seq = seq
        started = time.thread_time()
        try:
            handler(message)
        except (PersistenceError, OSError):
            raise   # the service cannot keep its state (disk full, say): it stops, and says why
        except GridslamError as error:
            # A message that decodes but that the core cannot use (an image too small for a
            # template, say): counted and dropped like a malformed one; the service keeps running.
            self.counters.rejected += 1
            if self.counters.rejected <= 10 or self.counters.rejected % LOG_EVERY == 0:   # (maybe every frame)
                log.warning("%s: rejected seq %d on %s (%d so far): %s", self.name, seq, key, self.counters.rejected, error)
        except Exception:
            # Not a known rejection: a case the core did not foresee (a numerical corner of OpenCV
            # on a valid but absurd frame, say). One message must not take the service down:
            # the traceback goes to the log, the count to the status, and the next
            # message is served; the frame shows downstream as a gap.
            self.counters.handler_errors += 1
            if self.counters.handler_errors <= 10 or self.counters.handler_errors % LOG_EVERY == 0:
                log.exception("%s: failed on seq %d on %s (%d so far)", self.name, seq, key, self.counters.handler_errors)
        finally:
            self._current_seq = None
            self._busy_s += time.thread_time() - started

    def _put(self, entry: tuple[int, tuple[str, bytes, str] | None]) -> None:
        if self.observer:
            try:
                self._inbox.put_nowait(entry)
            except queue.Full:
                self.counters.dropped_busy += 1
                if entry[1] is None:   # a newest-only marker: let the next sample queue a new one
                    subscription = self._subscriptions[entry[0]]
                    with subscription.lock:
                        subscription.pending = None
            return
        # Blocks Zenoh's delivery thread while the inbox is full: that is the back pressure.
        while not self._stop.is_set():
            try:
                self._inbox.put(entry, timeout=0.1)
                return
            except queue.Full:
                continue

    def _reply(self, query: zenoh.Query, key: str, answer: Callable[..., Message], parameters: bool) -> None:
        # Reply on our own key, not the query's (which may hold wildcards): replies on one key
        # would be consolidated into one.
        try:
            message = answer(query.parameters.get) if parameters else answer()
            query.reply(key, codec.encode(message), encoding=zenoh.Encoding(codec.encoding_of(message)))
        except GridslamError as error:   # a bad request: the querier is told why
            query.reply_err(str(error))
        except Exception:  # a failing answer must not kill Zenoh's thread; the querier times out
            log.exception("%s: query on %s failed", self.name, query.key_expr)

    def _publish_status_if_due(self) -> None:
        now = time.monotonic()
        if now - self._last_status >= STATUS_PERIOD_S:
            self._last_status = now
            self._send(f"status/{self.name}/{self.instance}", self.status())

    def _close(self) -> None:
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception as error:  # already gone with the session; nothing to keep
                log.debug("undeclare failed: %s", error)
        self._entities.clear()
        self._publishers.clear()
        if self.session is not None:
            self.session.close()
            self.session = None

    def _install_signal_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        handler = lambda signum, frame: self.stop()  # noqa: E731
        return {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}

    @staticmethod
    def _restore_signal_handlers(previous) -> None:
        for sig, handler in (previous or {}).items():
            signal.signal(sig, handler)
