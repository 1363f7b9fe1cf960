"""OLE compound files ([MS-CFB], version 3): lazy reads of one stream.

:class:`StreamReader` keeps the allocation tables ``olefile`` parsed and reads one stream
later with a file handle of its own, so that views are read on demand, from several threads,
without keeping the file open or re-parsing its tables; :func:`find_entry` finds a stream's
directory entry by its ``/``-separated path. ``olefile`` parses the files; it cannot write
them. Compound files for tests (Zeiss ``.txrm`` scans) are written by
:func:`ctpipe.testing.write_compound_file`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["StreamReader", "find_entry", "MINI_STREAM_CUTOFF"]

SECTOR = 512
#: Streams shorter than this live in the mini stream.
MINI_STREAM_CUTOFF = 4096
_ENDOFCHAIN = 0xFFFFFFFE


def _sectors(nbytes: int, size: int = SECTOR) -> int:
    return -(-nbytes // size)


def find_entry(ole, path: str):
    """The ``olefile`` directory entry of ``path`` (case-insensitive, ``/``-separated), or None."""
    node = ole.root
    for part in path.split("/"):
        node = getattr(node, "kids_dict", {}).get(part.lower())
        if node is None:
            return None
    return node


class StreamReader:
    """Reads whole streams of a compound file on demand, from the tables ``olefile`` parsed.

    Each :meth:`read` opens the file itself, so calls from several threads do not share a
    file position, and nothing stays open between reads.

    Parameters
    ----------
    ole : olefile.OleFileIO
        Open on ``path``; only read here (its FAT, mini FAT and root entry are copied).
    path : str or Path
    """

    def __init__(self, ole, path) -> None:
        self.path = path
        self.sector_size = int(ole.sectorsize)
        self.mini_size = int(ole.minisectorsize)
        self.cutoff = int(ole.minisectorcutoff)
        self.fat = np.array(ole.fat, np.uint32)
        self._mini_offsets = None
        self._minifat = None
        if ole.root.size:
            if ole.minifat is None:
                ole.loadminifat()
            self._minifat = np.array(ole.minifat, np.uint32)
            count = _sectors(int(ole.root.size), self.sector_size)
            root_sectors = self._chain(self.fat, int(ole.root.isectStart), count, "the mini stream")
            self._mini_offsets = (root_sectors.astype(np.int64) + 1) * self.sector_size

    def read(self, start: int, size: int, name: str) -> bytes:
        """The ``size`` bytes of the stream whose first (mini) sector is ``start`` (named ``name`` in errors)."""
        if size == 0:
            return b""
        with open(self.path, "rb") as handle:
            if size >= self.cutoff:
                sectors = self._chain(self.fat, start, _sectors(size, self.sector_size), name)
                offsets = (sectors.astype(np.int64) + 1) * self.sector_size
                return self._gather(handle, offsets, self.sector_size, size, name)
            if self._mini_offsets is None:
                raise OSError(f"{name}: is in the mini stream, but the file has none")
            minis = self._chain(self._minifat, start, _sectors(size, self.mini_size), name)
            per = self.sector_size // self.mini_size
            index = minis.astype(np.int64) // per
            if index.size and index.max() >= len(self._mini_offsets):
                raise OSError(f"{name}: mini sector beyond the end of the mini stream")
            offsets = self._mini_offsets[index] + (minis.astype(np.int64) % per) * self.mini_size
            return self._gather(handle, offsets, self.mini_size, size, name)

    def _chain(self, table: np.ndarray, start: int, count: int, name: str) -> np.ndarray:
        if count == 0:
            return np.empty(0, np.uint32)
        if start >= len(table):
            raise OSError(f"{name}: first sector {start} is outside the allocation table")
        if start + count <= len(table):
            # Streams written in one go occupy consecutive sectors: check that in one step.
            run = table[start:start + count]
            following = np.arange(start + 1, start + count, dtype=np.uint32)
            if np.array_equal(run[:-1], following) and run[-1] == _ENDOFCHAIN:
                return np.arange(start, start + count, dtype=np.uint32)
        chain = np.empty(count, np.uint32)
        sector = start
        for i in range(count):
            if sector >= len(table):
                raise OSError(f"{name}: sector chain leaves the allocation table after {i} of {count} sectors")
            chain[i] = sector
            sector = int(table[sector])
        if sector != _ENDOFCHAIN:
            raise OSError(f"{name}: sector chain does not end after {count} sectors, as the stream size says")
        return chain

    @staticmethod
    def _gather(handle, offsets: np.ndarray, unit: int, size: int, name: str) -> bytes:
        out = bytearray(len(offsets) * unit)
        # Merge consecutive units into one read each.
        breaks = np.flatnonzero(np.diff(offsets) != unit) + 1
        first = 0
        for last in list(breaks) + [len(offsets)]:
            handle.seek(int(offsets[first]))
            want = (last - first) * unit
            got = handle.readinto(memoryview(out)[first * unit:first * unit + want])
            if got != want and (last != len(offsets) or first * unit + got < size):
                raise OSError(f"{name}: the file ends inside the stream")
            first = last
        return bytes(out[:size])
