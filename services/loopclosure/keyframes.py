"""The keyframes of the view templates on disk: an append-only binary file, read back by
template id (docs/closure_geometry.md).

Layout: a 16-byte header (magic ``GSKFSTOR``, format version, zero) and then one record per
keyframe: payload length (uint32), CRC32 of the template id and payload (uint32), template id
(uint64), payload (``Keyframe.to_bytes``), little-endian. Records are flushed as written, so a
killed process leaves every record it wrote; appending a template id again supersedes the
earlier record.

Memory holds only the index (two arrays over the template ids, which are dense: 0, 1, 2, …;
offset and length, 12 bytes per template) and a small LRU cache of decoded keyframes. The file is bounded: a keyframe that
would take it beyond ``max_bytes`` is not stored (counted in ``dropped``, logged once), and
its closures then fall back to what the map does without geometry.

On open, every record is checked: a torn last record (a crash while writing) is cut off with a
warning; a damaged record anywhere else is an error naming the file and byte offset; a file
that is not a keyframe store is refused, untouched.
"""

from __future__ import annotations

import collections
import logging
import os
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np

from services.common.journal import JournalError
from services.loopclosure.geometry import Keyframe, KeyframeError

log = logging.getLogger(__name__)

MAGIC = b"GSKFSTOR"
VERSION = 1
_FILE_HEADER = struct.Struct("<8sII")   # magic, version, reserved
_RECORD = struct.Struct("<IIQ")         # payload length, CRC32 of (template id, payload), template id
_ID = struct.Struct("<Q")
# No keyframe comes near this (200 features take 7.7 KB): a longer record's length field is damaged.
MAX_RECORD = 16 * 2**20


def _crc(template_id: int, payload: bytes) -> int:
    return zlib.crc32(payload, zlib.crc32(_ID.pack(template_id)))


