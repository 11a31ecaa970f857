"""Fixtures shared by the suite (plain helpers: tests/service_rig.py, tests/run_rig.py,
tests/can_rig.py, tests/fake_robot.py).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.service_rig import (
    Sim,
    sim_service,
)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sim]:
    with sim_service(tmp_path_factory.mktemp("sim")) as s:
        yield s
