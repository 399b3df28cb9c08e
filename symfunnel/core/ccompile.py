"""Compile generated C once and cache the result by a hash of its sources, the compiler and the flags.

The cache lives in $SYMFUNNEL_CACHE, else $XDG_CACHE_HOME/symfunnel, else ~/.cache/symfunnel. An entry is built
in a temporary directory and renamed into place, so concurrent runs never see half-built files. Each entry records
the size and sha256 of its output (entry.json); an entry that does not match (truncated, emptied, altered, or from
before the record existed) is rebuilt with one warning instead of being loaded. When the cache directory cannot be
written, the output is built in a private temporary directory (removed at exit), again with one warning. Two
processes that need the same entry at once build it once: the builder holds an exclusive lock on the entry's lock
file (flock; removed when the build ends), and the other waits for it, then loads what it built. The
compiler runs in its own process group under a time limit ($SYMFUNNEL_COMPILE_TIMEOUT seconds, default 600); on
timeout, Ctrl-C or SIGTERM the whole group (gcc and its cc1/as/ld children) is killed and the temporary files removed.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import json
import os
import shutil
import signal
import subprocess
import tempfile
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from .errors import InputError

__all__ = ["Built", "cache_dir", "find_compiler", "compile_cached", "verify_entry", "run_compiler", "SHARED_FLAGS"]

#: Flags for the shared libraries the checks and the sampled-data loops load through ctypes. gcc's -Og: ISO C
#: (-std=c99, so no floating-point contraction) gives the same IEEE results at any -O level, and measured on the
#: sampled loop (controller, plant step and loop libraries) it ran as fast as at -O2 (arm7 at 1 kHz for 3 s: 1.31
#: against 1.32 CPU-s, paper 0.06 against 0.06, bit-identical q, dq, tau and margins) at about 60 % of the
#: compile time (arm7's 1.5 against 0.9 CPU-s of gcc); what ships is compiled by its own Makefile's flags.
SHARED_FLAGS = ("-std=c99", "-Og", "-fPIC", "-shared")

#: The record of an entry's output, written last into the entry before it is renamed into place.
RECORD = "entry.json"
DEFAULT_TIMEOUT = 600.0


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
                   cache: Path | None = None, on_build=None, timeout: float | None = None,
                   identity: bytes | None = None) -> Built:
    """Compile `compile_files` (names in `sources`) into `output` with `flags`, once per distinct input.

    The key is sha256 over the compiler and its version, the flags, the output name and every source file's
    name and text (headers included) — or, given `identity`, those bytes in place of the sources, which may then be
    a callable returning them, called only when the entry must be built (generating the sources can cost more
    than compiling them). A compiler failure raises RuntimeError with its diagnostics.
    `on_build(message)` is called just before the compiler runs (not on a cache hit), for progress output.
    `timeout` (default `compile_timeout()`) bounds the compiler's run; a damaged entry is rebuilt with a warning.
    """
    flags = tuple(flags)
    cc = find_compiler()
    key = _key(sources if identity is None else {"identity": identity}, flags + tuple(libs) + tuple(compile_files),
               output, cc)
    root = Path(cache) if cache is not None else cache_dir()
    entry = root / key[:32]
    target = entry / output
    if entry.exists():
        problem = verify_entry(entry, output, key)
        if problem is None:
            return Built(target, key, True)
        if problem != LEGACY:                  # an earlier version's entry is rebuilt without a warning
            warnings.warn(f"compile cache entry {entry} is damaged ({problem}); rebuilding it", RuntimeWarning,
                          stacklevel=2)
        if not _discard(entry, root):
            root = _private_root()
            entry, target = root / key[:32], root / key[:32] / output
    with _build_lock(root, key, output, on_build):
        if entry.exists() and verify_entry(entry, output, key) is None:     # built while this process waited
            return Built(target, key, True)
        return _build_entry(sources, compile_files, output, flags, libs, cc, key, root, entry, target, on_build,
                            timeout)


@contextlib.contextmanager
def _build_lock(root: Path, key: str, output: str, on_build):
    """Hold an exclusive flock on `root/.<key>.lock` while the entry is built, so that concurrent processes
    compile it once; no lock (and no error) where the cache cannot be written or flock does not exist."""
    try:
        import fcntl
        root.mkdir(parents=True, exist_ok=True)
    except (ImportError, OSError):
        yield
        return
    path = root / f".{key[:32]}.lock"
    said = False
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
        except OSError:
            yield
            return
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if on_build is not None and not said:
                    said = True
                    on_build(f"waiting for another process compiling {output} into {root}")
                fcntl.flock(fd, fcntl.LOCK_EX)
            # the holder before us removed the file as it finished: our lock is on an unlinked inode, retry
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(path))
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def _build_entry(sources, compile_files, output, flags, libs, cc, key, root, entry, target, on_build,
                 timeout) -> Built:
    """Compile into a temporary directory of `root` and rename it into `entry` (the body of compile_cached)."""
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", dir=root))
    except OSError as exc:
        if str(root) not in _WARNED:            # once per process and cache directory
            _WARNED.add(str(root))
            warnings.warn(f"compile cache {root} is not writable ({exc.strerror or exc}); building in a "
                          "temporary directory instead", RuntimeWarning, stacklevel=3)
        root = _private_root()
        entry, target = root / key[:32], root / key[:32] / output
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", dir=root))
    from . import lifecycle
    lifecycle.register_temporary(tmp)
    try:
        if on_build is not None:
            on_build(f"compiling {output} (one-time; cached in {root})")
        if callable(sources):
            sources = sources()
        for name, data in sources.items():
            mode = "wb" if isinstance(data, bytes) else "w"
            with open(tmp / name, mode, **({} if isinstance(data, bytes) else {"encoding": "utf-8"})) as fh:
                fh.write(data)
        cmd = [cc, *flags, "-o", output, *compile_files, *libs]
        returncode, err = run_compiler(cmd, cwd=tmp, timeout=compile_timeout() if timeout is None else timeout)
        if returncode != 0 or err.strip():
            raise RuntimeError(f"compiling {output} failed ({' '.join(cmd)}):\n{err.strip()}")
        _write_record(tmp, output, key)
        try:
            os.rename(tmp, entry)
        except OSError:
            if verify_entry(entry, output, key) is not None:   # lost a race with a broken entry: rebuild next time
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return Built(target, key, True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        lifecycle.unregister_temporary(tmp)
    return Built(target, key, False)


def compile_timeout() -> float:
    """The compiler's time limit in seconds: $SYMFUNNEL_COMPILE_TIMEOUT, else 600."""
    try:
        v = float(os.environ.get("SYMFUNNEL_COMPILE_TIMEOUT", DEFAULT_TIMEOUT))
    except ValueError:
        raise InputError(f"is '{os.environ['SYMFUNNEL_COMPILE_TIMEOUT']}'", key="SYMFUNNEL_COMPILE_TIMEOUT",
                         expected="a number of seconds > 0") from None
    from .deadline import check_seconds
    return check_seconds(v, key="SYMFUNNEL_COMPILE_TIMEOUT")


