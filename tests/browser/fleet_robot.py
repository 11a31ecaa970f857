"""One simulated robot of the fleet, in a process of its own (the fleet page's browser
test kills it): a real service runtime on its own data dir (three calibrations in its run
store, :func:`tests.services.fleet.test_fleet.robot_data`) with the real publisher, until killed.

    python -m tests.browser.fleet_robot DATA_DIR NAME K ENDPOINT
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from services.runtime.fleet import FleetPublisher
from services.runtime.runtime import Runtime
from tests.services.fleet.test_fleet import robot_data, settings


def main(data: str, name: str, k: str, endpoint: str) -> None:
    robot_data(Path(data), int(k))
    url = f"http://{name}.lab.invalid:8080/"  # where the lab would reach its console
    rt = Runtime(settings(Path(data), name, fleet_connect=[endpoint], fleet_console_url=url))
    pub = FleetPublisher.open(rt)
    print("publishing", flush=True)
    try:
        threading.Event().wait()
    finally:
        pub.close()
        rt.close()


if __name__ == "__main__":
    main(*sys.argv[1:5])
