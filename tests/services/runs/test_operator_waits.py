"""What a run without motion capture waits for from its operator, as its status says it
(issue 45 item 3): ``waits_for`` names the answer owed (the API call is in its
description), the step says it in words, and nothing is owed once answered."""

from __future__ import annotations

from pathlib import Path

from services.runs.protocol import CalibrationRun
from services.runs.state import State
from tests.run_rig import Rig


class Watching(Rig):
    """An operator who answers only what the status says is owed, and notes it."""

    seen: dict[State, tuple[str | None, str]]
    times: dict[State, tuple[float, float | None]]

    def _changed(self, run: CalibrationRun) -> None:
        super()._changed(run)
        st = run.status
        if st.waits_for is not None and st.state not in self.seen:
            self.seen[st.state] = (st.waits_for, st.step)
            self.times[st.state] = (st.progress, st.remaining_s)
            self.play_operator(run)


def test_the_status_says_what_the_operator_owes_in_words(tmp_path: Path) -> None:
    rig = Watching(tmp_path, metrology="imu")
    rig.operator = False  # the rig's own operator answers at entry, unasked
    rig.seen, rig.times = {}, {}
    run = rig.run()
    assert run.status.state == "DONE", run.status.errors
    seen = rig.seen
    assert seen[State.MARK][0] == "continue" and seen[State.MEASURE][0] == "references"
    for _, step in seen.values():
        assert "POST" not in step and "/calibrations" not in step, step
    assert seen[State.MARK][1].startswith("mark the floor under module 1's steering axis")
    assert run.status.waits_for is None
    # at MARK the drive is still to come: not 100 % (it was), and its time is counted
    p = run.config.protocol
    progress, remaining = rig.times[State.MARK]
    assert remaining is not None and remaining >= 2 * p.rest_time + p.drive_length / 0.4
    assert progress < 0.9, (progress, remaining)
    assert rig.times[State.MEASURE][0] > progress


def test_a_drive_steered_by_the_nominal_betas_is_a_note_the_operator_sees(
    tmp_path: Path,
) -> None:
    """A gyro whose scale is 50 % off: the spins cannot be solved before the drive, which is
    steered by the nominal betas (the final solve then refuses the run, as it should).
    That was a log line only; the status's notes say it."""
    run = Rig(tmp_path, metrology="imu", gyro_scale_error=0.5).run()
    notes = run.status.notes
    assert len(notes) == 1, (notes, run.status.errors)
    assert notes[0].startswith("the straight drive is steered by the nominal betas"), notes
