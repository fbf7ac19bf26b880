"""An append-only journal of JSON records, one per line as `JSON<TAB>CRC32`, flushed as written
so a killed process leaves every record it wrote on disk. Services keep their inputs (or their
decisions) in one and rebuild their state by replaying it after a restart.

The first line is a header (format, version, parameters); reopening with another header is an
error, since replaying under other parameters would build another state. A torn last record
(the process died mid-write: no newline, or a bad checksum) is reported with a warning and cut
off; a damaged record anywhere else is an error naming the file and line.
"""

from __future__ import annotations

import json
import logging
import os
import zlib
from pathlib import Path

from services.common.errors import DataError, PersistenceError

log = logging.getLogger(__name__)


class JournalError(PersistenceError, DataError):
    """A journal that cannot be read or written (the message names the file and line)."""


def _line(record: dict) -> str:
    text = json.dumps(record, separators=(",", ":"), allow_nan=False)
    return f"{text}\t{zlib.crc32(text.encode()):08x}\n"


class Journal:
    """Opens (or creates) a journal; `records` holds the records already in it (header excluded)."""

    def __init__(self, path: Path, header: dict):
        self.path = Path(path)
        self.records: list[dict] = []
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.exists() and self.path.stat().st_size > 0:
                self._load(header)
            else:
                with open(self.path, "w") as handle:
                    handle.write(_line(header))
            self.handle = open(self.path, "a")
        except OSError as error:
            raise JournalError(f"{self.path}: cannot open ({error.strerror})") from None

    def append(self, record: dict) -> None:
        try:
            self.handle.write(_line(record))
            self.handle.flush()
        except OSError as error:
            raise JournalError(f"{self.path}: cannot append ({error.strerror})") from None
        self.records.append(record)

    def close(self) -> None:
        try:
            self.handle.flush()
            os.fsync(self.handle.fileno())
        except OSError as error:
            log.error("%s: could not flush: %s", self.path, error.strerror)
        finally:
            self.handle.close()

    def _load(self, header: dict) -> None:
        expected = _line(header).encode()
        with open(self.path, "rb") as handle:
            first = handle.readline()
        if not (expected.startswith(first) or first.startswith(expected.split(b",")[0])):
            # Neither this kind of journal's header (maybe torn, or damaged after its format)
            # nor a prefix of it: some other file, given by mistake. It is left untouched.
            raise JournalError(f"{self.path}: not a {header.get('format', 'gridslam')} journal (line 1 is no header of "
                               "one); use another file")
        records, good, _ = read_records(self.path)
        if records and records[0] != header:
            raise JournalError(f"{self.path}: written with {records[0]}, not {header}; "
                               "use another file or the same parameters")
        self.records = records[1:]
        if good < self.path.stat().st_size:   # cut the torn record so that appends follow intact ones
            with open(self.path, "r+b") as handle:
                handle.truncate(good)
                if good == 0:   # the torn record was the header itself: write it again
                    handle.write(_line(header).encode())


def read_records(path: Path) -> tuple[list[dict], int, bool]:
    """The intact records of a journal, header first, the bytes they span, and whether a torn
    last record was left out (logged as a warning). Only reads: a service may be appending."""
    try:
        with open(path, "rb") as handle:
            lines = handle.read().split(b"\n")
    except FileNotFoundError:
        raise JournalError(f"{path}: no such file") from None
    except OSError as error:
        raise JournalError(f"{path}: cannot read ({error.strerror})") from None
    complete, tail = lines[:-1], lines[-1]   # the part after the last newline is torn, if any
    records, good, torn = [], 0, bool(tail)
    for number, raw in enumerate(complete, start=1):
        text, tab, crc = raw.decode("utf-8", errors="replace").rpartition("\t")
        if not tab or f"{zlib.crc32(text.encode()):08x}" != crc:
            if number == len(complete) and not tail:
                torn = True
                break
            raise JournalError(f"{path}: line {number}: record is damaged (checksum mismatch)")
        records.append(json.loads(text))
        good += len(raw) + 1
    if torn:
        log.warning("%s: torn last record skipped (a crash while writing)", path)
    return records, good, torn


SESSION = "session"   # a journal record {"session": k, "localize": ..., "map": ...}: the records after it are session k's


def sessions(records: list[dict]) -> list[dict]:
    """The session records of a journal's records (header excluded)."""
    return [record for record in records if SESSION in record]


def continue_session(source: Path, target: Path, header: dict, localize: bool, origin: Path) -> dict:
    """Start the journal ``target`` as a copy of the journal ``source`` (a saved map's, in the
    results folder ``origin``) followed by the record that starts its next session, and return
    that record. The source is only read, and checked first — its header must be ``header`` (the
    same kind of journal, written with the same parameters) and every record intact (a torn last
    one is left out, with a warning)."""
    source, target = Path(source), Path(target)
    records, good, _ = read_records(source)
    if not records or records[0].get("format") != header.get("format"):
        raise JournalError(f"{source}: not a {header.get('format', 'gridslam')} journal")
    if records[0] != header:
        differing = sorted(key for key in {**records[0].get("params", {}), **header.get("params", {})}
                           if records[0].get("params", {}).get(key) != header.get("params", {}).get(key))
        what = f"other parameters ({', '.join(differing)})" if differing else "another version or vocabulary"
        raise JournalError(f"{source}: the map was made with {what} than this run's; run with the settings "
                           "(preset, config) it was made with")
    record = {SESSION: 1 + len(sessions(records[1:])), "localize": bool(localize), "map": str(origin)}
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(source, "rb") as handle:
            intact = handle.read(good)
        with open(target, "wb") as handle:
            handle.write(intact)
            handle.write(_line(record).encode())
            handle.flush()
            os.fsync(handle.fileno())
    except OSError as error:
        raise JournalError(f"{target}: cannot write ({error.strerror or error})") from None
    return record