def run_compiler(cmd: list[str], *, cwd: Path, timeout: float) -> tuple[int, str]:
    """Run `cmd` in its own process group; kill the whole group on timeout or any exception (Ctrl-C, SIGTERM).

    The compiler's own temporaries (cc*.s, cc*.o, *.res) go to a private $TMPDIR, removed when it ends however it
    ends (and by the watchdog when the process is stopped): a killed gcc left them in the user's $TMPDIR."""
    import shutil
    import tempfile

    from . import lifecycle
    proc = None
    scratch = None
    try:
        # a signal between the fork inside Popen and the registration would leave the compiler running: the two
        # happen with signals deferred, and the signal is raised here, inside the try that kills the group
        with lifecycle.signals_deferred():
            scratch = tempfile.mkdtemp(prefix="symfunnel-cc-")
            lifecycle.register_temporary(scratch)
            env = dict(os.environ, TMPDIR=scratch, TMP=scratch, TEMP=scratch)
            proc = subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, start_new_session=True, env=env)
            lifecycle.register_child(proc.pid, group=True)
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        raise RuntimeError(f"compiling with {cmd[0]} took longer than {timeout:g} s and was stopped "
                           "(raise $SYMFUNNEL_COMPILE_TIMEOUT if the code is large)") from None
    except BaseException:
        if proc is not None:
            _kill_group(proc)
        raise
    finally:
        if proc is not None:
            lifecycle.unregister_child(proc.pid)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
            lifecycle.unregister_temporary(scratch)
    return proc.returncode, (out or "") + (err or "")


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL the process group led by `proc` (the compiler and every child it started) and reap `proc`."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.communicate(timeout=10)
    except (subprocess.TimeoutExpired, OSError, ValueError):
        pass


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_record(directory: Path, output: str, key: str | None = None) -> None:
    path = directory / output
    rec = {"output": output, "size": path.stat().st_size, "sha256": _sha256(path), "key": key}
    with open(directory / RECORD, "w", encoding="utf-8") as fh:
        json.dump(rec, fh)


#: what `verify_entry` says of an entry an earlier symfunnel wrote (its record has no key): rebuilt, not damaged
LEGACY = "written by an earlier symfunnel (its record names no key)"


def verify_entry(entry: Path, output: str, key: str | None = None) -> str | None:
    """None when `entry` holds `output` with the size and sha256 its record names, and (given `key`) the record
    names that key (an entry copied over another's is not this one); else what is wrong."""
    target = entry / output
    try:
        with open(entry / RECORD, encoding="utf-8") as fh:
            rec = json.load(fh)
        size, digest = int(rec["size"]), str(rec["sha256"])
    except FileNotFoundError:
        return "no integrity record"
    except (OSError, ValueError, KeyError, TypeError):
        return "unreadable integrity record"
    if key is not None and "key" not in rec:
        return LEGACY
    if key is not None and rec.get("key") != key:
        return "its record names another key (an entry copied over this one)"
    try:
        actual = target.stat().st_size
    except OSError:
        return f"{output} is missing"
    if actual != size:
        return f"{output} is {actual} bytes, recorded {size}"
    try:
        if _sha256(target) != digest:
            return f"{output} does not match its recorded sha256"
    except OSError as exc:
        return f"{output} cannot be read ({exc.strerror or exc})"
    return None


def _discard(entry: Path, root: Path) -> bool:
    """Move a damaged entry aside and delete it; False when the cache cannot be changed."""
    try:
        aside = Path(tempfile.mkdtemp(prefix=".discard.", dir=root))
        os.rename(entry, aside / "entry")
    except OSError:
        return False
    shutil.rmtree(aside, ignore_errors=True)
    return True


_PRIVATE: list[Path] = []
_WARNED: set[str] = set()


def _private_root() -> Path:
    """A per-process cache directory in the system's temporary directory, removed when the process exits."""
    if not _PRIVATE:
        d = Path(tempfile.mkdtemp(prefix="symfunnel-cache-"))
        _PRIVATE.append(d)
        atexit.register(shutil.rmtree, d, True)
    return _PRIVATE[0]
