"""What a service keeps to recover from faults around it (docs/reliability.md).

- `OutputMemory`: what the service published for each of its last input frames. A frame that
  arrives again (a source re-sending the frames in flight after a downstream service was
  restarted) gets the same outputs published again instead of recomputed, so the restarted
  service downstream gets them and this service's state is untouched. (Samples lost on the
  way, with a router or a lease, are another matter: Zenoh's advanced publisher keeps them and
  the subscribers that missed them ask for them again, services/common/service.py.)
- `RouterLink`: whether this process's session has a link to a router, from the transport's
  events: lost (no router left: what the service publishes now is lost, so its inbox waits) and
  back (a router again: the camera frames lost with it come again from the source, and the ones
  after them wait, services/common/sequencing.py).

Pure: no zenoh here; the adapter turns Zenoh's transport events into `opened` and `closed`.
"""

from __future__ import annotations

import collections
from typing import Any

REPLAY_FRAMES = 64       # frames whose outputs are kept to answer a re-sent input again


def sent_again(last: int | None, seq: int) -> bool:
    """Whether an output of frame `seq`, on a stream whose newest frame so far is `last`, is one
    sent again (a service answering a re-sent input frame with its kept outputs, at most
    REPLAY_FRAMES back) rather than a new one or a new run's first."""
    return last is not None and last - REPLAY_FRAMES <= seq <= last


def new_run(last: int | None, seq: int) -> bool:
    """Whether frame `seq`, on a stream whose newest frame so far is `last`, starts a new run of
    the robot: further back than a frame sent again can be. Every observer of a pipeline (the
    viewer, the Foxglove bridge, the ROS 2 node, the fleet map) tells the three apart by these
    two rules: newer than `last` (the next frame), `sent_again` (drawn already: dropped) and
    `new_run` (the track starts afresh). A run shorter than REPLAY_FRAMES that is run again
    from its start is taken as sent again: by its frame numbers alone it is one."""
    return last is not None and seq < last - REPLAY_FRAMES


class OutputMemory:
    """The outputs (topic, message) published for each of the last `frames` input frames."""

    def __init__(self, frames: int):
        self.frames = frames
        self._outputs: collections.OrderedDict[int, list[tuple[str, Any]]] = collections.OrderedDict()

    def remember(self, seq: int, topic: str, message: Any) -> None:
        self._outputs.setdefault(seq, []).append((topic, message))
        while len(self._outputs) > self.frames:
            self._outputs.popitem(last=False)

    def of(self, seq: int) -> list[tuple[str, Any]]:
        """What was published for input frame `seq` (nothing once it is older than the last `frames`)."""
        return list(self._outputs.get(seq, ()))

    def __len__(self) -> int:
        return len(self._outputs)


class RouterLink:
    """The links of one session to routers. `opened` and `closed` come from the transport's
    threads; the service's thread reads `down` (the last link closed, none back yet) and takes
    `back()` (a link came back since the last one closed) once."""

    def __init__(self):
        self._routers: set[str] = set()
        self._lost = False   # the last link closed
        self._back = False   # ... and one opened again since

    def opened(self, router: str) -> None:
        self._routers.add(router)
        self._back = self._lost

    def closed(self, router: str) -> None:
        self._routers.discard(router)
        self._lost = self._lost or not self._routers

    @property
    def down(self) -> bool:
        """No router since the last link closed: what is published now is lost."""
        return self._lost and not self._back

    def back(self) -> bool:
        """Whether the link came back after it was lost (then frames that skip ahead wait for the
        ones lost); true once per loss."""
        if self._lost and self._back:
            self._lost = self._back = False
            return True
        return False
