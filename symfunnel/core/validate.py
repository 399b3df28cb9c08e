"""Helpers for validating parsed TOML tables with errors that name the file, the key and what was expected."""

from __future__ import annotations

import difflib
import math
from typing import Any, Iterable

from .errors import InputError

_MISSING = object()

#: the shortest horizon a simulation accepts, in output steps (or sample periods): a check over fewer points says
#: next to nothing, and a horizon of 1e-300 s "holds at all 2 points"
MIN_HORIZON_STEPS = 10


def check_horizon(t_final: float, step: float, *, key: str, file: str | None = None,
                  step_name: str = "output step dt") -> None:
    """InputError unless t_final spans at least MIN_HORIZON_STEPS steps of `step` seconds."""
    if not (math.isfinite(t_final) and t_final >= MIN_HORIZON_STEPS * step * (1 - 1e-9)):
        raise InputError(f"is {t_final:.6g} s, {t_final / step:.3g} of the {step_name} = {step:.6g} s", file=file,
                         key=key, expected=f"a horizon of at least {MIN_HORIZON_STEPS} of them "
                         f"(t_final >= {MIN_HORIZON_STEPS * step:.6g} s)")


#: the most memory the arrays of one run may take: a longer run is refused before any work (one line, exit 2)
MAX_RUN_BYTES = 4 << 30


def check_run_memory(samples: float, values_per_sample: int, *, key: str, file: str | None = None,
                     what: str = "samples") -> None:
    """InputError naming `key` (the options that set the count, e.g. '--t-final x --rate') when `samples` records of
    `values_per_sample` doubles would exceed MAX_RUN_BYTES: estimated up front, not met as a MemoryError."""
    need = float(samples) * int(values_per_sample) * 8.0
    if not need <= MAX_RUN_BYTES:
        raise InputError(f"make {float(samples):.3g} {what} of {int(values_per_sample)} values, "
                         f"{need / 2**30:.3g} GiB of arrays", file=file, key=key,
                         expected=f"at most {MAX_RUN_BYTES / 2**30:g} GiB: a shorter horizon or a lower rate")


def join(prefix: str, key: str | int) -> str:
    """Dotted key path: join('model', 'links') -> 'model.links'; join('links', 2) -> 'links[2]'."""
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return f"{prefix}.{key}" if prefix else key


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """A ' (did you mean ...?)' hint, or '' when nothing is close (a choice spelt with other case comes first)."""
    choices = list(choices)
    same = [c for c in choices if c.lower() == word.lower()]
    close = same or difflib.get_close_matches(word, choices, n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


def check_keys(table: Any, allowed: Iterable[str], *, file: str, prefix: str,
               required: Iterable[str] = ()) -> dict:
    """Check that `table` is a table whose keys are all `allowed` and hold every `required` key."""
    allowed = list(allowed)
    if not isinstance(table, dict):
        raise InputError(f"is {a_type(table)}", file=file, key=prefix or "(top level)",
                         expected="a table")
    for k in table:
        if k not in allowed:
            hint = did_you_mean(k, allowed)
            raise InputError(f"unknown key{hint}", file=file, key=join(prefix, k),
                             expected="one of " + ", ".join(sorted(allowed)))
    for k in required:
        if k not in table:
            raise InputError("is missing", file=file, key=join(prefix, k), expected="a value")
    return table


def a_type(value: Any) -> str:
    """`type_name` with its article: 'an array', 'a string', 'a table'."""
    name = type_name(value)
    return ("an " if name[:1] in "aeiou" else "a ") + name


def type_name(value: Any) -> str:
    """A TOML-ish name for the type of a parsed value."""
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def get_float(table: dict, key: str, default: Any = _MISSING, *, file: str, prefix: str,
              minimum: float | None = None, maximum: float | None = None, strict_min: bool = False,
              strict_max: bool = False) -> float:
    """A finite number (int or float, not bool) within optional bounds."""
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=join(prefix, key), expected="a number")
        return default
    return as_float(table[key], file=file, key=join(prefix, key), minimum=minimum, maximum=maximum,
                    strict_min=strict_min, strict_max=strict_max)


