"""One writer at a time per output folder: an advisory lock on ``<folder>/.stillbox.lock``.

A run that writes into a dataset (``generate``, ``merge``, ``index``) or a benchmark run folder
holds a POSIX record lock (``fcntl``) on the file stillbox_gen.layout.LOCK_FILE inside that folder
while it writes. A second run on the same folder is refused at once with a ConfigError naming the
folder and the process that holds it. The kernel drops the lock when its process ends, however it
ends (``kill -9`` included): a lock file left by a killed run blocks nothing, and the next run
takes it over. A run that ends deletes the lock file when no other run holds it (and only while
it is empty: the lock writes nothing into it, so a user's file of that name is never deleted), so
a finished folder holds no lock file; ``validate`` accepts one left by a killed run. On a file
system without record locks the run goes on unlocked, with a warning.

Shards (``generate --shard I/N``) render disjoint scenes into one folder at the same time: each
holds a shared lock on byte 0 of the file and an exclusive lock on a byte of its own
(:func:`_shard_byte`), so two runs of the same shard, or a shard beside an unsharded run (which
locks the whole file exclusively), are refused, while the shards of one split run together.
Each shard also holds a shared lock on a byte of its split N (:func:`_split_byte`, far above the
shard bytes) and, once locked, looks for a lock on any other split's byte: shards of two
different splits (``0/2`` beside ``0/4``, whose scenes overlap) are refused. Two of them starting
at the same instant may both be refused, never both admitted.

POSIX locks belong to a process: a second lock of the same folder from the same process would
succeed, and closing any descriptor of the file would drop it. :func:`folder_lock` therefore
keeps one lock per folder and process; nested uses of the same folder are no-ops.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path

from .errors import ConfigError
from .layout import LOCK_FILE

# struct flock of fcntl(F_GETLK) on Linux (x86-64 and arm64): type, whence, start, len, pid
_FLOCK = "hhqqi4x"
_BUSY = (errno.EAGAIN, errno.EACCES)  # what a refused non-blocking lock raises
_UNSUPPORTED = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS)  # a file system without locks
_HELD: dict[str, int] = {}  # folder (real path) -> nesting depth in this process


class FolderInUse(ConfigError):
    """Another process holds the lock of the folder (message names the folder and the process)."""


def _shard_byte(shard: tuple[int, int]) -> int:
    """Offset of the byte shard (I, N) locks exclusively: one distinct byte per (I, N), N >= 2."""
    i, n = shard
    return 1 + n * (n - 1) // 2 + i


#: the largest N of ``--shard I/N``: its shard bytes (about N^2 / 2) stay below _SPLIT_BASE
MAX_SHARDS = 1_000_000
#: first byte of the split bytes: above every shard byte of any split up to MAX_SHARDS
_SPLIT_BASE = 1 << 40


def _split_byte(n: int) -> int:
    """Offset of the byte every shard of a split into ``n`` locks shared."""
    return _SPLIT_BASE + n


def _ranges(shard: tuple[int, int]) -> list[tuple[int, int, bool]]:
    """(start, length, exclusive) locks of a run; length 0 = to the end of any file."""
    if shard[1] <= 1:
        return [(0, 0, True)]
    return [(0, 1, False), (_shard_byte(shard), 1, True), (_split_byte(shard[1]), 1, False)]


def _other_split(fd: int, n: int) -> int | None:
    """PID of a process holding the byte of a split other than ``n`` (None when none does);
    locks of this process are not reported (F_GETLK)."""
    below = (_SPLIT_BASE, n)  # the split bytes of 0..n-1
    above = (_split_byte(n) + 1, 0)  # those of n+1 and up, to the end of any file
    for start, length in (below, above):
        if pid := _holder(fd, start, length, exclusive=True):
            return pid
    return None


def _holder(fd: int, start: int, length: int, exclusive: bool) -> int | None:
    """PID of a process whose lock conflicts with the one wanted (None when unknown)."""
    want = fcntl.F_WRLCK if exclusive else fcntl.F_RDLCK
    query = struct.pack(_FLOCK, want, os.SEEK_SET, start, length, 0)
    try:
        kind, _, _, _, pid = struct.unpack(_FLOCK, fcntl.fcntl(fd, fcntl.F_GETLK, query))
    except (OSError, struct.error):
        return None
    return pid if kind != fcntl.F_UNLCK and pid > 0 else None


def _same_file(fd: int, path: Path) -> bool:
    """True when ``path`` still names the file open as ``fd`` (not deleted or replaced)."""
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _acquire(path: Path, what: str, folder: Path, shard: tuple[int, int]) -> int:
    """Open and lock ``path`` without waiting; FolderInUse when another process holds it."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise ConfigError(f"{what}: cannot write into '{folder}' ({e.strerror})") from None
        try:
            for start, length, exclusive in _ranges(shard):
                mode = (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB
                try:
                    fcntl.lockf(fd, mode, length, start)
                except OSError as e:
                    if e.errno in _UNSUPPORTED:
                        return _unlocked(fd, what, folder, e)
                    if e.errno not in _BUSY:
                        raise
                    pid = _holder(fd, start, length, exclusive)
                    by = f"process {pid}" if pid else "another process"
                    raise FolderInUse(
                        f"{what}: '{folder}' is in use by another run ({by} holds "
                        f"'{path}'); wait for it to end, or use another folder"
                    ) from None
            if shard[1] > 1 and (pid := _other_split(fd, shard[1])):
                raise FolderInUse(
                    f"{what}: '{folder}' is in use by a shard of another split (process {pid} "
                    f"holds '{path}'; this run is a shard of {shard[1]}); give every shard the "
                    "same N, or use another folder"
                )
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, path):  # not deleted by a run that ended meanwhile
            return fd
        os.close(fd)


