"""Reading user files safely: regular files only, a size cap, and numbers that mean what they say.

Every file symfunnel reads from the user (a scenario, a point file, a URDF) goes through `read_input`, so a FIFO,
a device such as /dev/zero or a directory ends in one clear error instead of a hang or an exhausted memory.
Numbers are checked as they are parsed: a float literal that overflows to infinity (``1e309``) or underflows
(``1e-400``, or any non-zero literal below the smallest normal double) is refused, as is an integer with more
digits than Python converts (4300).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import stat
import sys
from typing import Any

from .errors import InputError

#: The largest input file read, in bytes (16 MiB; scenarios and URDFs are a few kB to a few MB).
MAX_INPUT_BYTES = 16 * 1024 * 1024

_TINY = sys.float_info.min          # smallest positive normal double, 2.2e-308
_recorders: list[dict] = []         # open `recording()` blocks: path -> sha256 of every file read


@contextlib.contextmanager
def recording():
    """Collect {resolved path: sha256} of every file `read_input` reads inside the block (a campaign's inputs)."""
    seen: dict[str, str] = {}
    _recorders.append(seen)
    try:
        yield seen
    finally:
        _recorders.remove(seen)


def file_digest(path: str | os.PathLike) -> str | None:
    """sha256 of a file's content now (None when it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return hashlib.sha256(fh.read()).hexdigest()
    except OSError:
        return None


def read_input(path: str | os.PathLike, *, expected: str, limit: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of a regular file of at most `limit` bytes; InputError naming the file otherwise."""
    file = str(path)
    try:
        # O_NONBLOCK: opening a FIFO with no writer must not block; it is refused below as not a regular file.
        fd = os.open(file, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise InputError("no such file", file=file, expected=expected) from None
    except IsADirectoryError:
        raise InputError("is a directory", file=file, expected=expected) from None
    except OSError as exc:
        raise InputError(f"cannot be read ({exc.strerror or exc})", file=file, expected=expected) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise InputError("is a directory", file=file, expected=expected)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"is not a regular file (it is a {_kind(st.st_mode)})", file=file, expected=expected)
        if st.st_size > limit:
            raise InputError(f"is {st.st_size} bytes, larger than the limit of {limit} bytes", file=file,
                             expected=expected)
        chunks, total = [], 0
        while True:                     # read to the cap even if the file grows while we read it
            try:
                b = os.read(fd, min(1 << 20, limit + 1 - total))
            except OSError as exc:
                raise InputError(f"cannot be read ({exc.strerror or exc})", file=file, expected=expected) from None
            if not b:
                break
            chunks.append(b)
            total += len(b)
            if total > limit:
                raise InputError(f"is larger than the limit of {limit} bytes", file=file, expected=expected)
        data = b"".join(chunks)
        if _recorders:
            digest = hashlib.sha256(data).hexdigest()
            for seen in _recorders:
                seen[os.path.realpath(file)] = digest
        return data
    finally:
        os.close(fd)


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "FIFO"
    if stat.S_ISCHR(mode):
        return "character device"
    if stat.S_ISBLK(mode):
        return "block device"
    if stat.S_ISSOCK(mode):
        return "socket"
    return "special file"


def read_text(path: str | os.PathLike, *, expected: str, limit: int = MAX_INPUT_BYTES) -> str:
    """`read_input` decoded as UTF-8 (InputError when it is not); a leading byte-order mark, which editors on
    Windows write and TOML forbids, is dropped."""
    data = read_input(path, expected=expected, limit=limit)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"is not UTF-8 text ({exc.reason} at byte {exc.start})", file=str(path),
                         expected=expected) from None


def _line_of(text: str, literal: str) -> str:
    """' at line N' for the first line holding `literal` as a token, or ''."""
    pat = re.compile(r"(?<![\w.])" + re.escape(literal) + r"(?![\w.])")
    for i, line in enumerate(text.splitlines(), 1):
        if pat.search(line):
            return f" at line {i}"
    return ""


