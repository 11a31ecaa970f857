"""The run's solver plot (``GET /calibrations/{id}/plot.png``, services.runs.plots): what it
draws is what the run measured.  A calibration without motion capture has no poses: its
plot was three panels, two of them empty, under a title promising fixed points."""

from __future__ import annotations

import struct
from pathlib import Path

from services.runs.plots import calibration_plot
from swpc_hw.files.dataset import load_dataset
from tests.run_rig import Rig


def png_size(png: bytes) -> tuple[int, int]:
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", png[16:24])
    return int(w), int(h)


def test_the_plot_has_the_pose_panels_only_when_there_are_poses(tmp_path: Path) -> None:
    sizes = {}
    for metrology in ("mocap", "imu"):
        run = Rig(tmp_path / metrology, metrology=metrology).run()
        assert run.status.state == "DONE", run.status.errors
        assert run.result is not None
        ds = load_dataset(run.run_dir / "dataset")
        sizes[metrology] = png_size(calibration_plot(ds, run.result))
        assert (ds.poses.shape[0] > 0) == (metrology == "mocap")
    # 16 x 5.2 in at 90 dpi: three panels; 6.4 x 5.2 in: the robot frame alone
    assert sizes == {"mocap": (1440, 468), "imu": (576, 468)}
