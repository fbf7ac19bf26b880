"""The expmap service's queryable map/route on real in-process sessions: a query with two
points gets the shortest route over the map (and the route is published for the viewer); a bad
point is an error reply naming the parameter."""

import threading

from schemas import MapRoute
from services.common import codec, topics
from services.common.runtime import RuntimeConfig
from services.expmap.service import ExpMapConfig, ExpMapService
from tests.netutil import client_session, endpoint, free_port, router_session, wait_for
from tests.unit.test_expmap import deliver, messages, square_steps


def test_a_route_query_gets_the_shortest_route_and_a_bad_point_an_error(tmp_path):
    port = free_port()
    router = router_session(port)
    expmap = ExpMapService(RuntimeConfig(connect=[endpoint(port)]), ExpMapConfig(store=tmp_path / "map.log",
                                                                                  new_experience_distance=0.6))
    expmap._send = lambda topic, message: None    # a square driven 1.25 times, in the map before serving
    deliver(expmap, messages(square_steps()))
    del expmap._send
    thread = threading.Thread(target=expmap.run)
    thread.start()
    client = client_session(port)
    published = []
    subscriber = client.declare_subscriber(topics.key("robot0", "map/route"), lambda sample: published.append(sample))
    try:
        key = topics.key("robot0", "map/route")
        wait_for(lambda: any(r.ok for r in client.liveliness().get(topics.health_key("robot0", "expmap", expmap.instance),
                                                                  timeout=1)))
        replies = list(client.get(f"{key}?from=0,0;to=2,2", timeout=5))
        assert len(replies) == 1 and replies[0].ok is not None
        route = codec.decode(replies[0].ok.payload.to_bytes(), MapRoute, str(replies[0].ok.encoding))
        assert route.found and route.experiences[0] == 0 and len(route.poses) == len(route.experiences) >= 2
        assert abs(route.poses[-1].position.x - 2.0) < 0.7 and abs(route.poses[-1].position.y - 2.0) < 0.7
        assert 3.0 < route.length < 6.0   # round two sides of the 2 m square, not across it
        wait_for(lambda: published)
        bad = list(client.get(f"{key}?from=0,0;to=north", timeout=5))
        assert len(bad) == 1 and bad[0].err is not None and "parameter 'to'" in bad[0].err.payload.to_string()
    finally:
        subscriber.undeclare()
        expmap.stop()
        thread.join(timeout=10)
        client.close()
        router.close()
