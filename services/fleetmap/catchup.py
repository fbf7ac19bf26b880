"""The fleet map's catch-up, a pure core: which part of what a robot sends (a `map/update`, its
`map/snapshot`, its `fleet/closure` and `fleet/closures?from=N`) the fleet map has not taken yet.

The same experience, link or closure may come more than once — live and again from a catch-up,
or live after a restart replayed it from the journal — and some may not come at all (an inbox
full, two routers cut apart). A robot's map grows in order (experiences 0, 1, …, links in the
order its map made them) and its inter-robot closures are numbered from 0, so what the fleet map
has is a count of each, and an input is taken when it is the next one: nothing is fused twice,
and a gap (an input beyond the next) says what to ask for."""

from __future__ import annotations


def map_increment(known: int, links_known: int, experiences: list, first_link: int, links: list):
    """What a robot's map message adds to the ``known`` experiences and ``links_known`` links the
    fleet map has of it: ``(experiences, links)`` new to it, in order, or ``None`` when the message
    does not follow on from what it has (a part went by unheard: take the robot's snapshot).
    ``experiences`` have an ``id``; ``links`` are the message's links from the map's link number
    ``first_link`` on (a snapshot: all of them, from 0)."""
    fresh = sorted((e for e in experiences if e.id >= known), key=lambda e: e.id)
    if first_link > links_known or [e.id for e in fresh] != list(range(known, known + len(fresh))) or \
            (known == 0 and not fresh):
        return None
    return fresh, [link for number, link in enumerate(links, first_link) if number >= links_known]


class ClosureIntake:
    """The inter-robot closures heard, taken once each in every robot's order: ``next[robot]`` is
    the index of the next closure to take from it; the ones taken wait in ``waiting`` until both
    of their frames are on the fleet map (``place``)."""

    def __init__(self):
        self.next: dict[str, int] = {}
        self.waiting: list[tuple[str, object]] = []
        self.duplicates = 0

    def replayed(self, robot: str, index: int) -> None:
        """A closure of ``robot`` taken before (the journal replayed)."""
        self.next[robot] = max(self.next.get(robot, 0), index + 1)

    def missed(self, robot: str, records: list) -> bool:
        """Whether ``records`` (with an ``index``) skip closures of ``robot`` not taken yet."""
        return bool(records) and min(r.index for r in records) > self.next.get(robot, 0)

    def take(self, robot: str, records: list) -> list:
        """Take ``robot``'s closures that come next, in index order (the rest are dropped: a gap
        is filled by asking from ``next[robot]``); returns those taken."""
        taken = []
        for record in sorted(records, key=lambda r: r.index):
            if record.index < self.next.get(robot, 0):
                self.duplicates += 1
            elif record.index == self.next.get(robot, 0):
                self.next[robot] = record.index + 1
                self.waiting.append((robot, record))
                taken.append(record)
        return taken

    def place(self, placement) -> list[tuple[str, object, object]]:
        """The waiting closures that ``placement(robot, record)`` can place (not ``None``), in the
        order they came, as ``(robot, record, placed)``; the others keep waiting."""
        placed, still = [], []
        for robot, record in self.waiting:
            where = placement(robot, record)
            if where is None:
                still.append((robot, record))
            else:
                placed.append((robot, record, where))
        self.waiting = still
        return placed


class FramePlacements:
    """Where one robot's map puts its frames (experience, offset), for placing closures.

    A `map/pose` says the frame's pose and experience; the offset taken from it against the
    experience's pose as last published lags the map's own record whenever the map has moved the
    experience since without publishing it (on the campus 185 of 493 closures were so off, by up to
    0.25 m, and by 0.9 m while map/frames did not answer: hundreds of standard deviations). So a
    frame is placed by the map's own record: the placement its map/pose carries, or for a frame
    whose map/pose had none or was missed, `map/frames`, asked through ``ask(first, last)`` for
    every frame from it to the newest posed: a list of (frame, experience, offset), None when it
    does not answer). While it does not answer (a map busy solving, a robot cut off) the frame
    waits, asked again every ``retry`` seconds; only after ``patience`` seconds of silence (a map
    gone) is the map/pose's placement taken."""

    def __init__(self, kept: int, retry: float, patience: float):
        self.kept, self.retry, self.patience = kept, retry, patience
        self.posed: dict[int, tuple[int, tuple[float, float, float]]] = {}    # from map/pose
        self.placed: dict[int, tuple[int, tuple[float, float, float]]] = {}   # from map/frames
        self.newest = -1
        self.down_until = -float("inf")
        self.silent_since: float | None = None

    def pose(self, frame: int, experience: int, offset: tuple[float, float, float], recorded: bool = False) -> None:
        """A frame's map/pose: ``recorded`` when it carries the map's own placement of the frame
        (`MapPose.placement`), which then needs no asking."""
        self.posed[frame] = (experience, offset)
        self.newest = max(self.newest, frame)
        if len(self.posed) > self.kept:
            del self.posed[next(iter(self.posed))]   # the oldest heard
        if recorded:
            self.placed[frame] = (experience, offset)
            if len(self.placed) > self.kept:
                del self.placed[min(self.placed)]

    def find(self, frame: int, ask, now: float):
        """The frame's (experience, offset), or None while it must wait (not posed yet, or its
        map's record not to be had yet)."""
        found = self.placed.get(frame)
        if found is not None or frame > self.newest:
            return found
        if now >= self.down_until:
            rows = ask(frame, self.newest)
            if rows is None:
                self.down_until = now + self.retry
                self.silent_since = now if self.silent_since is None else self.silent_since
            else:
                self.silent_since = None
                for placed, experience, offset in rows:
                    self.placed[placed] = (experience, tuple(offset))
                for old in sorted(self.placed)[:max(0, len(self.placed) - self.kept)]:
                    del self.placed[old]
                # (a frame its map does not record: the map/pose's)
                return self.placed.get(frame, self.posed.get(frame))
        if self.silent_since is not None and now - self.silent_since >= self.patience:
            return self.posed.get(frame)
        return None
