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

import collections
import logging
import os
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import zenoh

from schemas import Header, ServiceStatus, Time
from schemas.base import Message
from services.common import codec, topics
from services.common.errors import ConfigError, GridslamError, PersistenceError
from services.common.runtime import RuntimeConfig, ServiceStopped, open_session

log = logging.getLogger(__name__)

INBOX_SIZE = 16          # samples waiting for the main thread; beyond this, publishers are pushed back
REPLAY_FRAMES = 64       # frames whose outputs are kept to answer a re-sent input again
STATUS_PERIOD_S = 1.0    # how often the status message is published
LOG_EVERY = 1000         # after the first 10, one log line per this many decode errors, gaps, rejections
# After the link to the router came back, a frame that skips ahead of the last one handled waits
# this long for the ones before it (lost with the router, sent again by the source), so that
# frames are still handled in order. A gap that is real (a skipped file, a live camera's drops)
# ends the wait.
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
class SeqTracker:
    """Detects gaps and stale (duplicate or out-of-order) `seq` numbers on one subscription."""

    last: int | None = None

    def check(self, seq: int) -> tuple[int, bool]:
        """(frames missing before `seq`, whether `seq` is stale)."""
        if self.last is not None and seq <= self.last:
            return 0, True
        missing = 0 if self.last is None else seq - self.last - 1
        self.last = seq
        return missing, False