def _unlocked(fd: int, what: str, folder: Path, e: OSError) -> int:
    """A folder whose file system has no record locks (some cluster file systems): warn, go on
    without the lock (returns ``fd`` as if locked; closing it later is harmless)."""
    warnings.warn(
        f"{what}: '{folder}' cannot be locked ({e.strerror}); a second run into it would not be "
        "refused",
        stacklevel=4,
    )
    return fd


def _release(fd: int, path: Path) -> None:
    """Delete the lock file when no other process holds a lock on it, then drop ours."""
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, 0, 0)  # no one else: safe to delete
        if _same_file(fd, path) and os.fstat(fd).st_size == 0:
            path.unlink()
    except OSError:
        pass  # another shard still holds it: it deletes the file when it ends
    finally:
        os.close(fd)


@contextlib.contextmanager
def folder_lock(folder: Path, what: str, shard: tuple[int, int] = (0, 1)) -> Iterator[None]:
    """Hold the lock of ``folder`` (created when missing with its missing parents, which are
    removed again at the end if they are then empty) for the block; ``what`` names it in
    messages (e.g. "--out"); ``shard`` is the (I, N) of ``generate --shard`` ((0, 1): the whole
    folder).

    Raises FolderInUse (a ConfigError) when another process holds it, ConfigError when the folder
    cannot be created or written. Nothing is written into the folder but the lock file.
    """
    folder = Path(folder)
    key = os.path.realpath(folder)
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    # the folders this lock makes, deepest first: removed again at the end while they are empty
    created = [p for p in (folder, *folder.absolute().parents) if not p.exists()]
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{what}: '{folder}' exists and is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{what}: cannot create '{folder}' ({e.strerror})") from None
    path = folder / LOCK_FILE
    try:
        fd = _acquire(path, what, folder, shard)
    except BaseException:
        _remove_empty(created)
        raise
    _HELD[key] = 1
    try:
        yield
    finally:
        del _HELD[key]
        _release(fd, path)
        _remove_empty(created)  # only when empty: a run refused before writing anything


def _remove_empty(folders: list[Path]) -> None:
    """Remove ``folders`` (deepest first) while each is empty; stop at the first that is not."""
    for f in folders:
        try:
            f.rmdir()
        except OSError:
            return
