"""The node's stepping clock (soft_twin.stepper.Stepper): a thread calling
tick() every period on the monotonic clock, re-timed by set_period, stopped
by close; a late tick is taken at once and not repeated."""

import time

import pytest

from soft_twin.stepper import Stepper


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.001)
    return True


def test_ticks_at_the_period_until_closed():
    times = []
    s = Stepper(lambda: times.append(time.monotonic()), 0.005)
    s.start()
    assert _wait(lambda: len(times) >= 101)
    s.close()
    n = len(times)
    time.sleep(0.03)
    assert len(times) == n, "ticked after close"
    # deadlines are k * period from the start: 100 periods take 0.5 s whatever each tick's jitter
    span = times[100] - times[0]
    assert 0.5 - 0.005 <= span < 0.5 + 0.1, span     # (the first tick may itself be late)
    assert s.ticks == n


def test_set_period_retimes_from_now():
    times = []
    s = Stepper(lambda: times.append(time.monotonic()), 0.002)
    s.start()
    assert _wait(lambda: len(times) >= 5)
    t_change = time.monotonic()
    s.set_period(0.05)
    assert _wait(lambda: sum(t > t_change for t in times) >= 4)
    s.close()
    # at most one tick of the old schedule can slip in after the change (it
    # may have been under way): every later one keeps the new period, the
    # first of them a period after the change (lower bounds only: a slow
    # machine makes the gaps longer, never shorter)
    new = [t for t in times if t > t_change][1:]
    assert all(t >= t_change + 0.05 - 1e-3 for t in new), [t - t_change for t in new]
    gaps = [b - a for a, b in zip(new, new[1:])]
    assert all(g >= 0.05 - 1e-3 for g in gaps), gaps
    assert s.period == 0.05


def test_a_late_tick_runs_at_once_and_is_not_repeated():
    """A tick that overruns several periods: the next runs right after it,
    then the schedule goes on from there (no burst of missed ticks: the
    node's step works out how many twin steps are due from the wall clock)."""
    times = []

    def tick():
        times.append(time.monotonic())
        if len(times) == 3:
            time.sleep(0.05)            # 10 periods late
    s = Stepper(tick, 0.005)
    s.start()
    assert _wait(lambda: len(times) >= 8)
    s.close()
    gap_after_slow = times[3] - times[2]
    assert 0.05 <= gap_after_slow < 0.05 + 0.05
    # back on schedule: 4 ticks take ~4 periods (a burst of the ~10 missed ticks would take ~0)
    assert times[7] - times[3] >= 3 * 0.005, times[3:8]


def test_bad_period_is_refused_naming_it():
    with pytest.raises(ValueError, match="period"):
        Stepper(lambda: None, 0.0)
    s = Stepper(lambda: None, 0.01)
    with pytest.raises(ValueError, match="period"):
        s.set_period(-1.0)
    s.close()                            # never started: closing is fine