@dataclass
class Subscription:
    topic: str
    model: type[Message]
    handler: Callable[[Message], None]
    newest_only: bool
    drop_stale: bool
    sparse: bool
    seq: SeqTracker = field(default_factory=SeqTracker)
    pending: tuple[str, bytes, str] | None = None   # newest_only: the one sample kept
    lock: threading.Lock = field(default_factory=threading.Lock)
    held: dict[int, tuple[str, Message]] = field(default_factory=dict)   # waiting: seq → (key, message)
    follows: Callable[[Message], int | None] | None = None   # the seq a message comes after (None: none)
    on_stale: Callable[[Message], None] | None = None       # called for a stale message instead of the replay
    held_since: float | None = None                          # when the wait for a `follows` link began

    @property
    def ordered(self) -> bool:
        """Every frame is expected, in order (not a sparse, newest-only or replay-accepting topic)."""
        return self.drop_stale and not self.sparse


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
        self._outputs: collections.OrderedDict[int, list[tuple[str, Message]]] = collections.OrderedDict()
        self._routers: set[str] = set()   # routers this session has a link to (Zenoh threads write it)
        self._link_lost = False           # the last one closed
        self._link_back = False           # ... and one opened again since
        self._recovering_until: float | None = None   # frames after a gap wait until then
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
        subscription = Subscription(topic, topics.model_of(topic), handler, newest_only, drop_stale, sparse or newest_only,
                                    follows=follows, on_stale=on_stale)
        subscription.seq.last = handled_up_to
        index = len(self._subscriptions)
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

        self._entities.append(self.session.declare_subscriber(topics.key(robot or self.robot, topic), on_sample))

    def queryable(self, topic: str, answer: Callable[..., Message], parameters: bool = False) -> None:
        """Answer queries on `topic` with `answer()` (called on a Zenoh thread: keep it read-only);
        with `parameters`, `answer(get)`, `get(name)` giving the selector's parameter or None. An
        answer that raises a GridslamError replies with its one line as an error."""
        assert self.session is not None, "queryable() belongs in setup()"
        key = topics.key(self.robot, topic)
        self._entities.append(self.session.declare_queryable(key, lambda query: self._reply(query, key, answer, parameters)))

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
        self._outputs.setdefault(seq, []).append((topic, message))
        while len(self._outputs) > REPLAY_FRAMES:
            self._outputs.popitem(last=False)

    def _send(self, topic: str, message: Message) -> None:
        self.publisher(topic).put(codec.encode(message))

    def publisher(self, topic: str) -> zenoh.Publisher:
        """The publisher of `topic`, declared on first use."""
        publisher = self._publishers.get(topic)
        if publisher is None:
            publisher = self._publishers[topic] = self.session.declare_publisher(
                topics.key(self.robot, topic), encoding=zenoh.Encoding(codec.encoding_of(topics.model_of(topic))),
                congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE,
            )
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
        outputs = self._outputs.get(seq, ())
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
        zid = str(event.transport.zid)
        if event.kind == zenoh.SampleKind.DELETE:
            self._routers.discard(zid)
            self._link_lost = self._link_lost or not self._routers
        else:
            self._routers.add(zid)
            self._link_back = self._link_lost

    def _replay_after_reconnection(self) -> None:
        """Publish the outputs of the last REPLAY_FRAMES frames again, in frame order, before anything new.

        Outputs still queued when the link closed (the router restarted, or this process was
        stopped beyond its lease and the router dropped it) are lost, and the frames handled
        after the link is back would get through first: downstream would see a gap, then count
        the lost frames, re-sent later, as stale, and lose them. Replayed first, they arrive in
        order; what downstream already has is stale to it and costs nothing (issue 7)."""
        self._link_lost = self._link_back = False
        count = 0
        for outputs in list(self._outputs.values()):
            for topic, output in outputs:
                self._send(topic, output)
                count += 1
        self.counters.replayed += count
        log.warning("%s: the link to the router was lost and is back; %d recent output(s) published again",
                    self.name, count)

    def _serve_once(self) -> None:
        if self._link_lost:
            if not self._link_back:
                # No router: what this service would publish now is lost, so its inbox waits.
                self._stop.wait(max(self.idle_timeout, 0.01))
                return
            self._replay_after_reconnection()
            self._recovering_until = time.monotonic() + RECOVERY_S
        if self._recovering_until is not None and time.monotonic() > self._recovering_until:
            self._end_recovery()
        self._end_overdue_waits()
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
        try:
            message = codec.decode(payload, subscription.model, encoding)
        except codec.CodecError as error:
            self.counters.decode_errors += 1
            if self.counters.decode_errors <= 10 or self.counters.decode_errors % LOG_EVERY == 0:
                log.warning("%s: dropped message on %s (%d so far): %s", self.name, key, self.counters.decode_errors, error)
            return
        self.counters.received += 1
        seq = message.header.seq
        last = subscription.seq.last
        if subscription.follows is not None:
            if self._wait_for_previous(subscription, key, message):
                return
        elif self._recovering_until is not None and subscription.ordered and last is not None and seq > last + 1:
            # Frames lost with the router come again after this one: it waits for them.
            if not subscription.held:
                log.warning("%s: seq %d follows %d on %s after a reconnection; waiting up to %.0f s for the frames between",
                            self.name, seq, last, key, RECOVERY_S)
            if seq in subscription.held:
                self.counters.stale += 1   # it came twice while waiting: once is enough
                return
            subscription.held[seq] = (key, message)
            if len(subscription.held) > MAX_HELD:
                self._end_recovery()
            return
        self._deliver(subscription, key, message)
        self._release(subscription)

    def _wait_for_previous(self, subscription: Subscription, key: str, message: Message) -> bool:
        """Hold `message` when the one it follows has not been handled yet; whether it was held."""
        seq, last = message.header.seq, subscription.seq.last
        if self._follows_on(subscription, message) or (last is not None and seq <= last):
            return False
        if seq in subscription.held:
            self.counters.stale += 1   # it came twice while waiting: once is enough
            return True
        if not subscription.held:
            subscription.held_since = time.monotonic()
        subscription.held[seq] = (key, message)
        if len(subscription.held) > MAX_HELD:
            self._stop_waiting(subscription, f"more than {MAX_HELD} messages wait")
        return True

    @staticmethod
    def _follows_on(subscription: Subscription, message: Message) -> bool:
        """Whether `message` may be handled now: the frame it comes after has been."""
        last = subscription.seq.last
        if subscription.follows is None:
            return last is None or message.header.seq <= last + 1
        previous = subscription.follows(message)
        return previous is None or (last is not None and previous <= last)

    def _end_overdue_waits(self) -> None:
        now = time.monotonic()
        for subscription in self._subscriptions:
            if subscription.held_since is None:
                continue
            limit = ORDER_WAIT_S if subscription.seq.last is not None else ORDER_WAIT_FIRST_S
            if now - subscription.held_since > limit:
                self._stop_waiting(subscription, f"waited {limit:.0f} s")

    def _stop_waiting(self, subscription: Subscription, reason: str) -> None:
        seq, _ = min(subscription.held.items())
        previous = subscription.follows(subscription.held[seq][1])
        log.warning("%s: %s on %s for seq %s, which seq %d follows; handling the %d held message(s) with a gap",
                    self.name, reason, subscription.topic, previous, seq, len(subscription.held))
        self._release(subscription, everything=True)

    def _release(self, subscription: Subscription, everything: bool = False) -> None:
        """Handle the held frames that now follow on (all of them, in order, when `everything`)."""
        while subscription.held:
            seq = min(subscription.held)
            if not everything and not self._follows_on(subscription, subscription.held[seq][1]):
                return
            self._deliver(subscription, *subscription.held.pop(seq))
        subscription.held_since = None

    def _end_recovery(self) -> None:
        self._recovering_until = None
        for subscription in self._subscriptions:
            self._release(subscription, everything=True)

    def _deliver(self, subscription: Subscription, key: str, message: Message) -> None:
        """Check `seq` (stale: replay the outputs; a gap: count it) and call the handler."""
        seq = message.header.seq
        missing, stale = subscription.seq.check(seq)
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
            # on a valid but absurd frame, say). One message must not take the service down
            # (issue 7): the traceback goes to the log, the count to the status, and the next
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
