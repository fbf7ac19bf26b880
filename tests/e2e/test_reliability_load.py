"""Load (issue 7), the short CI variant of `gridslam bench load` (docs/reliability.md has the
2,000-frame figures): the source at its full rate on 1241×376 stereo frames through the whole
stack. No frame is missing, and no process's resident memory grows with the frames it has
handled: a queue growing anywhere would hold about a megabyte per frame."""

from __future__ import annotations

import pytest

from services.benchmarks.load import growth, measure_load
from tests.netutil import endpoint, free_port

pytestmark = pytest.mark.serial   # memory and rates at full load

FRAMES = 120


def test_full_rate_1241x376_stereo_holds_memory_flat(tmp_path):
    result = measure_load(FRAMES, tmp_path, endpoint(free_port()))
    assert result.missing_frames == 0 and not result.restarts
    names = {record.name for record in result.processes.values()}
    assert {"router", "source", "egomotion", "gridcells", "loopclosure", "expmap", "runner"} <= names, names
    for record in result.processes.values():
        early, late, _ = growth(record, FRAMES)
        assert early is not None and late is not None, record.name
        # 90 frames between the two samples: a queue of them would be ~80 MiB.
        assert (late - early) / 1024 < 40, (record.name, early, late)
        assert record.peak_kib / 1024 < 1024, (record.name, record.peak_kib)
    assert result.throughput_fps is not None and result.throughput_fps > 0