class KeyframeStore:
    """Opens (or creates) the keyframe file at ``path`` and indexes the keyframes in it.

    ``max_bytes`` bounds the file (header and superseded records included); ``cache`` is the
    number of decoded keyframes kept in memory (least recently used ones go first).
    """

    def __init__(self, path: Path, max_bytes: int = 512 * 2**20, cache: int = 256):
        if max_bytes < _FILE_HEADER.size or cache < 0:
            raise ValueError(f"keyframe store: max_bytes = {max_bytes}, cache = {cache} out of range")
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.cache_size = int(cache)
        self.dropped = 0              # keyframes not stored because of max_bytes
        self._offsets = np.full(64, -1, np.int64)   # payload offset per template id, −1: none
        self._lengths = np.zeros(64, np.int32)
        self._count = 0
        self._cache: collections.OrderedDict[int, Keyframe] = collections.OrderedDict()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "a+b", buffering=0)   # writes append; reads seek
        except OSError as error:
            raise JournalError(f"{self.path}: cannot open ({error.strerror})") from None
        try:
            self._size = self._load()
        except BaseException:
            self._file.close()
            raise

    # -- public

    def __len__(self) -> int:
        return self._count

    def __contains__(self, template_id: int) -> bool:
        return 0 <= template_id < len(self._offsets) and self._offsets[template_id] >= 0

    def __enter__(self) -> KeyframeStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def size(self) -> int:
        """Bytes in the file."""
        return self._size

    def append(self, template_id: int, keyframe: Keyframe) -> bool:
        """Store the keyframe of ``template_id`` (superseding an earlier one); False when the
        file would exceed ``max_bytes`` (the keyframe is then counted in ``dropped``)."""
        if template_id < 0 or template_id >= 2**32:
            raise ValueError(f"keyframe store: template id {template_id} out of range")
        payload = keyframe.to_bytes()
        record = _RECORD.pack(len(payload), _crc(template_id, payload), template_id) + payload
        if self._size + len(record) > self.max_bytes:
            if self.dropped == 0:
                log.warning("%s: full (%d bytes of %d); keyframes of new templates are not stored from template %d on",
                            self.path, self._size, self.max_bytes, template_id)
            self.dropped += 1
            return False
        try:
            written = self._file.write(record)
            while written < len(record):   # an unbuffered write may stop short (e.g. a signal)
                written += self._file.write(record[written:])
        except OSError as error:
            raise JournalError(f"{self.path}: cannot append ({error.strerror})") from None
        self._index(template_id, self._size + _RECORD.size, len(payload))
        self._size += len(record)
        self._cache.pop(template_id, None)
        return True

    def get(self, template_id: int) -> Keyframe | None:
        """The keyframe of ``template_id``, or None when none is stored."""
        keyframe = self._cache.get(template_id)
        if keyframe is not None:
            self._cache.move_to_end(template_id)
            return keyframe
        if template_id not in self:
            return None
        offset, length = int(self._offsets[template_id]), int(self._lengths[template_id])
        try:
            self._file.seek(offset - _RECORD.size)
            raw = self._file.read(_RECORD.size + length)
        except OSError as error:
            raise JournalError(f"{self.path}: cannot read ({error.strerror})") from None
        _, crc, _ = _RECORD.unpack_from(raw)
        payload = raw[_RECORD.size:]
        if len(payload) != length or crc != _crc(template_id, payload):
            raise JournalError(f"{self.path}: byte {offset - _RECORD.size}: keyframe record of template "
                               f"{template_id} is damaged (checksum mismatch)")
        try:
            keyframe = Keyframe.from_bytes(payload)
        except KeyframeError as error:
            raise JournalError(f"{self.path}: byte {offset - _RECORD.size}: {error}") from None
        if self.cache_size:
            self._cache[template_id] = keyframe
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return keyframe

    def truncate(self, count: int) -> int:
        """Drop the keyframes of template ids ≥ ``count`` (from the file as well); returns how
        many records were dropped. Called after the template journal is replayed, so a keyframe
        written just before a crash cut off its template's journal record leaves no orphan."""
        records = list(self._scan(verify=False))
        dropped = [i for i, (_, template_id, _) in enumerate(records) if template_id >= count]
        if not dropped:
            return 0
        try:
            if len(dropped) == len(records) - dropped[0]:   # all at the end, as after a crash: cut them off
                os.ftruncate(self._file.fileno(), records[dropped[0]][0] - _RECORD.size)
            else:
                self._rewrite([record for record in records if record[1] < count])
        except OSError as error:
            raise JournalError(f"{self.path}: cannot truncate ({error.strerror})") from None
        self._size = self._load()
        self._cache = collections.OrderedDict((k, v) for k, v in self._cache.items() if k < count)
        return len(dropped)

    def copy_from(self, path: Path) -> None:
        """Take the keyframes of another store (a saved map's, checked with check_file) as this
        one's, replacing what it holds."""
        self._file.close()
        try:
            shutil.copyfile(path, self.path)
            self._file = open(self.path, "a+b", buffering=0)
        except OSError as error:
            raise JournalError(f"{self.path}: cannot copy {path} ({error.strerror or error})") from None
        self._cache.clear()
        self._size = self._load()

    def close(self) -> None:
        if self._file.closed:
            return
        try:
            os.fsync(self._file.fileno())
        except OSError as error:
            log.error("%s: could not flush: %s", self.path, error.strerror)
        finally:
            self._file.close()

    # -- internal

    def _index(self, template_id: int, offset: int, length: int) -> None:
        if template_id >= len(self._offsets):
            grow = max(template_id + 1, 2 * len(self._offsets))
            self._offsets = np.concatenate([self._offsets, np.full(grow - len(self._offsets), -1, np.int64)])
            self._lengths = np.concatenate([self._lengths, np.zeros(grow - len(self._lengths), np.int32)])
        if self._offsets[template_id] < 0:
            self._count += 1
        self._offsets[template_id] = offset
        self._lengths[template_id] = length

    def _load(self) -> int:
        """Check the header (writing it into an empty file), index every record, cut a torn last
        one; the file's size."""
        self._offsets[:] = -1
        self._count = 0
        header = _FILE_HEADER.pack(MAGIC, VERSION, 0)
        self._file.seek(0)
        head = self._file.read(_FILE_HEADER.size)
        if len(head) < _FILE_HEADER.size:
            if not header.startswith(head):
                raise JournalError(f"{self.path}: not a keyframe store (no {MAGIC.decode()} header); use another file")
            # Empty, or the header itself was torn: (re)write it.
            os.ftruncate(self._file.fileno(), 0)
            self._file.write(header)
            return _FILE_HEADER.size
        magic, version, _ = _FILE_HEADER.unpack(head)
        if magic != MAGIC:
            raise JournalError(f"{self.path}: not a keyframe store (no {MAGIC.decode()} header); use another file")
        if version != VERSION:
            raise JournalError(f"{self.path}: keyframe store version {version}, this build reads version {VERSION}; "
                               "use another file")
        end = _FILE_HEADER.size
        for offset, template_id, length in self._scan(verify=True):
            self._index(template_id, offset, length)
            end = offset + length
        size = os.fstat(self._file.fileno()).st_size
        if end < size:
            log.warning("%s: torn last record cut off at byte %d (a crash while writing)", self.path, end)
            os.ftruncate(self._file.fileno(), end)
        return end

    def _scan(self, *, verify: bool):
        return _scan(self._file, self.path, verify=verify)

    def _rewrite(self, records: list[tuple[int, int, int]]) -> None:
        """Replace the file by one holding ``records`` (in order), atomically."""
        temporary = self.path.with_name(self.path.name + ".tmp")
        with open(temporary, "wb") as out:
            out.write(_FILE_HEADER.pack(MAGIC, VERSION, 0))
            for offset, _, length in records:
                self._file.seek(offset - _RECORD.size)
                out.write(self._file.read(_RECORD.size + length))
            out.flush()
            os.fsync(out.fileno())
        os.replace(temporary, self.path)
        self._file.close()
        self._file = open(self.path, "a+b", buffering=0)


