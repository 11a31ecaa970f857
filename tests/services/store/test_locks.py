"""One service per data dir and per CAN channel (services/store/locks.py): a second one stops
before touching anything, and lets go when it ends.
"""

from __future__ import annotations

import math
import uuid
from pathlib import Path

import pytest
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.runtime.runtime import Runtime
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.service_rig import TOKEN


def test_a_second_service_on_the_data_dir_stops_before_touching_it(tmp_path: Path) -> None:
    from services.store.locks import ChannelLock, LockedError

    first = Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
    try:
        first.store.upsert("live1", "2026-01-01T00:00:00Z", {"id": "live1", "state": "SPIN"})
        with pytest.raises(LockedError, match="in use by swpc serve pid"):
            Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
        got = first.store.get("live1")
        assert got is not None and got[0]["state"] == "SPIN"  # the first one's run: untouched
        lock = ChannelLock("socketcan", "can7").acquire()
        try:
            with pytest.raises(LockedError, match="socketcan:can7 is in use"):
                ChannelLock("socketcan", "can7").acquire()
        finally:
            lock.release()
        ChannelLock("socketcan", "can7").acquire().release()  # free again
    finally:
        first.close()
    Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN))).close()  # released


def test_a_second_runtime_on_the_can_channel_stops_and_lets_go(tmp_path: Path) -> None:
    """Two services, one bus: the second one's Runtime.open() stops at the channel's lock
    and gives back what it took (its data dir's lock)."""
    from services.store.locks import LockedError

    channel = f"swpc-lock-{uuid.uuid4().hex[:8]}"

    def runtime(name: str) -> Runtime:
        return Runtime(
            ServiceSettings(
                data_dir=tmp_path / name,
                token=SecretStr(TOKEN),
                can_interface="virtual",
                can_channel=channel,
                zenoh_listen=[free_tcp_endpoint()],
            )
        )

    first = runtime("a").open()
    try:
        with pytest.raises(LockedError, match=f"CAN virtual:{channel} is in use"):
            runtime("b").open()
        runtime("b").close()  # its data dir is free again
    finally:
        first.close()
    second = runtime("b").open()  # the channel too, once the first has stopped
    assert second.drives is not None and math.isfinite(second.clock.now())
    second.close()
