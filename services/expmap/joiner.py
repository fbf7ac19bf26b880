"""The map's frames, joined from its three inputs by frame number (`seq`).

A frame of the map is its grid pose, its view template and the loop closures confirmed on it
(the view says how many: several share the frame's seq). They arrive on three topics in any
interleaving; the joiner hands out whole frames in frame order, so the map, deterministic in its
input order, is the same whatever order the topics' messages arrive in:

- a frame waits until its pose, its view and all of its closures are in;
- a frame whose view never comes (loopclosure rejected the image) is skipped once a later view
  arrived (views come in frame order), rather than holding every later frame behind it;
- a frame the map already holds (re-sent after a restart) goes out at once, marked `in_map`, to
  be answered again; its closures are not waited for, and a closure for it is stale, as is one
  already in hand.

Pure: the messages are opaque here; the adapter passes their seq and what the joiner needs of
them, and `mapped`, the last seq the map holds (None: none).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class JoinedFrame:
    seq: int
    pose: Any
    view: Any
    closures: tuple[Any, ...]   # in the order of the frames they close (their `frame`)
    in_map: bool                # the map holds it already: answer it again, apply nothing


class FrameJoiner:
    """Grid poses (`pose`), view templates (`view`) and loop closures (`closure`) in, whole
    frames out (`next`), in frame order."""

    def __init__(self):
        self._poses: dict[int, Any] = {}
        self._views: dict[int, tuple[Any, int]] = {}                # seq → (view, closures it announces)
        self._closures: dict[int, list[tuple[int, Any]]] = {}      # seq → [(frame it closes, closure)]
        self.skipped = 0   # frames with a pose but no view template

    @property
    def held(self) -> tuple[int, int, int]:
        """How many poses, views and frames' closures wait (bounded: what is older than the last
        frame out is dropped)."""
        return len(self._poses), len(self._views), len(self._closures)

    def pose(self, seq: int, pose: Any) -> None:
        self._poses[seq] = pose

    def view(self, seq: int, view: Any, closures: int) -> None:
        """The view template of frame `seq`, which announces `closures` loop closures."""
        self._views[seq] = (view, closures)

    def closure(self, seq: int, frame: int, closure: Any, mapped: int | None) -> bool:
        """A loop closure confirmed on frame `seq`, closing frame `frame` (of the map's numbering);
        False (stale: dropped) when the map holds frame `seq` already or this closure is in hand."""
        closures = self._closures.get(seq, [])
        if (mapped is not None and seq <= mapped) or any(f == frame for f, _ in closures):
            return False
        self._closures[seq] = [*closures, (frame, closure)]
        return True

    def next(self, mapped: int | None) -> JoinedFrame | None:
        """The next whole frame in frame order, or None while it waits for an input."""
        while self._poses:
            seq = min(self._poses)
            entry = self._views.get(seq)
            if entry is None and any(s > seq for s in self._views):
                # Views come in frame order, so this frame's never will (loopclosure rejected it):
                # skip it rather than hold every later frame behind it.
                self._poses.pop(seq)
                self.skipped += 1
                log.warning("expmap: frame %d skipped: no view template for it, later ones arrived", seq)
                continue
            if entry is None:
                return None
            in_map = mapped is not None and seq <= mapped   # re-sent after a restart
            if not in_map and len(self._closures.get(seq, ())) < entry[1]:
                return None
            pose = self._poses.pop(seq)
            view, _ = self._views.pop(seq)
            closures = sorted(self._closures.pop(seq, ()), key=lambda pair: pair[0])
            for stale in [s for s in self._views if s < seq]:
                del self._views[stale]
            for stale in [s for s in self._closures if s < seq]:
                del self._closures[stale]
            return JoinedFrame(seq, pose, view, tuple(closure for _, closure in closures), in_map)
        return None