def _scan(file, path: Path, *, verify: bool):
    """(payload offset, template id, payload length) of every intact record, in file order.
    With ``verify`` the checksums are checked: a bad record followed by more data is an
    error naming its byte offset; a bad or incomplete last record ends the scan (torn)."""
    size = os.fstat(file.fileno()).st_size
    position = _FILE_HEADER.size
    while position + _RECORD.size <= size:
        file.seek(position)
        length, crc, template_id = _RECORD.unpack(file.read(_RECORD.size))
        end = position + _RECORD.size + length
        if length > MAX_RECORD:
            raise JournalError(f"{path}: byte {position}: keyframe record is damaged (length {length})")
        if end > size:
            return   # torn: the record runs past the end of the file
        if verify:
            payload = file.read(length)
            if crc != _crc(template_id, payload):
                if end == size:
                    return   # torn: the last record's bytes did not all reach the disk
                raise JournalError(f"{path}: byte {position}: keyframe record is damaged (checksum mismatch)")
        yield position + _RECORD.size, template_id, length
        position = end


def check_file(path: Path) -> int:
    """Read a keyframe store without changing it and check every record (a saved map's, before
    it is used): the number of keyframes; JournalError naming the file and what is wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as file:
            head = file.read(_FILE_HEADER.size)
            if len(head) < _FILE_HEADER.size or _FILE_HEADER.unpack(head)[0] != MAGIC:
                raise JournalError(f"{path}: not a keyframe store (no {MAGIC.decode()} header)")
            version = _FILE_HEADER.unpack(head)[1]
            if version != VERSION:
                raise JournalError(f"{path}: keyframe store version {version}, this build reads version {VERSION}")
            return len({template_id for _, template_id, _ in _scan(file, path, verify=True)})
    except FileNotFoundError:
        raise JournalError(f"{path}: no such keyframe store") from None
    except OSError as error:
        raise JournalError(f"{path}: cannot read ({error.strerror})") from None
