"""Strip the symbol tables and debug sections of ELF shared libraries, in place.

    python strip_symbols.py DIR ...      # every *.so and *.so.N under each DIR

deploy/Dockerfile runs it on the dependencies' libraries in its build stage, whose base image
has no binutils (and an offline build cannot install them): it does for a shared library what
`strip --strip-unneeded` does. A shared library is loaded and linked through its program
headers and its dynamic symbol table (`.dynsym`); the static symbol table (`.symtab`,
`.strtab`) and the DWARF sections (`.debug_*`) serve debuggers and symbolised backtraces only,
and some wheels ship them (docs/deploy.md, "What the image weighs").

Only 64-bit little-endian files are touched, and only where every section to drop and every
other non-loaded section lies after the last byte the loader reads: those are moved up, the
section header table is rewritten without the dropped entries, and the file is truncated. Any
other layout (or a file that is not ELF) is left as it is. Pure standard library: it runs with
the image's Python before anything else is installed.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

EHDR = struct.Struct("<16sHHIQQQIHHHHHH")   # ELF64 header
PHDR = struct.Struct("<IIQQQQQQ")           # program header
SHDR = struct.Struct("<IIQQQQIIQQ")         # section header
SHF_ALLOC = 0x2
SHF_INFO_LINK = 0x40
SHT_RELA, SHT_NOBITS, SHT_REL = 4, 8, 9
PT_LOAD = 1
SHN_LORESERVE = 0xFF00


def droppable(name: str) -> bool:
    return name in (".symtab", ".strtab") or name.startswith(".debug")


def strip(data: bytes) -> bytes | None:
    """The library without its symbol table and debug sections, or None when there is nothing
    to drop or the file is not laid out as this function expects."""
    if len(data) < EHDR.size or data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        return None   # not ELF64 little-endian
    header = list(EHDR.unpack_from(data))
    phoff, shoff, phentsize, phnum, shentsize, shnum, shstrndx = (header[5], header[6], header[9], header[10],
                                                                  header[11], header[12], header[13])
    if shoff == 0 or shnum == 0 or shstrndx >= SHN_LORESERVE or shentsize != SHDR.size or phentsize != PHDR.size:
        return None
    segments = [list(PHDR.unpack_from(data, phoff + i * PHDR.size)) for i in range(phnum)]
    sections = [list(SHDR.unpack_from(data, shoff + i * SHDR.size)) for i in range(shnum)]
    names_offset = sections[shstrndx][4]
    names = [data[names_offset + s[0]:data.index(b"\0", names_offset + s[0])].decode("ascii", "replace")
             for s in sections]
    drop = {i for i in range(1, shnum) if droppable(names[i])}
    if not drop:
        return None

    # What the loader reads, as runs of bytes: the ELF and program headers and every segment.
    # They keep their order; the holes between them (where the dropped sections are, ahead of
    # the segments that patchelf appends when a wheel is repaired) shrink by whole multiples of
    # the largest segment alignment, so each segment's offset stays congruent to its address.
    ranges = sorted([(0, EHDR.size), (phoff, phoff + phnum * PHDR.size)]
                    + [(p[2], p[2] + p[5]) for p in segments if p[5]])
    runs: list[list[int]] = []
    for begin, end in ranges:
        if runs and begin <= runs[-1][1]:
            runs[-1][1] = max(runs[-1][1], end)
        else:
            runs.append([begin, end])
    align = max([p[7] for p in segments if p[0] == PT_LOAD] + [1])

    def run_of(offset: int) -> int | None:
        return next((k for k, (begin, end) in enumerate(runs) if begin <= offset <= end), None)

    def loaded(section: list[int]) -> bool:
        return section[2] & SHF_ALLOC or section[1] == SHT_NOBITS

    for i in range(1, shnum):
        begin, size = sections[i][4], 0 if sections[i][1] == SHT_NOBITS else sections[i][5]
        inside = any(b < begin + size and begin < e for b, e in runs)
        if (i in drop and (loaded(sections[i]) or inside)) or (loaded(sections[i]) and run_of(begin) is None):
            return None   # a section to drop is loaded, or one that is loaded lies outside the segments
    moved = [i for i in range(1, shnum) if i not in drop and not loaded(sections[i])
             and not any(b <= sections[i][4] < e for b, e in runs)]
    kept = [i for i in range(shnum) if i not in drop]
    index = {old: new for new, old in enumerate(kept)}

    out = bytearray()
    shifts = []
    for begin, end in runs:
        shift = (begin - len(out)) // align * align
        shifts.append(shift)
        out += bytes(begin - shift - len(out))
        out += data[begin:end]
    for segment in segments:
        segment[2] -= shifts[run_of(segment[2])] if segment[5] else 0
    header[5] -= shifts[run_of(phoff)]
    for i in kept:
        section = sections[i]
        link = 0 if section[6] == 0 else index.get(section[6])
        info_is_index = section[1] in (SHT_REL, SHT_RELA) or section[2] & SHF_INFO_LINK
        info = (0 if section[7] == 0 else index.get(section[7])) if info_is_index else section[7]
        if link is None or info is None:
            return None   # a kept section refers to a dropped one
        section[6], section[7] = link, info
        if i in moved:
            out += bytes(-len(out) % max(section[8], 1))
            offset, section[4] = section[4], len(out)
            out += data[offset:offset + section[5]]
        elif i:
            section[4] -= shifts[run_of(section[4])]
    out += bytes(-len(out) % 8)
    header[6], header[12], header[13] = len(out), len(kept), index[shstrndx]
    for i in kept:
        out += SHDR.pack(*sections[i])
    out[:EHDR.size] = EHDR.pack(*header)
    for k, segment in enumerate(segments):
        PHDR.pack_into(out, header[5] + k * PHDR.size, *segment)
    return bytes(out)


def strip_file(path: Path) -> int:
    """Strip one library in place (its mode and hard links stay); the bytes saved."""
    data = path.read_bytes()
    stripped = strip(data)
    if stripped is None:
        return 0
    with open(path, "r+b") as handle:
        handle.write(stripped)
        handle.truncate()
    return len(data) - len(stripped)


def libraries(folder: Path):
    for path in sorted(folder.rglob("*.so*")):
        if path.is_file() and not path.is_symlink() and (path.suffix == ".so" or ".so." in path.name):
            yield path


def main(folders: list[str]) -> int:
    saved = sum(strip_file(path) for folder in folders for path in libraries(Path(folder)))
    print(f"strip_symbols: {saved / 1e6:.1f} MB of symbol tables and debug sections removed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
