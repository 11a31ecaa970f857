"""Recording CAN traffic (python-can's Logger, candump format for ``.log``) and the
kernel receive buffer of socket buses.

A :class:`Recorder` with ``total_bytes`` is a bounded rolling log: python-can's
:class:`can.SizedRotatingLogger` starts a new file every ``total_bytes / ROLLING_FILES``
bytes, and its rotator deletes the oldest rotated files of the same base name so that all
of them together stay within ``total_bytes`` (across restarts: the base file is appended
to).  A write that fails (a full disk) stops the recorder, or pauses the rolling log
until it can write again, and keeps the reason in :attr:`Recorder.error`; the traffic
itself is never affected.

A recorder with a ``sample_period_s`` keeps, of the frames written with ``sample=True``
(the driver's rolling log between recordings: an idle robot), only what
:class:`IdleSampler` keeps: the periodic traffic (heartbeats, encoder feedback, any other
device's frames) once per period per CAN id, every event (a host command, a fault report,
a homing status, an error frame, a heartbeat whose content changed) at once.  An idle
4-module robot at 200 Hz feedback sends ~1 650 frames a second, 100 kB/s of candump
lines, 360 MB an hour written to the robot's flash for the rolling log to forget; at one
per second per id it is 12 frames a second.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can

from firmware_protocol import codec

log = logging.getLogger(__name__)

SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux; not in Python's socket


ROLLING_FILES = 8
"""A rolling log is kept in about this many files (the newest one being written)."""


def rolling_files(base: str | os.PathLike[str]) -> list[Path]:
    """The rotated files of the rolling log ``base`` (``<stem>_<time>_#<n><suffix>``),
    oldest first."""
    p = Path(base)
    files = [f for f in p.parent.glob(f"{p.stem.split('.')[0]}_*{p.suffix}") if f.is_file()]
    return sorted(files, key=lambda f: (f.stat().st_mtime, f.name))


SIZE_CHECK_EVERY = 64
"""Frames between two looks at the file's size (a text file's ``tell()`` is slow)."""


class _SizedRotatingLogger(can.SizedRotatingLogger):
    """python-can's :class:`can.SizedRotatingLogger`, which asks the file its size
    (``TextIOWrapper.tell()``, the slowest part of writing a frame: 4 % of a whole
    calibration's CPU in the suite) only every :data:`SIZE_CHECK_EVERY` frames: a file
    may end that many candump lines past ``max_bytes`` (:func:`rolling_logger` leaves
    room for them)."""

    _unchecked = 0

    def should_rollover(self, msg: can.Message) -> bool:
        self._unchecked += 1
        if self._unchecked < SIZE_CHECK_EVERY:
            return False
        self._unchecked = 0
        return bool(super().should_rollover(msg))


def rolling_logger(base: str, total_bytes: int) -> can.SizedRotatingLogger:
    """python-can's sized rotating logger on ``base`` whose files stay within
    ``total_bytes`` all together (module docstring)."""
    per_file = max(64 << 10, total_bytes // ROLLING_FILES)
    # a file may end SIZE_CHECK_EVERY lines (at most 160 bytes: CAN FD) past max_bytes
    logger = _SizedRotatingLogger(
        base, max_bytes=per_file - SIZE_CHECK_EVERY * 160, append=True
    )

    def rotate(source: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
        os.replace(source, dest)
        budget = total_bytes - per_file  # room for the new base file
        files = rolling_files(base)
        sizes = [f.stat().st_size for f in files]
        while files and sum(sizes) > budget:
            with contextlib.suppress(FileNotFoundError):
                files[0].unlink()
            files.pop(0)
            sizes.pop(0)

    logger.rotator = rotate
    return logger


#: frames of our protocol that are events, kept whenever they come
EVENT_COMMANDS = codec.HOST_COMMANDS | {codec.Command.FAULT_REPORT, codec.Command.HOMING_STATUS}


class IdleSampler:
    """Which frames of an idle bus a rolling log keeps (module docstring).  Time is each
    frame's own stamp (python-can's bus time), so the same frames give the same choice."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last: dict[tuple[bool, int], float] = {}
        self._heartbeat: dict[int, object] = {}

    def keep(self, msg: can.Message) -> bool:
        if self.period_s <= 0 or msg.is_error_frame:
            return True
        key = (bool(msg.is_extended_id), int(msg.arbitration_id))
        changed = False
        if not msg.is_extended_id:
            node, command = codec.split_id(msg.arbitration_id)
            if command in EVENT_COMMANDS:
                return True
            if command == codec.Command.HEARTBEAT:
                content: object = bytes(msg.data)
                with contextlib.suppress(codec.ProtocolError):
                    hb = codec.parse(msg.arbitration_id, bytes(msg.data))
                    if isinstance(hb, codec.Heartbeat):  # all but its counter
                        content = dataclasses.replace(hb, counter=0)
                changed = self._heartbeat.get(node) != content
                self._heartbeat[node] = content
        t = float(msg.timestamp)
        last = self._last.get(key)
        if changed or last is None or not last <= t < last + self.period_s:
            self._last[key] = t
            return True
        return False


