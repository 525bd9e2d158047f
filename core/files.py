"""Files riray reads and writes. Input: :func:`open_regular` / :func:`read_regular` read only
regular files, bounded (a FIFO or a device is refused, never waited on or read without end).
Output: every file riray writes (PNG, .npy, .npz, JSON, .rit) goes through :func:`atomic_write`.

The data goes to a temporary file in the target's folder, named
``TARGET.<pid>-<host>.<random>.tmp`` (pid of the writer, 8 hex digits of its host name's
hash), which is flushed, fsynced and renamed onto the target with os.replace; the folder is
then fsynced. Readers see the old file or the new one, never a part. On any error or interrupt
before the rename the temporary file is removed and the target is untouched; an OSError is
raised as :class:`WriteError`, whose message names the target and the OS's cause. A Ctrl-C
(SIGINT) in the main thread is held back during the rename, so it happens whole or not at
all, and a temporary file is never removed after it was renamed.

A writer killed outright (SIGKILL, power loss) leaves its temporary file behind. The next write
to the same target removes those of the target's own temporary files whose writer is gone: a
process of this host that no longer exists, or any writer whose file has not changed for
STALE_TMP_S seconds (writers on other hosts sharing the folder cannot be checked otherwise). A
concurrent writer of the same target is left alone; the last rename wins.
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import re
import signal
import socket
import stat
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from typing import BinaryIO

STALE_TMP_S = 3600.0   # seconds without a change after which any writer's temporary file
                       # counts as abandoned (a live writer writes without pause)


class WriteError(OSError):
    """An output file could not be written: ``cannot write PATH: CAUSE`` (``errno`` is the
    OS's)."""


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def temp_pattern(path: str | os.PathLike) -> re.Pattern:
    """The names of ``path``'s temporary files (groups: writer pid, host tag)."""
    name = os.path.basename(os.fspath(path))
    return re.compile(re.escape(name) + r"\.(\d+)-([0-9a-f]{8})\.[0-9a-f]{12}\.tmp")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:                       # another user's process (EPERM): it exists
        return True
    return True


def remove_stale_temps(path: str | os.PathLike) -> list[str]:
    """Remove the abandoned temporary files of ``path`` (see the module's doc); returns their
    paths. Files it cannot inspect or remove are left."""
    path = os.path.abspath(os.fspath(path))
    folder, pattern, host = os.path.dirname(path), temp_pattern(path), _host_tag()
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = pattern.fullmatch(name)
        if m is None:
            continue
        tmp = os.path.join(folder, name)
        try:
            idle = time.time() - os.stat(tmp).st_mtime
            pid = int(m.group(1))
            gone = m.group(2) == host and pid != os.getpid() and not _pid_alive(pid)
            if gone or idle > STALE_TMP_S:
                os.unlink(tmp)
                removed.append(tmp)
        except OSError:
            pass
    return removed


class _Out(io.BufferedIOBase):
    """The temporary file as ``write`` sees it (write, tell, seek, flush). It is not a real file
    object, so numpy writes arrays through ``write`` (an OSError then carries its errno instead
    of numpy's "N requested and M written"). Once the write is over, it only counts: a ZipFile
    left behind by a failed numpy.savez closes into the void from its destructor, not onto the
    terminal."""

    def __init__(self, f: BinaryIO):
        super().__init__()
        self._f: BinaryIO | None = f
        self._pos = self._end = 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def write(self, data) -> int:
        n = memoryview(data).nbytes
        if self._f is not None:
            self._f.write(data)
        self._pos += n
        self._end = max(self._end, self._pos)
        return n

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = 0) -> int:
        self._pos = offset + (0, self._pos, self._end)[whence]
        if self._f is not None:
            self._f.seek(self._pos)
        return self._pos

    def flush(self) -> None:
        if self._f is not None:
            self._f.flush()

    def close(self) -> None:
        """Detach (the real file is the helper's to close)."""
        self._f = None


def _open_temp(tmp: str) -> BinaryIO:
    """The new temporary file ``tmp``, opened for writing (never an existing one)."""
    return open(tmp, "xb")


_COMMAND = threading.local()      # .pending: [(temporary file, target)] inside command_output


