"""Small I/O helpers: atomic writes, so that a failure never leaves a half-written output file."""

from __future__ import annotations

import contextlib
import errno
import math
import os
import tempfile
from pathlib import Path


def umask_mode(directory: bool = False) -> int:
    """The permission bits a plain open()/mkdir() would give, so temporary files renamed into place do too."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


_FULL = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}


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
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if exc.errno in _FULL:                  # a full disk, a file size limit (ulimit -f), a quota
            from .errors import InputError
            raise InputError(f"cannot be written ({exc.strerror or exc})", file=str(path),
                             expected="space for the file on its device (and no file size limit below it)") \
                from None
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        lifecycle.unregister_temporary(tmp)


_staging: list[dict] = []


@contextlib.contextmanager
def staged():
    """Hold back every `atomic_write` of the block and write them all when it succeeds: a command that fails or
    is stopped half-way (its wall-clock limit, a signal) leaves none of its files, not some of them."""
    batch: dict[Path, str | bytes] = {}
    _staging.append(batch)
    try:
        yield batch
    finally:
        _staging.remove(batch)
    if _staging:                                # nested: the outer block writes them
        _staging[-1].update(batch)
        return
    with contextlib.ExitStack() as stack:       # every file to its temporary first, then the renames
        tmps = [(stack.enter_context(atomic_path(path)), data, path) for path, data in batch.items()]
        for tmp, data, path in tmps:
            _write(tmp, data, path)


def _write(tmp: Path, data: str | bytes, target: Path) -> None:
    try:
        mode = "wb" if isinstance(data, bytes) else "w"
        with open(tmp, mode, **({} if isinstance(data, bytes) else {"encoding": "utf-8"})) as fh:
            fh.write(data)
    except OSError as exc:                      # a full disk, a file size limit (ulimit -f), ...
        from .errors import InputError
        raise InputError(f"cannot be written ({exc.strerror or exc})", file=str(target),
                         expected="space for the file on its device (and no file size limit below it)") from None


def atomic_write(path: str | os.PathLike, data: str | bytes) -> Path:
    """Write `data` to `path` atomically (temporary file + rename); returns the path. Inside `staged()` the write
    happens when the block ends."""
    if _staging:
        _staging[-1][Path(path)] = data
        return Path(path)
    with atomic_path(path) as tmp:
        _write(tmp, data, Path(path))
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
    file is removed when the block ends, and so is the directory when this call created it and nothing was written
    into it (a command refused on its input leaves nothing behind).
    """
    import fcntl

    from . import lifecycle
    from .errors import InputError
    d = Path(directory)
    created = not d.exists()
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
        if created:
            with contextlib.suppress(OSError):      # only when empty: rmdir refuses a directory with files
                d.rmdir()
