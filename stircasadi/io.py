"""Files written safely: atomic writes and output paths checked before the long work starts.

Every command and every writer in the package goes through here, so that

* a failed write (disk full, a kill, a crash) never leaves a truncated file under the real name:
  data go to a temporary file in the same folder, are flushed and fsync'ed, then renamed over
  the target (``os.replace`` is atomic on POSIX and Windows);
* an output path that equals an input, is a folder, or lies in a folder that does not exist or
  cannot be written is refused with a clear ``OutputError`` *before* anything is computed, and
  no input or earlier output is touched.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from .errors import OutputError

__all__ = ["atomic_write_text", "atomic_write_bytes", "atomic_path", "check_output", "same_file"]


def same_file(a, b) -> bool:
    """Whether two paths name the same file (resolved, or the same inode when both exist)."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def check_output(path, inputs=(), what: str = "output", suffixes: tuple | None = None,
                 folder: bool = False) -> Path:
    """Check that ``path`` can be written (a file, or a folder when ``folder``) and is none of
    ``inputs``; create nothing. Returns the path. Raises ``OutputError`` saying what is wrong and
    how to fix it."""
    if path is None or str(path) == "":
        raise OutputError(f"No {what} path given; pass --out PATH.")
    p = Path(path).expanduser()
    for src in inputs:
        if src is not None and same_file(p, src):
            raise OutputError(f"The {what} path {p} is the input file {src}; writing it would destroy "
                              "the input. Choose another --out path.")
    if folder:
        if p.exists() and not p.is_dir():
            raise OutputError(f"The {what} folder {p} exists and is a file; give a folder path.")
        parent = p if p.exists() else _nearest_existing(p)
    else:
        if p.is_dir():
            raise OutputError(f"The {what} path {p} is a folder; give a file name inside it, e.g. "
                              f"{p / ('out' + (suffixes[0] if suffixes else ''))}.")
        if suffixes and p.suffix.lower() not in suffixes:
            raise OutputError(f"The {what} file {p} should end in {' or '.join(suffixes)}; got "
                              f"{p.suffix or 'no suffix'!r}.")
        parent = p.parent if str(p.parent) else Path(".")
        if not parent.exists():
            raise OutputError(f"The folder {parent} of the {what} file does not exist; create it "
                              f"(mkdir -p {parent}) or choose another --out path.")
        if not parent.is_dir():
            raise OutputError(f"{parent} is not a folder; cannot write the {what} file {p} in it.")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"The folder {parent} is not writable; cannot write the {what} {p}. "
                          "Choose a writable location.")
    if p.exists() and not p.is_dir() and not os.access(p, os.W_OK):
        raise OutputError(f"The {what} file {p} exists and is read-only; remove it or choose another path.")
    return p


def _nearest_existing(p: Path) -> Path:
    q = p
    while not q.exists():
        if q.parent == q:
            break
        q = q.parent
    return q


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Context manager yielding a temporary path beside ``path``; on success the temporary file
    is fsync'ed and renamed over ``path``, on error it is removed and ``path`` is untouched.
    For writers that need a file name (h5py, matplotlib)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp",
                               dir=str(path.parent) if str(path.parent) else ".")
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        # mkstemp makes the file 0600; give it the mode an ordinary open() would (the existing
        # file's mode when replacing one, else 0666 less the umask)
        try:
            mode = path.stat().st_mode & 0o777
        except OSError:
            mode = 0o666 & ~_umask()
        os.chmod(tmp, mode)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename)."""
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
    except OSError as exc:
        raise OutputError(f"Could not write {path}: {exc.strerror or exc}. Nothing was changed at "
                          "that path; free disk space or choose another location.") from exc
    return path


def atomic_write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(str(folder) if str(folder) else ".", os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