@contextmanager
def command_output():
    """The files a command writes, as one. Inside the block every atomic_write writes and
    fsyncs its temporary file only; when the block ends without error they are all renamed
    into place, and from the first rename on SIGINT is ignored for the rest of the process, so
    the command's report is printed whole. On an error or a Ctrl-C before that, every
    temporary file is removed and no target changes. Not nested."""
    pending = _COMMAND.pending = []
    try:
        yield
        _COMMAND.pending = None
        _commit(pending, final=True)
    finally:
        _COMMAND.pending = None
        _discard(pending)


def _discard(pending: list) -> None:
    for tmp, _ in pending:
        _unlink(tmp)


def _commit(pending: list, final: bool = False) -> None:
    """Rename each (temporary file, target) of ``pending`` onto its target, taking it off the
    list once renamed, so a caller removes only temporary files that were not. SIGINT is held
    back meanwhile (main thread only: KeyboardInterrupt is raised only there) and delivered
    after; ``final``: ignored from now on instead."""
    main = threading.current_thread() is threading.main_thread()
    got = []
    if main:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN if final
                            else lambda signum, frame: got.append(signum))
    try:
        folders = {os.path.dirname(os.path.abspath(p)) for _, p in pending}
        while pending:
            tmp, path = pending[0]
            try:
                os.replace(tmp, path)
            except OSError as e:
                raise _error(path, e) from None
            pending.pop(0)
        for folder in folders:
            _sync_folder(folder)
    finally:
        if main and not final:
            signal.signal(signal.SIGINT, old if old is not None else signal.SIG_DFL)
            if got:
                signal.raise_signal(signal.SIGINT)


def _error(path: str, e: OSError) -> WriteError:
    """``cannot write PATH: CAUSE`` (the errno's text where there is one)."""
    cause = os.strerror(e.errno) if e.errno in errno.errorcode else (str(e) or type(e).__name__)
    err = WriteError(f"cannot write {path}: {cause}")
    err.errno = e.errno
    return err


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Call ``write(f)`` on a new temporary file beside ``path``, then flush, fsync and rename
    it onto ``path`` (inside :func:`command_output`: at the end of that block). WriteError
    naming ``path`` and the OS's cause on an OSError (disk full, no permission, a missing
    folder); any other error or interrupt is raised as it is. Either way ``path`` is left as it
    was and the temporary file removed."""
    path = os.fspath(path)
    remove_stale_temps(path)
    tmp = f"{path}.{os.getpid()}-{_host_tag()}.{os.urandom(6).hex()}.tmp"
    try:
        f = _open_temp(tmp)
    except OSError as e:
        raise _error(path, e) from None
    out = _Out(f)
    try:
        write(out)
        f.flush()
        os.fsync(f.fileno())
        out.close()
        f.close()
    except BaseException as e:
        out.close()
        try:
            f.close()                     # flushes what is buffered; closes the file anyway
        except OSError:
            pass
        _unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise _error(path, e) from None
        raise
    pending = getattr(_COMMAND, "pending", None)
    if pending is not None:
        pending.append((tmp, path))
        return
    pending = [(tmp, path)]
    try:
        _commit(pending)
    finally:
        _discard(pending)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` as UTF-8, atomically (:func:`atomic_write`)."""
    data = text.encode("utf-8")
    atomic_write(path, lambda f: f.write(data))


def _unlink(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def _sync_folder(folder: str) -> None:
    """fsync ``folder`` so the renames into it are durable (POSIX; a file system that cannot
    sync a folder is left as it is: the files are in place either way)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def open_regular(path: str | os.PathLike, max_bytes: int | None = None) -> BinaryIO:
    """``path`` opened for binary reading; ValueError naming it unless it is a regular file (of
    at most ``max_bytes`` bytes, when given). Opened non-blocking, so a FIFO is refused rather
    than waited on."""
    nonblock = getattr(os, "O_NONBLOCK", 0)
    fd = os.open(path, os.O_RDONLY | nonblock | getattr(os, "O_BINARY", 0))
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{os.fspath(path)}: not a regular file")
        if max_bytes is not None and info.st_size > max_bytes:
            raise ValueError(f"{os.fspath(path)}: {info.st_size} bytes, more than the "
                             f"{max_bytes} read")
        if nonblock:
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: str | os.PathLike, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path`` (see :func:`open_regular`), read bounded."""
    with open_regular(path, max_bytes) as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise ValueError(f"{os.fspath(path)}: more than {max_bytes} bytes")
    return data
