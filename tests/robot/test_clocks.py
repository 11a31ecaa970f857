"""The clocks (swpc_hw/clock.py): the lockstep master's schedule, wall stamps, virtual time."""

from __future__ import annotations

import collections
import threading
import time
import uuid

import pytest

from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import COINCIDENT_S, SimClock, VirtualClock, next_instant


def test_next_instant_merges_coincident_instants_and_skips_what_is_due() -> None:
    t = 10.0
    # the earliest, moved on to a candidate within a microsecond after it
    assert next_instant(t, [t + 0.005, t + 0.005 - 3e-7, t + 0.02]) == t + 0.005
    assert next_instant(t, [t + 0.005 + 2e-7, t + 0.005]) == t + 0.005 + 2e-7
    # not merged when further apart
    assert next_instant(t, [t + 0.005, t + 0.005 + 10 * COINCIDENT_S]) == t + 0.005
    # already due (a controller that sent its frame at t): the next step, not a tiny one
    assert next_instant(t, [t, t + 1e-7, t + 0.005]) == t + 0.005
    assert next_instant(t, [t - 1.0]) > t  # time always moves on


def test_sim_clock_wall_stamps_round_trip_exactly_whatever_the_epoch() -> None:
    """Times live on the wall-stamp grid, so a frame stamped ``wall()`` maps back to
    ``now()`` exactly, and two runs with different epochs see the same times (the same
    seed gives the same run, bit for bit)."""
    times = []
    for epoch in (1.7e9, 1.76e9 + 12345.0):
        clock = SimClock(epoch=epoch)
        stop = threading.Event()
        seen = []

        def master(clock: SimClock = clock, stop: threading.Event = stop) -> None:
            while not stop.is_set():
                if clock.wait_for_demand(stop):
                    clock.advance_to(clock.now() + 0.005, stop)

        th = threading.Thread(target=master, daemon=True)
        th.start()
        with clock.participant():
            for _ in range(50):
                clock.sleep(0.0137)
                assert clock.from_wall(clock.wall()) == clock.now()
                seen.append(clock.now())
        stop.set()
        clock.close()
        th.join(2.0)
        times.append(seen)
    assert times[0] == times[1]


def master_steps(wait: str) -> tuple[list[float], list[tuple[float, float]]]:
    """A master on a 10 ms grid (next_instant, as the simulator's) and a participant that
    waits 13 ms at a time with ``clock.<wait>``: the master's steps and, per wait, (asked,
    woken)."""
    clock = SimClock()
    stop = threading.Event()
    steps: list[float] = []

    def master() -> None:
        while not stop.is_set():
            if clock.wait_for_demand(stop):
                t = clock.now()
                t_next = next_instant(t, [t + 0.01, clock.next_wake()])
                clock.advance_to(t_next, stop)
                steps.append(clock.now())

    th = threading.Thread(target=master, daemon=True)
    th.start()
    waits = []
    with clock.participant():
        for _ in range(20):
            asked = clock.now() + 0.013
            getattr(clock, wait)(0.013)
            waits.append((asked, clock.now()))
    stop.set()
    clock.close()
    th.join(2.0)
    return steps, waits


def test_a_poll_wakes_at_the_masters_next_step_and_asks_for_none() -> None:
    """``Clock.poll``, a polling loop's wait: a sleep out of phase with the master's grid
    is a step of its own (the run's 20 ms looks split a third of the simulator's 10 ms
    physics steps in two); a poll ends at the first step at or after its time."""
    steps, waits = master_steps("sleep")
    assert all(woken == pytest.approx(asked, abs=1e-6) for asked, woken in waits)
    off_grid = [t for t in steps if abs(t / 0.01 - round(t / 0.01)) > 1e-3]
    assert len(off_grid) >= 15  # the sleeps' own steps
    steps, waits = master_steps("poll")
    assert all(abs(t / 0.01 - round(t / 0.01)) < 1e-3 for t in steps)  # the grid alone
    for asked, woken in waits:
        assert asked - 1e-6 <= woken < asked + 0.01 + 1e-6  # at most one step late


def test_a_paced_sim_clock_flows_when_no_one_waits_and_an_unpaced_one_stands_still() -> None:
    """Unpaced (as fast as the host can), an idle simulation costs nothing: time stands
    still until someone waits on it.  Paced (``make console``: 1 simulated s per wall s),
    it flows as a robot's time does: an idle console's robot sent no pose while nothing
    waited, and a service whose first pose came after its start-up's last wait stayed
    "motion capture stale" (make console, on a loaded host)."""
    stop = threading.Event()
    idle = SimClock()
    t0 = time.monotonic()
    assert not idle.wait_for_demand(stop, timeout=0.05) and not idle.demanded()
    assert time.monotonic() - t0 >= 0.04  # it waited for a demand
    paced = SimClock(max_speed=20.0)
    assert paced.demanded()
    t0 = time.monotonic()
    for _ in range(10):  # the master's loop, nobody else on the clock
        assert paced.wait_for_demand(stop)
        paced.advance_to(paced.now() + 0.05, stop)
    wall = time.monotonic() - t0
    assert paced.now() == pytest.approx(0.5, abs=1e-4)  # (on the wall stamps' grid)
    assert wall >= 0.45 / 20.0  # at the paced rate, not faster
    idle.close()
    paced.close()


def test_virtual_clock_moves_only_when_slept_on_and_runs_its_world() -> None:
    clock = VirtualClock(start=3.0, epoch=100.0)
    calls: list[float] = []
    clock.on_sleep.append(calls.append)
    assert clock.now() == 3.0 and clock.wall() == 103.0 and clock.from_wall(104.5) == 4.5
    clock.sleep(0.25)
    clock.sleep_until(4.0)
    clock.sleep_until(1.0)  # the past: no step
    assert clock.now() == 4.0 and calls == [3.25, 4.0]


@pytest.mark.parametrize("wake", [0.02, 0.0137])
def test_the_simulator_in_lockstep_takes_only_whole_ticks(wake: float) -> None:
    """A participant waking every ``wake`` s beside the simulator's 5 ms ticks: no step
    is a sliver between two instants that only rounding set apart (a fifth of the steps
    were, 1e-8 to 1e-6 s, each costing a whole tick); with wake-ups on the tick grid every
    step is a whole tick."""
    clock = SimClock()
    sim = VirtualRobot.open(
        interface="virtual",
        channel=f"ticks-{uuid.uuid4().hex[:8]}",
        options=SimOptions(physics_dt=0.005),
        clock=clock,
    )
    steps: collections.Counter[float] = collections.Counter()
    tick = sim._tick

    def counted(dt: float, t_end: float | None = None) -> None:
        steps[round(dt * 1e5) / 1e5] += 1  # 10 us bins
        tick(dt, t_end=t_end)

    sim._tick = counted  # type: ignore[method-assign]
    sim.start()
    try:
        with clock.participant():
            for _ in range(int(1.0 / wake)):
                clock.sleep(wake)
    finally:
        sim.stop()
        clock.close()
    assert sum(steps.values()) >= 1.0 / 0.005
    if wake == 0.02:
        assert set(steps) == {0.005}, steps
    else:  # wake-ups cut ticks, at 0.1 ms at least here, never at rounding's scale
        assert min(steps) >= 1e-4, steps
