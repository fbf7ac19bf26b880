"""docs/clients.md's client (examples/pose_client.py, no gridslam import) receives poses that a
real gridslam service publishes through a real router."""

import re
import subprocess
import sys

import zenoh

from schemas import EgoMotion, PlanarIncrement
from services.common import codec, topics
from tests.messages import header
from tests.netutil import REPO, client_session, endpoint, free_port, start, start_router, stop, wait_for

CLIENT = REPO / "examples" / "pose_client.py"


def test_docs_show_the_tested_client():
    docs = (REPO / "docs" / "clients.md").read_text()
    block = re.search(r"```python\n(.*?)```", docs, re.S).group(1)
    assert block == CLIENT.read_text()
    assert "import gridslam" not in block and "from services" not in block and "from schemas" not in block


def test_client_receives_grid_poses_from_a_running_service():
    port = free_port()
    router = start_router(port)
    service = start(["service", "gridcells", "--integrator", "deadreckoning", "-e", endpoint(port)])
    client = subprocess.Popen([sys.executable, str(CLIENT), "--connect", endpoint(port), "--count", "3"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = client_session(port)
    try:
        wait_for(lambda: any(r.ok for r in session.liveliness().get(f"{topics.PREFIX}/robot0/health/gridcells/*", timeout=1)))
        publisher = session.declare_publisher(topics.key("robot0", "egomotion"),
                                              encoding=zenoh.Encoding(codec.encoding_of(EgoMotion)))
        seq = 0

        def client_done():
            nonlocal seq
            publisher.put(codec.encode(EgoMotion(header=header(seq), increment=PlanarIncrement(forward=1.0, left=0.0, yaw=0.0),
                                                 quality=1.0, estimator="passthrough")))
            seq += 1
            return client.poll() is not None

        wait_for(client_done, timeout=20, period=0.2)
        out, err = client.communicate(timeout=5)
        assert client.returncode == 0, err
        lines = out.strip().splitlines()
        assert len(lines) == 3 and all(line.startswith("grid/pose seq=") for line in lines), out
        # Dead reckoning of 1 m per frame straight ahead: x grows by one per frame.
        xs = [float(re.search(r"x=(-?[\d.]+)", line).group(1)) for line in lines]
        assert [round(b - a, 3) for a, b in zip(xs, xs[1:])] == [1.0, 1.0]
    finally:
        session.close()
        if client.poll() is None:
            client.kill()
        stop(service)
        stop(router)
