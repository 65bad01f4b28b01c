"""An append-only scratch file that holds the host store's payload (tisem/store.py) off the heap.

One unnamed temporary file (`tempfile.TemporaryFile`: unlinked as it is created, so nothing is
left behind, not even after a crash). `append` writes a group of arrays back to back and returns
a `Record`; `read` reads them back into fresh numpy arrays with seek + readinto. No mmap: mapped
pages a process touches count in its resident memory, which is what the store must keep flat,
while the page cache behind plain reads is the kernel's to drop.

Records whose data is no longer needed are `release`d; their bytes become garbage. Once garbage
is both more than half the file and more than `rewrite_floor` bytes, the next `append` first
copies the live records into a new file and swaps it in, so the file stays within about twice
what is stored (or stored + floor) however long the drive.

Every write either completes or leaves all existing records as they were and raises a
`SpillError` (an OSError with the errno of the failed call) that names the spill directory (a
full disk, typically), so the caller can keep its own state unchanged too.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

_ALIGN = 8  # each array starts 8-byte aligned, so the views `read` returns are aligned
_COPY_CHUNK = 8 << 20


class SpillError(OSError):
    """The host store's spill file could not be created, written or read (a full disk, a
    missing or read-only store_dir): one line naming the folder and the cause."""


def _padded(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


class Record:
    """Where one group of arrays lies in the file. The file moves it when it rewrites itself,
    so holders keep the object, never its offset."""

    __slots__ = ("offset", "nbytes")

    def __init__(self, offset: int, nbytes: int):
        self.offset, self.nbytes = offset, nbytes


class SpillFile:
    def __init__(self, directory: str | os.PathLike | None = None, rewrite_floor: int = 64 << 20):
        self.dir = os.fspath(directory) if directory is not None else tempfile.gettempdir()
        if not os.path.isdir(self.dir):
            raise ValueError(
                f"store_dir {self.dir!r} is not an existing directory (the host "
                f"store spills its voxels to a temporary file there)"
            )
        self.rewrite_floor = int(rewrite_floor)
        self._file = self._new_file()
        self._size = 0  # bytes of the file in use, live records and garbage
        self._live: set[Record] = set()
        self.live_bytes = 0
        self.rewrites = 0

    @property
    def file_bytes(self) -> int:
        return self._size

    def _error(self, action: str, e: OSError) -> SpillError:
        return SpillError(
            e.errno,
            f"host store: could not {action} its spill file in "
            f"{self.dir} ({e.strerror or e}); set store_dir to a folder "
            f"with free space",
        )

    def _new_file(self):
        try:
            return tempfile.TemporaryFile(dir=self.dir, buffering=0)
        except OSError as e:
            raise self._error("create", e) from e

    # ------------------------------------------------------------------ raw io
    @staticmethod
    def _write_at(f, offset: int, chunks) -> None:
        f.seek(offset)
        for chunk in chunks:
            view = memoryview(chunk).cast("B")
            while len(view):
                view = view[f.write(view) :]  # unbuffered writes may be short

    @staticmethod
    def _read_into(f, offset: int, buf: memoryview) -> None:
        f.seek(offset)
        while len(buf):
            n = f.readinto(buf)
            if not n:
                raise OSError(0, "unexpected end of file")
            buf = buf[n:]

    # ------------------------------------------------------------------ records
    def append(self, arrays) -> Record:
        """Write the arrays (C-contiguous copies are made where needed) as one record."""
        chunks, nbytes = [], 0
        for a in arrays:
            a = np.ascontiguousarray(a)
            chunks.append(a)
            pad = _padded(a.nbytes) - a.nbytes
            if pad:
                chunks.append(bytes(pad))
            nbytes += a.nbytes + pad
        try:
            garbage = self._size - self.live_bytes
            if garbage > self.rewrite_floor and 2 * garbage > self._size:
                self._rewrite()
            self._write_at(self._file, self._size, chunks)
        except SpillError:
            raise
        except OSError as e:
            try:  # give the disk back; the bytes past _size are never read either way
                self._file.truncate(self._size)
            except OSError:
                pass
            raise self._error("write", e) from e
        rec = Record(self._size, nbytes)
        self._size += nbytes
        self._live.add(rec)
        self.live_bytes += nbytes
        return rec

    def read(self, rec: Record, layout) -> list[np.ndarray]:
        """The arrays of a record, given their [(dtype, shape)] as appended."""
        buf = np.empty(rec.nbytes, np.uint8)
        try:
            self._read_into(self._file, rec.offset, memoryview(buf))
        except OSError as e:
            raise self._error("read", e) from e
        out, pos = [], 0
        for dtype, shape in layout:
            n = int(np.prod(shape)) * np.dtype(dtype).itemsize
            out.append(buf[pos : pos + n].view(dtype).reshape(shape))
            pos += _padded(n)
        if pos != rec.nbytes:
            raise AssertionError(f"spill record of {rec.nbytes} B read as {pos} B")
        return out

    def release(self, rec: Record) -> None:
        """The record's bytes are garbage from now on."""
        self._live.remove(rec)
        self.live_bytes -= rec.nbytes

    def _rewrite(self) -> None:
        """Copy the live records, in file order, into a new file and use that one. On failure
        the new file is dropped and every record stays where it was."""
        new = self._new_file()
        try:
            recs = sorted(self._live, key=lambda r: r.offset)
            buf = np.empty(min(_COPY_CHUNK, max((r.nbytes for r in recs), default=0)), np.uint8)
            pos = 0
            for r in recs:
                for start in range(0, r.nbytes, len(buf)):
                    n = min(len(buf), r.nbytes - start)
                    self._read_into(self._file, r.offset + start, memoryview(buf)[:n])
                    self._write_at(new, pos + start, [buf[:n]])
                pos += r.nbytes
        except BaseException:
            new.close()
            raise
        pos = 0
        for r in recs:
            r.offset, pos = pos, pos + r.nbytes
        self._file.close()
        self._file, self._size = new, pos
        self.rewrites += 1