def float_literal(literal: str, *, file: str | None, text: str = "") -> float:
    """A float literal's value; InputError when it overflows or a non-zero literal underflows."""
    v = float(literal)
    low = literal.lower().lstrip("+-")
    if low in ("inf", "nan", "infinity"):
        return v
    if math.isinf(v):
        raise InputError(f"the number {literal}{_line_of(text, literal)} overflows a double", file=file,
                         expected=f"a number of magnitude below {sys.float_info.max:.4g}")
    if v == 0.0 and re.search(r"[1-9]", literal.split("e")[0].split("E")[0]) or 0.0 < abs(v) < _TINY:
        raise InputError(f"the number {literal}{_line_of(text, literal)} underflows (it would become "
                         f"{v:g})", file=file, expected=f"0 or a number of magnitude at least {_TINY:.4g}")
    return v


def loads_toml(text: str, *, file: str) -> dict:
    """Parse TOML with checked float literals; InputError for invalid TOML or unusable numbers."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    try:
        return tomllib.loads(text, parse_float=lambda s: float_literal(s, file=file, text=text))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"is not valid TOML: {exc}", file=file, expected="a TOML file") from None
    except (RecursionError, MemoryError):
        raise InputError("is nested too deeply", file=file, expected="a TOML file") from None
    except ValueError as exc:      # int('...5001 digits...'): Python's integer conversion limit
        raise _digits(exc, file) from None


def loads_json(text: str, *, file: str | None, expected: str) -> Any:
    """Parse JSON with checked numbers (no NaN/Infinity, no overflow or underflow); InputError otherwise."""
    def constant(name):
        raise InputError(f"holds {name}, which is not JSON", file=file, expected="finite numbers")
    def pairs(items):
        seen = {}
        for k, v in items:
            if k in seen:
                raise InputError(f"has the key '{k}' twice", file=file, expected="each key once")
            seen[k] = v
        return seen
    try:
        return json.loads(text, parse_float=lambda s: float_literal(s, file=file, text=text),
                          parse_constant=constant, object_pairs_hook=pairs)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"is not valid JSON ({exc})", file=file, expected=expected) from None
    except ValueError as exc:
        raise _digits(exc, file) from None


def _digits(exc: ValueError, file: str | None) -> InputError:
    """The error for a number Python refuses to convert (more than sys.get_int_max_str_digits() digits)."""
    m = re.search(r"has (\d+) digits", str(exc))
    what = f"an integer of {m.group(1)} digits" if m else f"a number that cannot be read ({exc})"
    return InputError(f"holds {what}", file=file, expected="numbers of at most 4300 digits")


def number_array(value: Any, shape: tuple[int, ...], *, file: str | None, key: str, scalar_ok: bool = False):
    """Check `value` is numbers (not strings or booleans) laid out as `shape`; returns a float ndarray.

    Accepted: a flat array of prod(shape) numbers; for a 2-D shape also an array of rows; a single number when
    `scalar_ok` (it fills the shape) or when the shape holds one number.
    """
    import numpy as np
    size = int(np.prod(shape))
    expected = (f"{size} numbers" if len(shape) == 1 else
                f"{shape[0]} x {shape[1]} numbers (an array of {shape[0]} rows, or {size} numbers)")

    def number(x, k):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise InputError(f"is {_type(x)}", file=file, key=k, expected="a number")
        try:
            v = float(x)
        except OverflowError:
            raise InputError("is too large for a double", file=file, key=k, expected="a finite number") from None
        if not math.isfinite(v):
            raise InputError(f"is {v}", file=file, key=k, expected="a finite number")
        return v

    if not isinstance(value, list):
        if scalar_ok or size == 1:
            return np.full(shape, number(value, key))
        raise InputError(f"is {_type(value)}", file=file, key=key, expected=expected)
    if len(shape) == 2 and value and all(isinstance(r, list) for r in value):
        if len(value) != shape[0] or any(len(r) != shape[1] for r in value):
            raise InputError("has the wrong shape", file=file, key=key, expected=expected)
        return np.array([[number(x, f"{key}[{i}][{j}]") for j, x in enumerate(r)] for i, r in enumerate(value)])
    if len(value) != size:
        raise InputError(f"has {len(value)} entries", file=file, key=key, expected=expected)
    flat = [number(x, f"{key}[{i}]") for i, x in enumerate(value)]
    a = np.array(flat, dtype=float)
    return a.reshape(shape, order="F") if len(shape) == 2 else a.reshape(shape)


def _type(x: Any) -> str:
    """`x`'s JSON type with its article: 'a string', 'an array', 'null'."""
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "an object", type(None): "null"}.get(type(x), "a " + type(x).__name__)
