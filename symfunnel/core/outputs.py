"""Output paths checked before the work starts, so a bad `--out` costs one line, not a finished computation."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from .errors import InputError


#: what marks a file symfunnel wrote (its generator line, title or metadata), searched in its first MARK_BYTES
MARKS = (b'<meta name="generator" content="symfunnel', b"<title>symfunnel report:", b"% symfunnel derive --latex",
         b"# A scenario written by `symfunnel init`", b"# Copied by `symfunnel init --from", b"Software\x00symfunnel",
         b"/Creator (symfunnel)")
MARK_BYTES = 16 << 20


def written_by_symfunnel(path: str | os.PathLike) -> bool:
    """True when the file at `path` carries one of symfunnel's MARKS (so replacing it loses nothing of the user's)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(MARK_BYTES)
    except OSError:
        return False
    return any(m in head for m in MARKS)


def check_not_input(path: str | os.PathLike, inputs, *, key: str) -> None:
    """InputError when `path` is (the same file as) one of the command's inputs: an input is never replaced."""
    p = Path(path)
    for src in inputs:
        try:
            same = os.path.samefile(p, src)
        except OSError:
            same = False
        if same or (not p.exists() and Path(os.path.abspath(p)) == Path(os.path.abspath(src))):
            raise InputError(f"is this command's input {src}", file=str(p), key=key,
                             expected="another path (an input is never replaced, not even with --force)")


def check_replaceable(path: str | os.PathLike, *, key: str, inputs=(), force: bool = False) -> Path:
    """A file path a command may write: never one of its inputs, and an existing file only when symfunnel wrote
    it or with --force (the rule `codegen --out` applies to a directory's files; InputError otherwise)."""
    p = check_output_file(path, key=key)
    check_not_input(p, inputs, key=key)
    if not force and p.exists() and not written_by_symfunnel(p):
        raise InputError("exists and was not written by symfunnel", file=str(p), key=key,
                         expected="--force to replace it, or another path")
    return p


def check_output_file(path: str | os.PathLike, *, key: str = "--out") -> Path:
    """Check that a file can be written at `path` (atomically, beside it); InputError naming it otherwise.

    Refused: an existing directory or non-regular file (a device would be replaced by the rename), a parent that
    is a file, and a directory where no file can be created (read-only, no permission, full).
    """
    p = Path(path)
    expected = "a writable file path"
    try:
        st = os.stat(p)
    except FileNotFoundError:
        st = None
    except NotADirectoryError:
        st = None                           # a parent is a file: reported below
    except OSError as exc:
        raise InputError(f"cannot be used ({exc.strerror or exc})", file=str(p), key=key, expected=expected) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise InputError("is a directory", file=str(p), key=key, expected="a file path (not a directory)")
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise InputError("exists and is not a regular file", file=str(p), key=key, expected=expected)
    parent = p.absolute().parent
    probe = parent
    while not (probe.exists() or probe.is_symlink()):               # the nearest existing ancestor decides whether parents can be made
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"cannot be created: {probe} is not a directory (Not a directory)", file=str(p), key=key, expected=expected)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".probe", dir=probe)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise InputError(f"cannot be written ({exc.strerror or exc} in {probe})", file=str(p), key=key,
                         expected=expected) from None
    return p


#: the largest --samples of verify and report (memory grows linearly with it: about 1 kB per sample)
MAX_SAMPLES = 1_000_000
#: the largest --points of `codegen --check` (memory grows linearly with it)
MAX_POINTS = 100_000


def check_count(value: int, *, key: str, minimum: int, maximum: int, what: str) -> int:
    """An integer option within [minimum, maximum] (the maximum keeps memory use bounded)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"is {value!r}", key=key, expected=f"{what}: an integer between {minimum} and {maximum}")
    if not minimum <= value <= maximum:
        raise InputError(f"is {value}", key=key, expected=f"{what} between {minimum} and {maximum}")
    return value


def scenario_inputs(scenario) -> list:
    """The files a command reads for its scenario (the TOML and the robot file it names), never to be replaced."""
    out = []
    if getattr(scenario, "path", None) is not None and Path(scenario.path).is_file():
        out.append(Path(scenario.path))
    raw = getattr(scenario, "raw", None)
    robot = (raw.get("model") or {}).get("path") if isinstance(raw, dict) and isinstance(raw.get("model"), dict) \
        else None
    if isinstance(robot, str) and out:
        out.append(out[0].parent / robot)
    return out
