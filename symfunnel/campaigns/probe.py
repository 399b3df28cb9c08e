"""A dask scheduler recognised by its handshake before `distributed.Client` is trusted with the address: a server
that never answers hung the client past its timeout, and one that sends junk made it allocate what the junk
claimed (a MemoryError of 2.82 EiB)."""

from __future__ import annotations


#: the largest handshake a dask scheduler sends on connecting (a few hundred bytes in practice)
MAX_HANDSHAKE_BYTES = 1 << 20


def probe_scheduler(host: str, port: int, timeout: float) -> str | None:
    """Connect and read the handshake a dask scheduler sends first, within `timeout` s in all: None when it is one
    (distributed's TCP framing: total length, frame count, frame lengths, frames, all consistent), else why not.
    OSError when the connection itself fails."""
    import socket
    import struct
    import time
    end = time.monotonic() + timeout
    with socket.create_connection((host, port), timeout=timeout) as c:
        def read(k: int) -> bytes:
            data = b""
            while len(data) < k:
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                c.settimeout(left)
                chunk = c.recv(k - len(data))
                if not chunk:
                    raise ConnectionError
                data += chunk
            return data
        try:
            total = struct.unpack("<Q", read(8))[0]
            if not 16 <= total <= MAX_HANDSHAKE_BYTES:
                return f"its first message claims {total} bytes (a dask handshake is a few hundred)"
            body = read(total)
            n = struct.unpack("<Q", body[:8])[0]
            lengths = struct.unpack(f"<{n}Q", body[8:8 + 8 * n]) if 8 + 8 * n <= total else None
            if lengths is None or 8 + 8 * n + sum(lengths) != total:
                return "its first message is not dask's framing"
        except (TimeoutError, socket.timeout):
            return f"no handshake within {timeout:g} s"
        except ConnectionError:
            return "it closed the connection without a handshake"
    return None
