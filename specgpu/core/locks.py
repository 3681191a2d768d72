"""One writer per output: an exclusive lock on every output file or folder while a command writes it.

A lock on ``path`` is the file ``.<name>.lock`` beside it (``out.exr`` -> ``.out.exr.lock``; folder ``seq`` ->
``.seq.lock``), taken on the resolved path (a folder reached through a symbolic link is locked where it is, so two
writers meet at one lock whichever name they use), held with an advisory ``flock`` and holding the writer's pid.
The kernel drops an ``flock`` when its process dies, even by ``kill -9``, so a lock left by a killed process is
recognised (its file is there, nobody holds it) and taken over; a live holder makes a second writer fail at once
with one line naming the holder's pid.

Temporary files are named after the process that writes them (``.<name>.<pid>.<random>.tmp<suffix>``, see
:func:`specgpu.io.paths.atomic_path`); :func:`clean_stale_temporaries` removes those of processes no longer
alive, which is what a killed writer leaves behind.
"""

from __future__ import annotations

import errno
import os
import re
from contextlib import ExitStack, contextmanager
from pathlib import Path

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows: locks by exclusive creation and a pid check
    fcntl = None

__all__ = ["OutputLocked", "resolved", "lock_path", "output_lock", "output_locks", "pid_alive",
           "clean_stale_temporaries"]


class OutputLocked(RuntimeError):
    """Another live process is writing the output."""


def resolved(path) -> Path:
    """The file or folder ``path`` names once every symbolic link is followed (the path a lock is taken on: two
    writers of one folder, one through a link to it, must meet at one lock)."""
    return Path(os.path.realpath(path))


def lock_path(path) -> Path:
    """The lock file of an output file or folder (beside the file or folder a symbolic link points to)."""
    path = resolved(path)
    return path.parent / f".{path.name}.lock"


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists (on this machine)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    return True


def _holder(lock: Path) -> str:
    try:
        text = lock.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return "another process"
    return f"pid {text}" if text.isdigit() else "another process"


class _Lock:
    def __init__(self, path: Path):
        self.target = Path(path)
        self.path = lock_path(path)
        self.fd: int | None = None
        self.stale_pid: int | None = None  # pid of a killed writer whose lock was cleared

    def acquire(self, make_parents: bool = False) -> "_Lock":
        folder = self.path.parent
        if make_parents and not folder.exists():
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise type(exc)(f"{self.target}: cannot create folder {folder} ({exc.strerror})") from None
        if not folder.is_dir():
            raise FileNotFoundError(f"{self.target}: folder {folder} does not exist")
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except PermissionError:
                raise PermissionError(f"{self.target}: cannot write in {folder} (permission denied)") from None
            except OSError as exc:
                raise OSError(exc.errno, f"{self.target}: cannot create its lock {self.path.name} "
                                         f"({exc.strerror})") from None
            try:
                self._flock(fd)
            except BaseException:
                os.close(fd)
                raise
            # the file may have been removed by the holder that just released it: lock the one at the path
            try:
                if os.fstat(fd).st_ino != os.stat(self.path).st_ino:
                    os.close(fd)
                    continue
            except FileNotFoundError:
                os.close(fd)
                continue
            break
        previous = os.read(fd, 32).decode("ascii", "replace").strip()
        if previous.isdigit() and int(previous) != os.getpid():
            self.stale_pid = int(previous)  # its writer died holding it (kill -9, power cut): cleared
        os.lseek(fd, 0, os.SEEK_SET)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd = fd
        return self

    def _flock(self, fd: int) -> None:
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise OSError(exc.errno, f"{self.target}: cannot lock ({exc.strerror})") from None
                raise OutputLocked(f"{self.target} is being written by {_holder(self.path)} "
                                   f"(lock {self.path}); wait for it or choose another output") from None
        # no flock: a lock whose pid is alive is held
        text = os.read(fd, 32).decode("ascii", "replace").strip()
        os.lseek(fd, 0, os.SEEK_SET)
        if text.isdigit() and int(text) != os.getpid() and pid_alive(int(text)):
            raise OutputLocked(f"{self.target} is being written by pid {text} (lock {self.path}); wait for it "
                               "or choose another output")

    def release(self) -> None:
        if self.fd is None:
            return
        try:  # remove first, then unlock: a waiting writer re-checks that it locked the file at the path
            self.path.unlink(missing_ok=True)
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None


@contextmanager
def output_lock(path: str | os.PathLike[str], *, make_parents: bool = False):
    """Hold the exclusive lock of one output file or folder for the ``with`` block (``make_parents``: create its
    missing parent folders first, as for an output folder).

    Raises
    ------
    OutputLocked
        A live process holds it: one line naming its pid and the lock file.
    FileNotFoundError, PermissionError
        The output's folder does not exist or cannot be written (found before any work is done).
    """
    lock = _Lock(Path(path)).acquire(make_parents)
    try:
        clean_stale_temporaries(resolved(path))  # temporaries are named after the file a link points to
        yield lock
    finally:
        lock.release()


@contextmanager
def output_locks(paths, *, make_parents: bool = False):
    """:func:`output_lock` on several outputs at once (all or none); duplicates (one file named twice, or
    through a symbolic link) are locked once."""
    seen, unique = set(), []
    for p in paths:
        if p is None:
            continue
        key = resolved(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    with ExitStack() as stack:
        held = [stack.enter_context(output_lock(p, make_parents=make_parents)) for p in unique]
        yield held


_PID_IN_TEMP = re.compile(r"\.(\d+)\.[^.]+\.tmp")


def clean_stale_temporaries(path) -> list[Path]:
    """Remove the temporary files a dead writer left for ``path`` (and, for a folder, inside it); return them.

    Only files named by :func:`specgpu.io.paths.atomic_path` (``.<name>.<pid>.<random>.tmp<suffix>``, possibly
    nested: the temporary of a temporary) after pids no longer alive are removed; a live writer's are left alone.
    """
    path = Path(path)
    removed = []
    places = [(path.parent, path.name)]
    if path.is_dir():
        places.append((path, None))
    for folder, name in places:
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            if not entry.name.startswith(".") or ".tmp" not in entry.name:
                continue
            if name is not None and not entry.name.lstrip(".").startswith(f"{name}."):
                continue
            pids = [int(p) for p in _PID_IN_TEMP.findall(entry.name)]
            if not pids or any(pid_alive(pid) for pid in pids):
                continue
            try:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
            except OSError:
                pass
    return removed
