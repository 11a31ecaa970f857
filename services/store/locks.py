"""One service per data dir and per CAN channel.

* The data dir: an exclusive ``flock`` on ``<data dir>/.lock``, held while the service
  runs (the kernel drops it when the process ends, however it ends).
* The CAN channel: an abstract Unix socket named after the interface and channel, bound
  while the service runs (Linux; released with the process; nothing on disk, so it holds
  across users and units, and across ``PrivateTmp=``).  A second service, or ``swpc
  validate`` on a robot, would otherwise command the same controllers.

A lock taken by another process raises :class:`LockedError` naming what holds it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from pathlib import Path

from swpc_hw.errors import SwpcError


class LockedError(SwpcError):
    """Another process holds the data dir or the CAN channel."""


class DataDirLock:
    """The exclusive lock of a data dir (module docstring)."""

    def __init__(self, data_dir: Path) -> None:
        self.path = Path(data_dir) / ".lock"
        self._fd: int | None = None

    def acquire(self) -> DataDirLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise LockedError(
                f"{self.path.parent}: the data dir is in use by {holder} "
                "(one service per data dir)"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"swpc serve pid {os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


class ChannelLock:
    """The exclusive claim on a CAN interface and channel (module docstring)."""

    def __init__(self, interface: str, channel: str) -> None:
        self.name = f"swpc-can:{interface}:{channel}"
        self._sock: socket.socket | None = None

    def acquire(self) -> ChannelLock:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind("\0" + self.name)
        except OSError as exc:
            sock.close()
            raise LockedError(
                f"CAN {self.name.split(':', 1)[1]} is in use by another swpc process "
                f"({exc.strerror}): one service commands a bus"
            ) from None
        self._sock = sock
        return self

    def release(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
