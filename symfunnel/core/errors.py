"""Errors that the CLI turns into one clear line and an exit code, never a traceback."""

from __future__ import annotations


class SymfunnelError(Exception):
    """Base class of every error symfunnel raises on purpose."""

    exit_code = 1


class InputError(SymfunnelError):
    """Bad input (a scenario, a point file, a URDF...): names the file, the key and what was expected; exit 2."""

    exit_code = 2

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None,
                 expected: str | None = None, example: str | None = None):
        self.file = file
        self.key = key
        self.expected = expected
        #: what to write instead (a few lines of TOML), printed by the CLI below the one-line message
        self.example = example
        self.reason = message
        parts = []
        if file:
            parts.append(str(file))
        if key:
            parts.append(f"key '{key}'")
        from .text import one_line
        head = one_line(": ".join(parts), 200)
        message = one_line(message, 250)
        text = f"{head}: {message}" if head else message
        if expected:
            text += f" (expected {one_line(expected, 250)})"
        super().__init__(text)

    def at(self, file: str | None = None, key: str | None = None) -> "InputError":
        """Return a copy located at `file` / `key` where this error did not know them yet."""
        return InputError(self.reason, file=self.file or file, key=self.key or key,
                          expected=self.expected, example=self.example)


class CheckFailed(SymfunnelError):
    """A verification check failed (exit 1): the run itself worked, the design did not pass."""

    exit_code = 1


class SimulationError(SymfunnelError):
    """A simulation could not proceed (wall-clock limit, integrator failure); exit 1."""

    exit_code = 1
