"""Fixtures shared by the suite (plain helpers: tests/service_rig.py, tests/run_rig.py,
tests/can_rig.py, tests/fake_robot.py).

The services the tests open answer to the name FastAPI's TestClient sends
(``testserver``), as a lab would list its own names in ``SWPC_ALLOWED_HOSTS``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator

import pytest

from tests.service_rig import Sim, sim_service

os.environ.setdefault("SWPC_ALLOWED_HOSTS", '["testserver"]')


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sim]:
    with sim_service(tmp_path_factory.mktemp("sim")) as s:
        yield s


@pytest.fixture(autouse=True)
def log_state() -> Iterator[None]:
    """``swpc serve`` configures logging (services/store/logs.py: a handler on the root
    logger, the levels of ``swpc`` and ``uvicorn``): put it back as it was for the tests
    after one that ran it in this process."""
    loggers = [logging.getLogger(n) for n in ("", "swpc", "uvicorn")]
    saved = [(list(lg.handlers), lg.level, lg.propagate) for lg in loggers]
    yield
    for lg, (handlers, level, propagate) in zip(loggers, saved, strict=True):
        lg.handlers[:] = handlers
        lg.setLevel(level)
        lg.propagate = propagate
