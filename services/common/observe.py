"""What the observers of a running pipeline (the viewer, the Foxglove bridge, the ROS 2 node)
take from it, declared once: which topics, subscribed how, and the map's messages as plain
tuples (the run recorder and the exports read them the same way)."""

from __future__ import annotations

from typing import Callable

# How an observer subscribes to each topic (Service.subscribe's options): every sample, in
# order, of what draws a path or builds the map; the newest only of the heavy or momentary ones.
# egomotion follows its predecessor (EgoMotion.previous_seq): several instances publish out of order.
OBSERVED: dict[str, dict] = {
    "egomotion": {"follows": lambda message: message.previous_seq},
    "grid/pose": {},
    "map/pose": {},
    "map/update": {"sparse": True},
    "loop/closure": {"sparse": True},
    "map/route": {"sparse": True},
    "camera/frame": {"newest_only": True},
    "grid/activity": {"newest_only": True},
    "view/template": {"newest_only": True},
}

# The experience map's link kinds, as every observer draws them.
ODOMETRIC, CLOSURE_KEPT, CLOSURE_REFUSED = 0, 1, 2


def observe(service, handlers: dict[str, Callable]) -> None:
    """Subscribe `service` (a common.service.Service, in its setup) to each topic of `handlers`
    as an observer. drop_stale=False: a seq going back is a new run, or a frame sent again,
    which the observer tells apart itself."""
    for topic, handler in handlers.items():
        service.subscribe(topic, handler, drop_stale=False, **OBSERVED[topic])


def link_kind(loop_closure: bool, accepted: bool = True) -> int:
    """ODOMETRIC, CLOSURE_KEPT or CLOSURE_REFUSED (a closure the map did not let bend it)."""
    return ODOMETRIC if not loop_closure else CLOSURE_KEPT if accepted else CLOSURE_REFUSED


def map_items(message) -> tuple[list[tuple[int, float, float]], list[tuple[int, int, int]]]:
    """A MapUpdate's or MapSnapshot's experiences (id, x, y) and links (source, target, kind)."""
    return ([(e.id, e.x, e.y) for e in message.experiences],
            [(link.source, link.target, link_kind(link.loop_closure, link.accepted)) for link in message.links])
