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
