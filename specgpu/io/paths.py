"""Where a file is written: temporary names, atomic replacement, and one-line write errors.

Every write goes to a temporary name in the target's folder (``.<name>.<pid>.<random>.tmp<suffix>``) and is renamed
over the target with :func:`os.replace` at the end, so a crash never leaves a partial file under the final name;
:func:`final_name` and :func:`final_names` turn those temporary names back into the names a user gave in messages.
Every error is one line that starts with the file's path (:func:`write_failed`, :func:`os_error`, :func:`disk_full`).
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import stat
from contextlib import contextmanager
from pathlib import Path

from specgpu.core.text import one_line

__all__ = [
    "new_temporary", "replace_with", "write_target", "atomic_path", "final_name", "final_names", "write_failed",
    "disk_full", "os_error", "error_of"
]

_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp(?P<suffix>\.[^.]*)?$")
_TEMP_IN_TEXT = re.compile(r"\.[^\s\"'()/\\]*?\.\d+\.[A-Za-z0-9_]+\.tmp[^\s\"'()/\\]*")


def final_name(name: str) -> str:
    """The file a temporary name (``.<name>.<pid>.<random>.tmp<suffix>``, possibly nested: the temporary of a
    temporary) stands for; any other name unchanged. A temporary whose suffix differs from its name's is a
    companion's (an ENVI header's temporary renamed to ``.img`` for its data file): it stands for that file."""
    while True:
        m = _TEMP_NAME.match(name)
        if m is None:
            return name
        name, suffix = m.group("name"), m.group("suffix") or ""
        if suffix and Path(name).suffix != suffix:
            name = str(Path(name).with_suffix(suffix)) if Path(name).suffix else name + suffix


def final_names(text: str) -> str:
    """``text`` (an error message) with every temporary file name replaced by the name of the file it stands for:
    a message names the output the user asked for, never the temporary written on its way."""
    return _TEMP_IN_TEXT.sub(lambda m: final_name(m.group(0)), str(text))


def new_temporary(path) -> Path:
    """Create an empty temporary file beside ``path`` (``.<name>.<pid>.<random>.tmp<suffix>``) and return it.

    It is created with ``0o666`` less the process's umask (and the folder's default ACL), as the kernel applies
    them to a plain ``open(path, "w")`` (:func:`tempfile.mkstemp` would make every output ``0o600``, unreadable to
    the user's group); :func:`replace_with` gives it the mode of the file it replaces, when there is one.
    """
    path = Path(path)
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(errno.EEXIST, f"{path}: no free temporary name beside it")


def replace_with(tmp, path) -> None:
    """Rename the finished temporary ``tmp`` over ``path`` atomically; a file already at ``path`` keeps its
    permission bits, as a plain ``open()`` that truncates it would keep them (applied now, once the temporary
    is written, so a read-only file can still be replaced as before)."""
    try:
        existing = os.stat(path)
        if stat.S_ISREG(existing.st_mode):
            os.chmod(tmp, stat.S_IMODE(existing.st_mode))
    except OSError:  # no file there yet (or not ours to stat): the creation mode stands
        pass
    os.replace(tmp, path)


def write_target(path) -> Path:
    """The file a write to ``path`` replaces: ``path`` itself, or the file a symbolic link at ``path`` points to
    (as a plain ``open()`` writes through a link; renaming over the link would replace the link instead)."""
    path = Path(path)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path next to ``path`` (same suffix); on success rename it over ``path`` atomically,
    on failure remove it.

    The temporary name carries the writer's pid (``.<name>.<pid>.<random>.tmp<suffix>``), so one left by a killed
    process is recognised and removed by :func:`specgpu.core.locks.clean_stale_temporaries`. The file gets the mode a
    plain ``open()`` would give (:func:`new_temporary`); a ``path`` that is a symbolic link is written through,
    to the file it points to. An operating-system error (disk full, read-only folder) is re-raised as one line
    naming ``path``, never the temporary name; so is any error whose message names the temporary.
    """
    path = Path(path)
    target = write_target(path)
    if target.is_dir():  # found before anything is written, not by the rename at the end
        error = IsADirectoryError(f"{path}: is a folder, not a file; choose a file name")
        error.errno = errno.EISDIR
        raise error
    try:
        tmp = new_temporary(target)
    except OSError as exc:
        raise os_error(path, exc) from None
    try:
        yield tmp
        replace_with(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and (str(exc).startswith("[Errno") or (exc.errno is None and
                                                                         str(path) not in str(exc))):
            raise os_error(path, exc) from None  # a raw OS message ("[Errno 21] ...: 'a' -> 'b'"): one line
        text = str(exc)
        if isinstance(exc, (OSError, ValueError)) and final_names(text) != text:
            try:
                error = type(exc)(final_names(text))
            except TypeError:  # a type that needs more than a message (UnicodeDecodeError): as it was raised
                raise exc from None
            if isinstance(exc, OSError):
                error.errno = exc.errno
            raise error from None
        raise


def write_failed(path: Path, tmp: Path, label: str, message: str) -> Exception:
    """The error of a library's failed write of ``tmp`` (on its way to ``path``): one line naming ``path``, with
    the operating system's cause when the disk is full (the library says only "write error" or "scanline
    failed"), else the library's message with temporary names replaced."""
    full = disk_full(tmp.parent)
    if full is not None:
        error = OSError(f"{path}: cannot write {label} ({full})")
        error.errno = errno.ENOSPC
        return error
    return ValueError(f"{path}: cannot write {label} ({one_line(final_names(message))})")


def disk_full(folder: Path, probe_bytes: int = 1 << 20) -> str | None:
    """"No space left on device, N MB free" when the file system holding ``folder`` cannot take ``probe_bytes``
    more (a probe file written, synced and removed), else None. Called after a write failed, while its partial
    file still holds what it wrote: a full disk then has less room than one more block of it."""
    probe = None
    try:
        probe = new_temporary(Path(folder) / "space-probe")
        with open(probe, "wb") as fh:
            fh.write(bytes(probe_bytes))
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
            return None
        reason = exc.strerror or "No space left on device"
        try:
            reason += f", {shutil.disk_usage(folder).free / 1e6:.1f} MB free"
        except OSError:
            pass
        return reason
    finally:
        if probe is not None:
            try:
                probe.unlink()
            except OSError:
                pass
    return None


def os_error(path: Path, exc: OSError) -> OSError:
    """``exc`` as one line that names ``path`` (and how much room is left when the disk is full)."""
    reason = exc.strerror or one_line(str(exc))
    if exc.errno == errno.ENOSPC:
        try:
            free = shutil.disk_usage(path.parent).free
            reason += f", {free / 1e6:.1f} MB free"
        except OSError:
            pass
    error = type(exc)(f"{path}: cannot write ({reason})")
    error.errno = exc.errno
    return error


def _suffix(path: Path, allowed: tuple[str, ...], what: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in allowed:
        raise ValueError(f"{path}: unknown {what} format {suffix!r}; expected {' or '.join(allowed)}")
    return suffix


def _check_exists(path: Path, what: str) -> None:
    if not path.exists():
        raise FileNotFoundError(f"{path}: {what} not found")
    if not path.is_file():
        raise ValueError(f"{path}: {what} is not a file")


def error_of(source) -> str:
    """``source.geterror()`` (an OpenImageIO reader or the module); a message holding a corrupt file's bytes that
    are not UTF-8 would otherwise raise UnicodeDecodeError."""
    try:
        return source.geterror()
    except UnicodeDecodeError:
        return "corrupt data (error message not UTF-8)"
