"""Compile generated C once and cache the result by a hash of its sources, the compiler and the flags.

The cache lives in $SYMFUNNEL_CACHE, else $XDG_CACHE_HOME/symfunnel, else ~/.cache/symfunnel. An entry is built
in a temporary directory and renamed into place, so concurrent runs never see half-built files.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from ..errors import InputError

__all__ = ["Built", "cache_dir", "find_compiler", "compile_cached", "SHARED_FLAGS"]

#: Flags for the shared library the checks load through ctypes.
SHARED_FLAGS = ("-std=c99", "-O2", "-fPIC", "-shared")


@dataclass(frozen=True)
class Built:
    """A compiled artifact: its path, the cache key, and whether it came from the cache (no compiler run)."""

    path: Path
    key: str
    cached: bool


def cache_dir() -> Path:
    """Where compiled code is cached."""
    env = os.environ.get("SYMFUNNEL_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "symfunnel"


def find_compiler() -> str:
    """The C compiler: $CC, else gcc, cc or clang on PATH; InputError when there is none."""
    cands = [os.environ["CC"]] if os.environ.get("CC") else ["gcc", "cc", "clang"]
    for c in cands:
        path = shutil.which(c)
        if path:
            return path
    raise InputError("no C compiler found", key="CC", expected="gcc, cc or clang on PATH, or $CC")


@lru_cache(maxsize=None)
def _compiler_id(cc: str) -> str:
    """The compiler's version banner (part of the cache key)."""
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
        return out.stdout.splitlines()[0] if out.stdout else cc
    except (OSError, subprocess.SubprocessError):
        return cc


def _key(sources: dict[str, str | bytes], flags: tuple[str, ...], output: str, cc: str) -> str:
    h = hashlib.sha256()
    for part in (cc, _compiler_id(cc), output, "\0".join(flags)):
        h.update(part.encode() + b"\0")
    for name in sorted(sources):
        data = sources[name]
        h.update(name.encode() + b"\0")
        h.update(data if isinstance(data, bytes) else data.encode("utf-8"))
        h.update(b"\0")
    return h.hexdigest()


def compile_cached(sources: dict[str, str | bytes], compile_files: list[str], output: str,
                   flags: tuple[str, ...] | list[str], *, libs: tuple[str, ...] = ("-lm",),
                   cache: Path | None = None, on_build=None) -> Built:
    """Compile `compile_files` (names in `sources`) into `output` with `flags`, once per distinct input.

    The key is sha256 over the compiler and its version, the flags, the output name and every source file's
    name and text (headers included). A compiler failure raises RuntimeError with its diagnostics.
    `on_build(message)` is called just before the compiler runs (not on a cache hit), for progress output.
    """
    flags = tuple(flags)
    cc = find_compiler()
    key = _key(sources, flags + tuple(libs) + tuple(compile_files), output, cc)
    root = Path(cache) if cache is not None else cache_dir()
    entry = root / key[:32]
    target = entry / output
    if target.exists():
        return Built(target, key, True)
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", dir=root))
    try:
        for name, data in sources.items():
            mode = "wb" if isinstance(data, bytes) else "w"
            with open(tmp / name, mode, **({} if isinstance(data, bytes) else {"encoding": "utf-8"})) as fh:
                fh.write(data)
        cmd = [cc, *flags, "-o", output, *compile_files, *libs]
        if on_build is not None:
            on_build(f"compiling {output} (one-time; cached in {root})")
        proc = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True)
        if proc.returncode != 0 or proc.stderr.strip():
            raise RuntimeError(f"compiling {output} failed ({' '.join(cmd)}):\n{proc.stderr.strip()}")
        try:
            os.rename(tmp, entry)
        except OSError:
            if not target.exists():     # lost a race with a broken entry: rebuild next time
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return Built(target, key, True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return Built(target, key, False)
