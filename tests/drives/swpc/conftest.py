"""Fixtures of the driver's back-to-back tests (:mod:`tests.drives.swpc.back_to_back_rig`)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.drives.swpc.back_to_back_rig import Rig, make_rig


@pytest.fixture
def rig() -> Iterator[Rig]:
    yield from make_rig()


@pytest.fixture
def active(rig: Rig) -> Rig:
    rig.drv.configure()
    rig.drv.activate()
    return rig
