"""Small I/O helpers: atomic writes, so that a failure never leaves a half-written output file."""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from pathlib import Path


def umask_mode(directory: bool = False) -> int:
    """The permission bits a plain open()/mkdir() would give, so temporary files renamed into place do too."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from . import lifecycle
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    lifecycle.register_temporary(tmp)
    try:
        yield Path(tmp)
        os.chmod(tmp, umask_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        lifecycle.unregister_temporary(tmp)


def atomic_write(path: str | os.PathLike, data: str | bytes) -> Path:
    """Write `data` to `path` atomically (temporary file + rename); returns the path."""
    with atomic_path(path) as tmp:
        mode = "wb" if isinstance(data, bytes) else "w"
        with open(tmp, mode, **({} if isinstance(data, bytes) else {"encoding": "utf-8"})) as fh:
            fh.write(data)
    return Path(path)


def json_safe(o):
    """A JSON-safe copy: numpy scalars and arrays to Python, non-finite floats to None (JSON has no NaN)."""
    import numpy as np
    if isinstance(o, dict):
        return {k: json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    if isinstance(o, np.ndarray):
        return json_safe(o.tolist())
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    return o


@contextlib.contextmanager
def exclusive_lock(directory: str | os.PathLike, *, what: str, key: str = "--out"):
    """Hold `directory/.lock` exclusively for the block (flock; released when the process dies, however it dies).

    A second holder is refused at once with InputError naming the directory and the pid that holds it. The lock
    file is removed when the block ends.
    """
    import fcntl

    from . import lifecycle
    from .errors import InputError
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot be created ({exc.strerror or exc})", file=str(d), key=key,
                         expected="a writable directory") from None
    path = d / ".lock"
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(f"cannot be locked ({exc.strerror or exc})", file=str(d), key=key,
                             expected="a writable directory") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
            except OSError:
                holder = "?"
            os.close(fd)
            raise InputError(f"is in use by another {what} (process {holder})", file=str(d), key=key,
                             expected=f"a directory no other {what} is writing; wait for it or choose another")
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino    # not a lock file its last holder just removed
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    lifecycle.register_temporary(path)
    try:
        yield path
    finally:
        lifecycle.unregister_temporary(path)
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)
