"""What ``swpc serve`` imports before it listens: no scipy (a third of its imports, about
0.5 s of CPU here and 10-20 s under the test VM's emulation, paid at every start and every
restart on failure).  The solvers import it at their first use (swpc_hw.calibration)."""

from __future__ import annotations

import subprocess
import sys

from tests.service_rig import ROOT

#: the imports of services.cli.serve.run, before the socket is opened
SERVE_IMPORTS = """
import sys
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.http.edge.server import listen_socket, server
from services.runtime.runtime import Runtime
from services.store.logs import configure, event
print(sorted(m for m in sys.modules if m == "scipy" or m.startswith("scipy.")))
"""


def test_the_service_starts_without_scipy() -> None:
    out = subprocess.run(
        [sys.executable, "-c", SERVE_IMPORTS], cwd=ROOT, capture_output=True, text=True,
        timeout=120, check=True,
    )
    assert out.stdout.strip() == "[]", out.stdout
