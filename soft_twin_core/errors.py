"""Every exception type of soft_twin_core, in one place (the ground floor:
this module imports nothing of the package).

Input errors (a file, a field, an option: the message names it) derive from
ValueError; solver failures (the physics did not converge: the message says
how far it got) from RuntimeError. A command-line front end maps the first
to exit code 2 and the second to exit code 3.
"""


# --- input errors: a bad file, field or option ---------------------------------

class ModelError(ValueError):
    """A robot description is invalid; the message names the field and value."""


class InputError(ValueError):
    """A rejected input of the twin (a command, a wrench, a query). ``reason``
    is one of :data:`soft_twin_core.commands.REJECT_REASONS`."""

    def __init__(self, reason, message):
        super().__init__(message)
        self.reason = reason


class ScenarioError(ValueError):
    """A scenario file is invalid; the message names the field."""


class PathError(ValueError):
    """A bad path field; the message names it."""


class PlanError(ValueError):
    """A bad planner option; the message names it."""


class PlanFileError(ValueError):
    """A bad plan file field; the message names it."""


class CalibrationError(ValueError):
    """A bad calibration input (data file, parameter name); the message names it."""


class StudyError(ValueError):
    """A study file is invalid; the message names the field."""


class CaseValidationError(StudyError):
    """Some cases of a study are invalid: ``errors`` is a list of
    (case index, message) pairs, the message naming the field."""

    def __init__(self, errors, n_cases):
        self.errors = list(errors)
        self.n_cases = n_cases
        lines = [f"case {i}: {msg}" for i, msg in self.errors[:20]]
        if len(self.errors) > 20:
            lines.append(f"... and {len(self.errors) - 20} more")
        super().__init__(f"{len(self.errors)} of {n_cases} cases are invalid (nothing was run):\n  "
                         + "\n  ".join(lines))


# --- solver failures: the physics did not converge -----------------------------

class StaticsError(RuntimeError):
    """The equilibrium solver did not converge; the message says why."""


class StepError(RuntimeError):
    """A constrained step did not converge; the state is left unchanged."""


class ContinuumConvergenceError(RuntimeError):
    """The shooting/continuation did not converge."""


class CalibrationFailed(RuntimeError):
    """A simulation of the recording failed (a time step did not converge)."""


class StudyInterrupted(RuntimeError):
    """The study stopped before every case was computed (Ctrl-C); the rows
    computed so far are saved and a rerun resumes."""
