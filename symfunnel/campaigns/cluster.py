"""A dask.distributed cluster for `symfunnel sweep --scheduler`: the address checked, the server probed before
dask's Client is made (a silent or foreign server is one line, not a hang), and workers waited for.
"""

from __future__ import annotations

from ..core.errors import InputError

__all__ = ["connect"]


def connect(address: str, timeout: float = 10.0, worker_timeout: float = 30.0):
    """A dask.distributed client of a running scheduler with workers; InputError naming the address otherwise."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a regular dependency
        raise InputError("needs the 'distributed' package", key="--scheduler",
                         expected="pip install distributed") from None
    host, port = _scheduler_address(address)
    try:                        # a plain connection first: a failed Client leaves a finalizer that hangs and prints
        from .probe import probe_scheduler
        why = probe_scheduler(host, port, timeout)
    except OSError as exc:
        raise InputError(f"cannot reach the scheduler at {address} ({exc.strerror or type(exc).__name__})",
                         key="--scheduler", expected="the address of a running dask scheduler (tcp://HOST:PORT)") \
            from None
    if why is not None:         # a server that never answers hung Client past its timeout; junk was a MemoryError
        raise InputError(f"is no dask scheduler at {address}: {why}", key="--scheduler",
                         expected="the address of a running dask scheduler (tcp://HOST:PORT)")
    try:
        client = Client(address, timeout=f"{timeout:g}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"cannot reach the scheduler at {address} ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else 'no answer'})", key="--scheduler",
                         expected="the address of a running dask scheduler (tcp://HOST:PORT)") from None
    try:
        client.wait_for_workers(1, timeout=worker_timeout)
    except (TimeoutError, OSError):
        client.close()
        raise InputError(f"the scheduler at {address} has no workers (waited {worker_timeout:g} s)",
                         key="--scheduler", expected="a scheduler with `dask worker` processes attached") from None
    return client


def _scheduler_address(address) -> tuple[str, int]:
    """(host, port) of a tcp://HOST:PORT address; InputError naming --scheduler otherwise."""
    from urllib.parse import urlsplit
    expected = "a dask scheduler address tcp://HOST:PORT"
    if not isinstance(address, str) or "://" not in address:
        raise InputError(f"is '{address}'", key="--scheduler", expected=expected)
    u = urlsplit(address)
    if u.scheme == "tls":
        raise InputError(f"is '{address}': a tls:// scheduler needs certificates, which symfunnel does not "
                         "configure", key="--scheduler", expected=expected + " (or a tcp:// tunnel)")
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme != "tcp" or not u.hostname or port is None or u.path not in ("", "/") or u.query:
        raise InputError(f"is '{address}'", key="--scheduler", expected=expected)
    return u.hostname, port