class Recorder:
    """python-can's Logger shared by the receive path and the senders (thread-safe).

    ``total_bytes``: a bounded rolling log (module docstring) instead of one file;
    ``sample_period_s``: frames written with ``sample=True`` go through an
    :class:`IdleSampler` of that period (0: every frame is kept).

    ``retry_s`` > 0 (the rolling log): a failed write pauses the log instead of ending
    it; the first frame ``retry_s`` or more after (on ``now``, the driver's clock) opens
    it again, and the frames in between are counted in :attr:`lost`.  So a disk that was
    full and has room again gets its log back without a restart.
    """

    def __init__(
        self,
        path: str,
        lock: threading.Lock | None = None,
        total_bytes: int | None = None,
        sample_period_s: float = 0.0,
        retry_s: float = 0.0,
        now: Callable[[], float] | None = None,
    ) -> None:
        self.path = path
        self.total_bytes = total_bytes
        self.logger: can.Listener = self._open()
        self.lock = lock or threading.Lock()
        self.closed = False
        self.error: str | None = None
        self.sampler = IdleSampler(sample_period_s)
        self.retry_s = retry_s
        self.now = now or time.monotonic
        self.lost = 0
        """Frames not written while the log was paused (``retry_s``)."""
        self._retry_at: float | None = None
        self._stopped = False

    def _open(self) -> can.Listener:
        if self.total_bytes:
            return rolling_logger(self.path, self.total_bytes)
        return can.Logger(self.path)

    def write(self, msg: can.Message, sample: bool = False) -> None:
        with self.lock:
            if self.closed and not self._resumed():
                if self._retry_at is not None:
                    self.lost += 1
                return  # (a frame racing with stop() is dropped, not an error)
            if sample and not self.sampler.keep(msg):
                return
            try:
                self.logger.on_message_received(msg)
            except (OSError, ValueError) as exc:
                self._failed(exc)

    def _failed(self, exc: Exception) -> None:
        """(lock held) A write failed: the log stops, or pauses until ``retry_s`` later."""
        self.error = f"{self.path}: {getattr(exc, 'strerror', None) or exc}"
        self.closed = True
        with contextlib.suppress(Exception):
            self.logger.stop()
        if self.retry_s > 0:
            self._retry_at = self.now() + self.retry_s
            log.error("CAN log paused: %s (tried again every %.0f s)", self.error, self.retry_s)
        else:
            log.error("CAN recording stopped: %s", self.error)

    def _resumed(self) -> bool:
        """(lock held) Open the paused log again if its retry is due; True once it is."""
        if self._stopped or self._retry_at is None or self.now() < self._retry_at:
            return False
        try:
            self.logger = self._open()
        except OSError as exc:
            self.error = f"{self.path}: {exc.strerror or exc}"
            self._retry_at = self.now() + self.retry_s
            return False
        log.warning("CAN log resumed: %s (%d frames lost while paused)", self.path, self.lost)
        self.closed, self.error, self._retry_at = False, None, None
        return True

    def stop(self) -> None:
        with self.lock:
            self._stopped = True
            if not self.closed:
                self.closed = True
                try:
                    self.logger.stop()
                except OSError as exc:
                    self.error = f"{self.path}: {exc.strerror or exc}"


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
