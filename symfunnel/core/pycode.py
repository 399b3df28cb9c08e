"""Compiled Python code of the generated interval and round-off tapes, cached in memory and on disk.

CPython's compile() of a large straight-line function is the dearest step of building a tape evaluator (1.7 s of
arm7's certificates); the code object is a pure function of the source text and the interpreter, so it is kept
as marshal data under $SYMFUNNEL_CACHE/pycode, keyed by sha256 over both, exactly as a .pyc is for a module.
"""

from __future__ import annotations

import hashlib
import marshal
import os
import sys
import tempfile
import types
from pathlib import Path

__all__ = ["compile_source"]

_MEMORY: dict[str, object] = {}
_MEMORY_MAX = 64
#: below this many characters compile() costs less than reading a file
_DISK_ABOVE = 20_000


def _key(source: str, filename: str) -> str:
    h = hashlib.sha256()
    for part in (sys.version, str(marshal.version), filename, source):
        h.update(part.encode("utf-8", "surrogatepass"))
        h.update(b"\0")
    return h.hexdigest()


def compile_source(source: str, filename: str):
    """compile(source, filename, "exec"), from the cache when the same source was compiled before."""
    key = _key(source, filename)
    code = _MEMORY.get(key)
    if code is not None:
        return code
    path = None
    if len(source) > _DISK_ABOVE:
        from .ccompile import cache_dir
        path = cache_dir() / "pycode" / f"{key[:40]}.marshal"
        code = _read(path)
    if code is None:
        code = compile(source, filename, "exec")
        if path is not None:
            _write(path, code)
    _MEMORY[key] = code
    while len(_MEMORY) > _MEMORY_MAX:
        _MEMORY.pop(next(iter(_MEMORY)))
    return code


def _read(path: Path):
    """The code object stored at path, or None when there is none or it cannot be read back (then rebuilt)."""
    try:
        data = path.read_bytes()
        code = marshal.loads(data)
    except (OSError, ValueError, EOFError, TypeError):
        return None
    return code if isinstance(code, types.CodeType) else None


def _write(path: Path, code) -> None:
    """Store code at path through a temporary file and a rename (a reader never sees half a file); a cache that
    cannot be written is skipped."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".pycode.", dir=path.parent)
        from . import lifecycle
        lifecycle.register_temporary(tmp)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(marshal.dumps(code))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        finally:
            lifecycle.unregister_temporary(tmp)
    except OSError:
        pass