def as_float(value: Any, *, file: str, key: str, minimum: float | None = None,
             maximum: float | None = None, strict_min: bool = False, strict_max: bool = False) -> float:
    """Check one value is a finite number within bounds."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"is {a_type(value)}", file=file, key=key, expected="a number")
    try:
        v = float(value)
    except OverflowError:
        raise InputError(f"is an integer of {len(str(value))} digits", file=file, key=key,
                         expected="a number of magnitude below 1.8e308") from None
    if not math.isfinite(v):
        raise InputError(f"is {v}", file=file, key=key, expected="a finite number")
    bound = _bounds_text(minimum, maximum, strict_min, strict_max)
    if minimum is not None and (v < minimum or (strict_min and v == minimum)):
        raise InputError(f"is {value}", file=file, key=key, expected=f"a number {bound}")
    if maximum is not None and (v > maximum or (strict_max and v == maximum)):
        raise InputError(f"is {value}", file=file, key=key, expected=f"a number {bound}")
    return v


def _bounds_text(lo, hi, slo, shi) -> str:
    parts = []
    if lo is not None:
        parts.append(("> " if slo else ">= ") + f"{lo:g}")
    if hi is not None:
        parts.append(("< " if shi else "<= ") + f"{hi:g}")
    return " and ".join(parts)


def get_int(table: dict, key: str, default: Any = _MISSING, *, file: str, prefix: str,
            minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer (not bool) within optional bounds."""
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=join(prefix, key), expected="an integer")
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"is {a_type(v)}", file=file, key=join(prefix, key), expected="an integer")
    if (minimum is not None and v < minimum) or (maximum is not None and v > maximum):
        raise InputError(f"is {v}", file=file, key=join(prefix, key),
                         expected="an integer " + _bounds_text(minimum, maximum, False, False))
    return v


def get_str(table: dict, key: str, default: Any = _MISSING, *, file: str, prefix: str,
            choices: Iterable[str] | None = None) -> str:
    """A string, optionally one of `choices` (with a did-you-mean hint)."""
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=join(prefix, key), expected="a string")
        return default
    v = table[key]
    if not isinstance(v, str):
        raise InputError(f"is {a_type(v)}", file=file, key=join(prefix, key), expected="a string")
    if choices is not None:
        choices = list(choices)
        if v not in choices:
            raise InputError(f"is '{v}'{did_you_mean(v, choices)}", file=file, key=join(prefix, key),
                             expected="one of " + ", ".join(f"'{c}'" for c in choices))
    return v


def get_bool(table: dict, key: str, default: Any = _MISSING, *, file: str, prefix: str) -> bool:
    """A boolean."""
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=join(prefix, key), expected="true or false")
        return default
    v = table[key]
    if not isinstance(v, bool):
        raise InputError(f"is {a_type(v)}", file=file, key=join(prefix, key), expected="true or false")
    return v


def per_joint(table: dict, key: str, n: int, default: Any = _MISSING, *, file: str, prefix: str,
              minimum: float | None = None, maximum: float | None = None, strict_min: bool = False,
              strict_max: bool = False) -> list[float]:
    """A per-joint setting: one number for every joint, or an array of n numbers."""
    full = join(prefix, key)
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=full, expected=f"a number or {n} numbers")
        value = default
    else:
        value = table[key]
    if isinstance(value, list):
        if len(value) != n:
            raise InputError(f"has {len(value)} entries", file=file, key=full,
                             expected=f"one number or {n} numbers (one per joint)")
        return [as_float(v, file=file, key=join(full, i), minimum=minimum, maximum=maximum,
                         strict_min=strict_min, strict_max=strict_max) for i, v in enumerate(value)]
    v = as_float(value, file=file, key=full, minimum=minimum, maximum=maximum,
                 strict_min=strict_min, strict_max=strict_max)
    return [v] * n


def get_names(table: dict, key: str, default: list, *, file: str, prefix: str, choices: Iterable[str]) -> list:
    """An array of names, each one of `choices` (with a did-you-mean hint naming the bad entry)."""
    choices = list(choices)
    names = get_list(table, key, default, file=file, prefix=prefix)
    for i, k in enumerate(names):
        if not isinstance(k, str) or k not in choices:
            hint = did_you_mean(k, choices) if isinstance(k, str) else ""
            raise InputError(f"is {k!r}{hint}", file=file, key=f"{join(prefix, key)}[{i}]",
                             expected="one of " + ", ".join(choices))
    return names


def get_list(table: dict, key: str, default: Any = _MISSING, *, file: str, prefix: str,
             length: int | None = None) -> list:
    """An array, optionally of a given length."""
    full = join(prefix, key)
    if key not in table:
        if default is _MISSING:
            raise InputError("is missing", file=file, key=full, expected="an array")
        return default
    v = table[key]
    if not isinstance(v, list):
        raise InputError(f"is {a_type(v)}", file=file, key=full, expected="an array")
    if length is not None and len(v) != length:
        raise InputError(f"has {len(v)} entries", file=file, key=full, expected=f"an array of {length}")
    return v
