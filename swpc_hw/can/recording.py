"""Recording CAN traffic (python-can's Logger, candump format for ``.log``) and the
kernel receive buffer of socket buses."""

from __future__ import annotations

import logging
import socket
import threading

import can

log = logging.getLogger(__name__)

SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux; not in Python's socket


class Recorder:
    """python-can's Logger shared by the receive path and the senders (thread-safe)."""

    def __init__(self, path: str, lock: threading.Lock | None = None) -> None:
        self.logger = can.Logger(path)
        self.lock = lock or threading.Lock()
        self.closed = False

    def write(self, msg: can.Message) -> None:
        with self.lock:
            if not self.closed:  # a frame racing with stop() is dropped, not an error
                self.logger.on_message_received(msg)

    def stop(self) -> None:
        with self.lock:
            if not self.closed:
                self.closed = True
                self.logger.stop()


def grow_receive_buffer(sock: socket.socket, size: int) -> int:
    """Ask the kernel for a ``size``-byte receive buffer on ``sock``; returns the one in effect.

    SO_RCVBUFFORCE (CAP_NET_ADMIN) may exceed net.core.rmem_max; without the capability
    SO_RCVBUF is capped at rmem_max.  Linux doubles the value asked (bookkeeping overhead),
    and a CAN frame's buffer costs several hundred bytes of it.
    """
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, size)
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
    got = int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    if got < size:
        log.warning(
            "CAN receive buffer %d bytes, asked %d: raise net.core.rmem_max "
            "(deploy/sysctl/60-swpc-can.conf) or grant CAP_NET_ADMIN",
            got,
            size,
        )
    return got
