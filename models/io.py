"""Files: atomic writes, paths that stay inside their directory, and reading a small input file
without being made to hang, to read forever or to follow a link loop.

An interrupted run leaves either the old file or the new one, never half (`atomic_path`).
A name that comes from input (a scene's name, an integrator's) becomes part of a file name only
through `inside`, which refuses a result outside the directory it was meant for.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path


class WriteFailed(OSError):
    """A result file could not be written (no space, read-only, a directory in its place...);
    the old file, if any, is intact. The message names the file and the cause."""

    def __str__(self) -> str:
        return f"cannot write {self.filename}: {self.strerror}"


def _write_failed(path: Path, exc: OSError) -> WriteFailed:
    if isinstance(exc, WriteFailed):
        return exc
    why = exc.strerror or str(exc)
    if os.path.isdir(path):
        why = "a directory is in its place"
    return WriteFailed(exc.errno or errno.EIO, why, str(path))



def user_cache_dir(env=os.environ) -> Path:
    """Where reelbench keeps what it can recompute (compiled programs, reference solutions):
    ``$REELBENCH_CACHE``, else ``$XDG_CACHE_HOME/reelbench``, else ``~/.cache/reelbench``."""
    if env.get("REELBENCH_CACHE"):
        return Path(env["REELBENCH_CACHE"]).expanduser()
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "reelbench"

@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success rename it over ``path``. A failure of
    the file system (full, read-only, a directory where the file goes) is a `WriteFailed`
    naming the file, with no temporary left behind."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise _write_failed(path, exc) from None
    try:
        yield Path(tmp)
        # mkstemp makes the file private (0600); a result file gets the usual umask mode
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _write_failed(path, exc) from None
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


# --------------------------------------------------------------------------------------------
# Paths built from names
# --------------------------------------------------------------------------------------------


def printable(text: str) -> str:
    """``text`` with every character that is not printable (a NUL, a newline, a bidirectional
    override such as U+202E) written as its escape, so that a message quoting input is one line
    that shows what it quotes: ``printable("a\\nb") == "a\\\\nb"``."""
    return "".join(ch if ch.isprintable() else ascii(ch)[1:-1] for ch in str(text))


class UnsafePath(ValueError):
    """A path built from a name would lie outside the directory it was meant for."""


def inside(directory: str | os.PathLike, *parts: str | os.PathLike) -> Path:
    """``directory / parts`` with symbolic links resolved, refused unless strictly inside ``directory``.

    Every writer that puts a name from input into a file name goes through this, so that a
    name such as ``../../elsewhere/evil`` (or a link planted inside ``directory``) can never
    make it write elsewhere:

        >>> inside("/tmp/out", "fig_fixed_length.png")
        PosixPath('/tmp/out/fig_fixed_length.png')
        >>> inside("/tmp/out", "../evil.png")
        Traceback (most recent call last):
        ...
        models.io.UnsafePath: '../evil.png' is not a file name inside /tmp/out: ...
    """
    base = Path(directory).resolve()
    if not parts:
        raise UnsafePath(f"inside({str(directory)!r}) needs a file name below the directory")
    for part in parts:
        text = os.fspath(part)
        if not text or "\x00" in text or os.path.isabs(text):
            raise UnsafePath(f"{text!r} is not a name below {base}: names are relative, non-empty, without NUL")
        if "/" in text or "\\" in text or text in (".", ".."):
            # one directory level per part: a name glued to a prefix ("fig_" + "../x") stays refused
            raise UnsafePath(f"{text!r} is not a file name inside {base}: a name from input must be one "
                             f"path component, without '/', '\\', or a bare '.' / '..'")
    target = base.joinpath(*parts).resolve()
    if base not in target.parents:
        shown = os.path.join(*map(os.fspath, parts))
        raise UnsafePath(f"{shown!r} leads outside {base} (to {target}): a name from input must stay a "
                         f"file name inside its output directory, and a link inside it may not lead out of it")
    return target


# --------------------------------------------------------------------------------------------
# Reading a small input file
# --------------------------------------------------------------------------------------------


class FileRefused(ValueError):
    """A file `read_regular_file` will not read; ``kind`` says why ("missing", "loop",
    "directory", "special", "too_large", "unreadable"), the message says it in words."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


_SPECIAL = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
            (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _refuse_unless_regular(mode: int, max_bytes: int, size: int) -> None:
    if stat.S_ISDIR(mode):
        raise FileRefused("directory", "is a directory, not a file")
    if not stat.S_ISREG(mode):
        what = next((name for test, name in _SPECIAL if test(mode)), "not a regular file")
        raise FileRefused("special", f"is {what}, not a regular file: give the path of a file on disk")
    if size > max_bytes:
        raise FileRefused("too_large", f"is {size:,} bytes, more than the {max_bytes:,} such a file may have")


def _os_problem(path: str, exc: OSError) -> FileRefused:
    if exc.errno == errno.ELOOP:
        return FileRefused("loop", "is a symbolic link loop (following it leads back to itself): "
                                   "point the link at a file")
    if exc.errno in (errno.ENOENT, errno.ENOTDIR):
        if os.path.islink(path):
            return FileRefused("missing", f"is a symbolic link to {os.readlink(path)!r}, which does not exist")
        return FileRefused("missing", "not found")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return FileRefused("unreadable", "cannot be read (permission denied)")
    if exc.errno == errno.ENAMETOOLONG:
        return FileRefused("unreadable", "cannot be read: the path is too long")
    return FileRefused("unreadable", f"cannot be read ({exc.strerror or exc})")


def require_regular(path: str | os.PathLike, max_bytes: float = float("inf")) -> None:
    """`FileRefused` unless ``path`` (links followed) is a regular file of at most ``max_bytes``:
    for readers that open a file themselves (numpy, zipfile), which a FIFO would block."""
    path = os.fspath(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _os_problem(path, exc) from None
    _refuse_unless_regular(st.st_mode, max_bytes, st.st_size)


def read_regular_file(path: str | os.PathLike, max_bytes: int) -> bytes:
    """The bytes of ``path``, a regular file of at most ``max_bytes``; anything else is refused
    (`FileRefused`) before it is read: a FIFO (whose open would block), a device (``/dev/zero``
    would be read until the memory runs out), a directory, a link loop, a file too large.

    The file is opened without blocking and checked again once open (it may have been
    replaced in between), and never more than ``max_bytes + 1`` bytes are read.
    """
    path = os.fspath(path)
    require_regular(path, max_bytes)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise _os_problem(path, exc) from None
    try:
        st = os.fstat(fd)
        _refuse_unless_regular(st.st_mode, max_bytes, st.st_size)
        chunks, total = [], 0
        while total <= max_bytes:
            chunk = os.read(fd, max_bytes + 1 - total)
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        if total > max_bytes:
            raise FileRefused("too_large", f"grew beyond {max_bytes:,} bytes while being read")
        return b"".join(chunks)
    finally:
        os.close(fd)
