"""Named families of interchangeable parts (model types, integrators, funnel shapes, transformations,
approximators, design variants): each registry is the single source of a scenario key's allowed values, the CLI's
choices and the table in the docs.

Ground floor: imports nothing of ours but the error type and the did-you-mean helper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterator

from .errors import InputError
from .validate import did_you_mean


@dataclass(frozen=True)
class Entry:
    """One registered part: its name, a one-line description and the object that implements it."""

    name: str
    description: str
    obj: Any


class Registry:
    """An ordered name -> part table for one scenario key (e.g. `design.transform`)."""

    def __init__(self, kind: str, key: str):
        self.kind = kind            # what the parts are, for messages ("funnel transformation")
        self.key = key              # the scenario key whose values this registry defines
        self._entries: dict[str, Entry] = {}

    def register(self, name: str, description: str) -> Callable[[Any], Any]:
        """Decorator: register `obj` under `name` (a name is registered once)."""
        def deco(obj):
            if name in self._entries:
                raise ValueError(f"{self.kind} '{name}' registered twice")  # a programming error, not input
            self._entries[name] = Entry(name, description, obj)
            return obj
        return deco

    def add(self, name: str, description: str, obj: Any) -> None:
        """Register `obj` under `name` (the non-decorator form)."""
        self.register(name, description)(obj)

    def names(self) -> list[str]:
        """The allowed values, in registration order."""
        return list(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[Entry]:
        return iter(self._entries.values())

    def get(self, name: str, *, file: str | None = None, key: str | None = None) -> Any:
        """The part registered under `name`; an InputError naming the key, with a did-you-mean, otherwise."""
        if name not in self._entries:
            hint = did_you_mean(str(name), self._entries) if isinstance(name, str) else ""
            raise InputError(f"is {name!r}, not a known {self.kind}{hint}", file=file, key=key or self.key,
                             expected="one of " + ", ".join(self._entries))
        return self._entries[name].obj

    def describe(self, name: str) -> str:
        """The one-line description of a registered name."""
        return self._entries[name].description

    def markdown_table(self) -> str:
        """The docs' table of allowed values: | value | description |."""
        rows = [f"| `{e.name}` | {e.description} |" for e in self]
        return "\n".join([f"| `{self.key}` | meaning |", "|---|---|", *rows])
