"""The dynamic mode's step schedule (pure arithmetic, no ROS, no clock).

Twin step k is due at wall time ``anchor + k dt`` (``anchor``: the monotonic
time of step 0, set when the first step is taken). The stepping clock takes
the steps due at its tick; an input may take the next step early (when
``step_on_command`` is on) as long as twin time never leads wall time by more
than one step; an input callback that finds the clock more than two periods
late catches up instead. ``steps_done`` counts the steps taken (or dropped)
since the anchor.
"""


def steps_due(now, anchor, dt, steps_done, early=False):
    """How many steps are due at monotonic time ``now`` [s] (<= 0: none).
    ``early``: step k may start as soon as step k - 1 is due."""
    if early:
        return int((now - anchor) / dt) + 1 - steps_done
    return int(round((now - anchor) / dt)) - steps_done


def clock_late(now, anchor, dt, steps_done):
    """Is the next step more than two periods past its tick? (False before the first step.)"""
    if anchor is None:
        return False
    return (now - anchor) / dt - steps_done > 2.0


def may_step_early(now, anchor, dt, steps_done):
    """May an input take the next step now? Only while twin time does not
    already lead wall time (so the step rate is kept)."""
    if anchor is None:
        return False
    return int((now - anchor) / dt) + 1 > steps_done


def catch_up(due, max_catchup_steps):
    """(steps to take, steps to drop) of ``due`` steps: a backlog beyond
    ``max_catchup_steps`` is dropped, so that twin time does not race to catch up."""
    if due > max_catchup_steps:
        return max_catchup_steps, due - max_catchup_steps
    return due, 0
