"""The map log when the crash came before the first record was complete (services/expmap/store.py
on services/common/journal.py): a torn header is cut and written again, so the service starts
an empty map and a later restart reads what it wrote."""

from __future__ import annotations

import logging
from dataclasses import asdict

from services.common.journal import _line
from services.expmap.graph import MapParams
from services.expmap.store import FORMAT, VERSION, MapStore, Step

PARAMS = MapParams(new_experience_distance=0.6)
STEPS = [Step(k, 0.1 * k, (0.2 * k, 0.0, 0.0), k // 3, None) for k in range(6)]


def header_line() -> str:
    return _line({"format": FORMAT, "version": VERSION, "params": asdict(PARAMS)})


def test_a_torn_header_is_written_again_and_the_log_reopens(tmp_path, caplog):
    path = tmp_path / "map.log"
    path.write_text(header_line()[:25])   # killed while writing the header of a new log
    with caplog.at_level(logging.WARNING):
        store = MapStore(path, PARAMS)
    assert "torn" in caplog.text and store.steps == []
    for step in STEPS:
        store.append(step)
    store.close()
    assert path.read_text().splitlines(keepends=True)[0] == header_line()
    reopened = MapStore(path, PARAMS)
    assert reopened.steps == STEPS
    reopened.close()


def test_a_header_with_a_bad_checksum_and_nothing_after_is_written_again(tmp_path, caplog):
    path = tmp_path / "map.log"
    path.write_text(header_line().replace('"version"', '"versioN"'))   # complete line, wrong CRC
    with caplog.at_level(logging.WARNING):
        store = MapStore(path, PARAMS)
    assert "torn last record" in caplog.text
    store.append(STEPS[0])
    store.close()
    assert MapStore(path, PARAMS).steps == STEPS[:1]
