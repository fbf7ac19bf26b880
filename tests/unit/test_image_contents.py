"""What deploy/Dockerfile cuts from the image, checked without Docker (docs/deploy.md, "What the
image weighs"): deploy/strip_symbols.py strips a real library that still loads and works; the
command line and every service import nothing of scipy but fft (and what it imports), which is
all of scipy the image keeps."""

from __future__ import annotations

import importlib.util
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import hnswlib

from tests.netutil import REPO

spec = importlib.util.spec_from_file_location("strip_symbols", REPO / "deploy" / "strip_symbols.py")
strip_symbols = importlib.util.module_from_spec(spec)
spec.loader.exec_module(strip_symbols)


def section_names(data: bytes) -> list[str]:
    """The section names of an ELF64 file, read with the struct layouts of the ELF format."""
    header = strip_symbols.EHDR.unpack_from(data)
    shoff, shnum, shstrndx = header[6], header[12], header[13]
    sections = [strip_symbols.SHDR.unpack_from(data, shoff + i * 64) for i in range(shnum)]
    names = sections[shstrndx][4]
    return [data[names + s[0]:data.index(b"\0", names + s[0])].decode() for s in sections]


def test_stripped_library_loses_its_symbols_and_debug_sections_and_still_works(tmp_path):
    """hnswlib's wheel ships DWARF sections and segments that auditwheel's patchelf appended
    after them: stripped, it is a fraction of its size, every symbol binds at load time
    (LD_BIND_NOW), and an index built with it finds its nearest neighbours."""
    original = Path(hnswlib.__file__)
    assert {".symtab", ".debug_info"} <= set(section_names(original.read_bytes()))
    copy = tmp_path / original.name
    shutil.copy(original, copy)
    libraries = original.parent / "chroma_hnswlib.libs"   # found through the module's $ORIGIN run path
    if libraries.is_dir():
        shutil.copytree(libraries, tmp_path / libraries.name)
    saved = strip_symbols.strip_file(copy)
    stripped = copy.read_bytes()
    assert saved > original.stat().st_size / 2
    names = section_names(stripped)
    assert not [name for name in names if name in (".symtab", ".strtab") or name.startswith(".debug")]
    assert {".dynsym", ".dynstr", ".text", ".shstrtab"} <= set(names)
    assert strip_symbols.strip(stripped) is None   # nothing left to drop: a second pass leaves it as it is
    program = ("import numpy as np, hnswlib; index = hnswlib.Index(space='l2', dim=8); "
               "index.init_index(max_elements=100); data = np.random.default_rng(0).random((100, 8)).astype(np.float32); "
               "index.add_items(data, np.arange(100)); labels, _ = index.knn_query(data[:10], k=1); "
               "assert (labels[:, 0] == np.arange(10)).all(); print(hnswlib.__file__)")
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60,
                            env={"PYTHONPATH": str(tmp_path), "LD_BIND_NOW": "1", "OPENBLAS_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == str(copy)


def test_other_files_are_left_as_they_are(tmp_path):
    text = tmp_path / "notes.so.txt"
    text.write_bytes(b"not an ELF file")
    elf32 = tmp_path / "lib32.so"
    elf32.write_bytes(b"\x7fELF\x01\x01" + bytes(58))
    assert strip_symbols.main([str(tmp_path)]) == 0
    assert text.read_bytes() == b"not an ELF file" and elf32.read_bytes() == b"\x7fELF\x01\x01" + bytes(58)
    assert strip_symbols.strip(struct.pack("<4s", b"\x7fELF")) is None


def test_the_command_line_and_the_services_import_only_scipy_fft():
    """The image keeps scipy.fft and what it imports (special, _lib): `gridslam` builds its whole
    parser for any command, and each service imports its module and what its settings name."""
    program = ("import importlib, sys; from services.cli import build_parser; build_parser(); "
               "from services.cli.service import SERVICES; [importlib.import_module(m) for m in SERVICES.values()]; "
               "import services.source.datasets, services.source.camera, services.source.synthetic, "
               "services.expmap.optimizers, services.evaluation.results; "
               "print(' '.join(sorted({'.'.join(m.split('.')[:2]) for m in sys.modules if m.startswith('scipy.')})))")
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 0, result.stderr
    parts = set(result.stdout.split()) - {"scipy.__config__", "scipy._cyutility", "scipy._distributor_init", "scipy.version"}
    assert parts <= {"scipy.fft", "scipy.special", "scipy._lib"}, parts
