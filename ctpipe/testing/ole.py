"""OLE compound files ([MS-CFB], version 3) written from a mapping of stream paths to bytes, for test scans.

:func:`write_compound_file` writes a tree of storages and streams the way [MS-CFB] lays them
out: 512-byte sectors chained by a FAT (with DIFAT sectors beyond 109 FAT sectors), a
directory whose siblings form a balanced red-black search tree, and streams shorter than
4096 bytes packed in 64-byte mini sectors of the mini stream (chained by the mini FAT), the
others in regular sectors. ``olefile`` reads such files back byte for byte; it cannot write.
:func:`ctpipe.testing.write_zeiss` writes its ``.txrm`` files with it; the reading side is
:mod:`ctpipe.io._ole`.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ctpipe.io._ole import _ENDOFCHAIN, MINI_STREAM_CUTOFF, SECTOR, _sectors

__all__ = ["write_compound_file"]

MINI_SECTOR = 64
_IDS_PER_SECTOR = SECTOR // 4
_HEADER_DIFAT = 109
_FREESECT, _FATSECT, _DIFSECT, _NOSTREAM = 0xFFFFFFFF, 0xFFFFFFFD, 0xFFFFFFFC, 0xFFFFFFFF
_MAX_SECTOR = 0xFFFFFFFA
_STORAGE, _STREAM, _ROOT = 1, 2, 5
_RED, _BLACK = 0, 1
_SIGNATURE = bytes.fromhex("D0CF11E0A1B11AE1")
_FORBIDDEN = set("/\\:!")


@dataclass
class _Entry:
    name: str
    kind: int
    data: memoryview | None = None
    children: dict[str, _Entry] = field(default_factory=dict)
    sid: int = 0
    left: int = _NOSTREAM
    right: int = _NOSTREAM
    child: int = _NOSTREAM
    color: int = _BLACK
    start: int = _ENDOFCHAIN
    size: int = 0


def _tree(streams: Mapping[str, object]) -> _Entry:
    root = _Entry("Root Entry", _ROOT)
    for path, data in streams.items():
        parts = path.split("/")
        for part in parts:
            if not 0 < len(part) <= 31 or _FORBIDDEN & set(part):
                raise ValueError(f"{path}: each name must have 1 to 31 characters and none of / \\ : !, got {part!r}")
        node = root
        for part in parts[:-1]:
            key = part.upper()
            child = node.children.setdefault(key, _Entry(part, _STORAGE))
            if child.kind != _STORAGE:
                raise ValueError(f"{path}: {part!r} is a stream, so it cannot hold {parts[-1]!r}")
            node = child
        key = parts[-1].upper()
        if key in node.children:
            raise ValueError(f"{path}: given twice (names are case-insensitive), or also used as a storage")
        view = memoryview(data).cast("B")
        if view.nbytes > 0xFFFFFFFF:
            raise ValueError(f"{path}: {view.nbytes} bytes; a version 3 compound file holds streams below 4 GiB")
        node.children[key] = _Entry(parts[-1], _STREAM, view, size=view.nbytes)
    return root


def _number(root: _Entry) -> list[_Entry]:
    """Directory order: root first, then depth first; siblings linked as a balanced search tree."""
    entries = [root]

    def visit(node: _Entry) -> None:
        kids = sorted(node.children.values(), key=lambda e: (len(e.name.encode("utf-16-le")), e.name.upper()))
        for kid in kids:
            kid.sid = len(entries)
            entries.append(kid)
        node.child = _link(kids, 0, _height(len(kids)))
        for kid in kids:
            visit(kid)

    visit(root)
    return entries


def _height(n: int) -> int:
    return int(n).bit_length()


def _link(kids: list[_Entry], depth: int, height: int) -> int:
    # A size-balanced tree has every empty child at depth height - 1 or height, so colouring the
    # deepest nodes red (their parents are black) gives every path the same number of black nodes.
    if not kids:
        return _NOSTREAM
    mid = len(kids) // 2
    node = kids[mid]
    node.color = _RED if height > 1 and depth == height - 1 else _BLACK
    node.left = _link(kids[:mid], depth + 1, height)
    node.right = _link(kids[mid + 1:], depth + 1, height)
    return node.sid


def write_compound_file(handle: io.BufferedIOBase, streams: Mapping[str, object]) -> None:
    """Write an OLE compound file holding ``streams`` to the binary ``handle``.

    Parameters
    ----------
    handle : binary file object, open for writing
    streams : mapping of path -> bytes-like
        Paths use ``/`` between storage names (``"ImageInfo/ImageWidth"``); storages are made
        for every prefix. Values are anything :class:`memoryview` takes (``bytes``, a
        C-contiguous array), written as they are.
    """
    root = _tree(streams)
    entries = _number(root)
    files = [e for e in entries if e.kind == _STREAM and e.size]
    small = [e for e in files if e.size < MINI_STREAM_CUTOFF]
    large = [e for e in files if e.size >= MINI_STREAM_CUTOFF]

    mini_chain: list[int] = []
    for e in small:
        e.start = len(mini_chain)
        n = _sectors(e.size, MINI_SECTOR)
        mini_chain.extend(range(e.start + 1, e.start + n))
        mini_chain.append(_ENDOFCHAIN)
    mini_bytes = len(mini_chain) * MINI_SECTOR

    # Sector budget (everything but the FAT and DIFAT), in file order after them.
    blocks = [("directory", _sectors(len(entries) * 128)), ("minifat", _sectors(len(mini_chain) * 4)),
              ("ministream", _sectors(mini_bytes))] + [(e, _sectors(e.size)) for e in large]
    payload = sum(n for _, n in blocks)
    n_fat = max(1, _sectors(payload, _IDS_PER_SECTOR))
    while True:
        n_difat = max(0, _sectors(n_fat - _HEADER_DIFAT, _IDS_PER_SECTOR - 1))
        if n_fat * _IDS_PER_SECTOR >= payload + n_fat + n_difat:
            break
        n_fat += 1
    total = n_fat + n_difat + payload
    if total > _MAX_SECTOR:
        raise ValueError(f"{total} sectors of {SECTOR} bytes: too large for a version 3 compound file")

    fat = np.full(n_fat * _IDS_PER_SECTOR, _FREESECT, np.uint32)
    fat[:n_fat] = _FATSECT
    fat[n_fat:n_fat + n_difat] = _DIFSECT
    starts = {}
    sector = n_fat + n_difat
    for key, n in blocks:
        if n:
            fat[sector:sector + n - 1] = np.arange(sector + 1, sector + n, dtype=np.uint32)
            fat[sector + n - 1] = _ENDOFCHAIN
            starts[id(key) if isinstance(key, _Entry) else key] = sector
        sector += n
    for e in large:
        e.start = starts[id(e)]
    root.start = starts.get("ministream", _ENDOFCHAIN)
    root.size = mini_bytes

    header = bytearray(SECTOR)
    header[0:8] = _SIGNATURE
    struct.pack_into("<HHHHH", header, 24, 0x003E, 3, 0xFFFE, 9, 6)
    struct.pack_into("<IIIIIIIII", header, 40, 0, n_fat, starts["directory"], 0, MINI_STREAM_CUTOFF,
                     starts.get("minifat", _ENDOFCHAIN), _sectors(len(mini_chain) * 4),
                     n_fat if n_difat else _ENDOFCHAIN, n_difat)
    difat = np.full(_HEADER_DIFAT + n_difat * (_IDS_PER_SECTOR - 1), _FREESECT, np.uint32)
    difat[:n_fat] = np.arange(n_fat, dtype=np.uint32)
    header[76:SECTOR] = difat[:_HEADER_DIFAT].astype("<u4").tobytes()
    handle.write(header)
    handle.write(fat.astype("<u4").tobytes())
    for k in range(n_difat):
        block = np.empty(_IDS_PER_SECTOR, np.uint32)
        block[:-1] = difat[_HEADER_DIFAT + k * (_IDS_PER_SECTOR - 1):_HEADER_DIFAT + (k + 1) * (_IDS_PER_SECTOR - 1)]
        block[-1] = n_fat + k + 1 if k + 1 < n_difat else _ENDOFCHAIN
        handle.write(block.astype("<u4").tobytes())

    directory = bytearray(_sectors(len(entries) * 128) * SECTOR)
    for e in entries:
        _pack_entry(directory, e)
    for sid in range(len(entries), len(directory) // 128):
        struct.pack_into("<III", directory, sid * 128 + 68, _NOSTREAM, _NOSTREAM, _NOSTREAM)
    handle.write(directory)
    _write_padded(handle, np.array(mini_chain, np.uint32).astype("<u4").tobytes())
    for e in small:
        handle.write(e.data)
        handle.write(bytes(_sectors(e.size, MINI_SECTOR) * MINI_SECTOR - e.size))
    handle.write(bytes(_sectors(mini_bytes) * SECTOR - mini_bytes))
    for e in large:
        _write_padded(handle, e.data)


def _write_padded(handle: io.BufferedIOBase, data) -> None:
    handle.write(data)
    nbytes = memoryview(data).nbytes
    handle.write(bytes(_sectors(nbytes) * SECTOR - nbytes))


def _pack_entry(buffer: bytearray, e: _Entry) -> None:
    name = e.name.encode("utf-16-le")
    offset = e.sid * 128
    buffer[offset:offset + len(name)] = name
    struct.pack_into("<HBBIII", buffer, offset + 64, len(name) + 2, e.kind, e.color, e.left, e.right, e.child)
    struct.pack_into("<IQ", buffer, offset + 116, e.start if e.kind != _STORAGE else 0, e.size)
