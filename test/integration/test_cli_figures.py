"""Every figure the command line writes for the shipped scenarios (issue
31): ``soft-twin-sim statics`` and ``dynamics`` (a short run: the figures,
not the physics) of each file of config/scenarios, each PNG checked as it
is saved, with matplotlib's own bounding boxes (``get_window_extent``):

- every axis with tick labels has a label with a unit in brackets or
  parentheses (``[m]``, ``[-]``, ``(mm)``);
- no two tick labels of an axis overlap;
- no legend inside a 2-D panel covers a plotted point of that panel.

The figures are drawn, checked and not written (the CLI's own writing is
tested in test_cli.py and test_visuals.py)."""

import contextlib
import io
import os
import re

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

from matplotlib.figure import Figure  # noqa: E402

from soft_twin_core import cli  # noqa: E402

SCENARIOS = sorted(f[:-5] for f in os.listdir(os.path.join(os.path.dirname(__file__), "..", "..", "config",
                                                            "scenarios")) if f.endswith(".yaml"))
UNIT = re.compile(r"\[[^\]]*\]|\([^)]*\)")


def figure_problems(fig, where):
    """What a reader of ``fig`` would trip over (list of strings, empty: none)."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    out = []
    for ax in fig.axes:
        if not ax.get_visible() or not ax.axison:
            continue
        name = f"{where} ({ax.get_title() or ax.get_label() or 'axes'})"
        is3d = hasattr(ax, "zaxis")
        for k in ("x", "y", "z") if is3d else ("x", "y"):
            axis = getattr(ax, f"{k}axis")
            ticks = [t for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
            if not ticks:
                continue
            label = axis.get_label_text()
            if not UNIT.search(label or ""):
                out.append(f"{name}: the {k} axis label has no unit: {label!r}")
            if k == "z":
                continue
            boxes = [t.get_window_extent(r) for t in ticks]
            if any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:]):
                out.append(f"{name}: overlapping {k} tick labels")
        legend = ax.get_legend()
        if legend is not None and not is3d:
            box = legend.get_window_extent(r)
            for line in ax.get_lines():
                xy = np.asarray(line.get_xydata(), dtype=float)
                if not len(xy):
                    continue
                p = ax.transData.transform(xy)
                if np.any((p[:, 0] > box.x0) & (p[:, 0] < box.x1) & (p[:, 1] > box.y0) & (p[:, 1] < box.y1)):
                    out.append(f"{name}: the legend covers the line {line.get_label()!r}")
                    break
    return out


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_the_figures_of_every_shipped_scenario_read_well(scenario, tmp_path, monkeypatch):
    seen, problems = [], []

    def check_instead_of_saving(fig, fname, *args, **kwargs):
        name = os.path.basename(str(fname))
        if name.endswith(".png"):
            seen.append(name)
            problems.extend(figure_problems(fig, f"{scenario}: {name}"))
    monkeypatch.setattr(Figure, "savefig", check_instead_of_saving)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        codes = []
        for argv in (["statics", scenario, "--plot", str(tmp_path / "s")],
                     ["dynamics", scenario, "--duration", "0.02", "--plot", str(tmp_path / "d")]):
            try:
                codes.append(cli.main(argv))
            except SystemExit as e:
                codes.append(e.code)
    # dynamics always runs; so does statics (loose objects held by friction where the file places them),
    # but for the catheter's insertion (the base carried 100 mm, the tip round the bend) it cannot follow: exit 3
    allowed = (0, None, 3) if scenario == "catheter_in_vessel" else (0, None)
    assert codes[1] in (0, None) and codes[0] in allowed
    assert "backbone_shapes.png" in seen and "tip.png" in seen and "energies.png" in seen
    assert not problems, "\n".join(problems)


PATHS = sorted(f for f in os.listdir(os.path.join(os.path.dirname(__file__), "..", "..", "config", "paths"))
               if f.endswith(".yaml"))


def _run_checked(monkeypatch, where, argvs):
    """Run the command lines with every PNG checked instead of written:
    (the PNG names seen, the problems found, the exit codes)."""
    seen, problems, codes = [], [], []

    def check_instead_of_saving(fig, fname, *args, **kwargs):
        name = os.path.basename(str(fname))
        if name.endswith(".png"):
            seen.append(name)
            problems.extend(figure_problems(fig, f"{where}: {name}"))
    with monkeypatch.context() as mp:
        mp.setattr(Figure, "savefig", check_instead_of_saving)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            for argv in argvs:
                try:
                    codes.append(cli.main(argv))
                except SystemExit as e:
                    codes.append(e.code)
    return seen, problems, codes


@pytest.mark.parametrize("path", PATHS)
def test_the_figures_of_every_shipped_plan_read_well(path, tmp_path, monkeypatch):
    plan = os.path.join(os.path.dirname(__file__), "..", "..", "config", "paths", path)
    seen, problems, codes = _run_checked(monkeypatch, path, [["plan", plan, "--plot", str(tmp_path),
                                                              "-o", str(tmp_path / "plan")]])
    assert codes == [0] or codes == [None]
    assert {"plan_tip_path.png", "plan_actuation.png"} <= set(seen)
    assert not problems, "\n".join(problems)


def test_the_workspace_and_a_rendered_run_read_well(tmp_path, monkeypatch):
    """The workspace figure of the default arm, and the figures ``render``
    draws from a saved dynamics run (JSON)."""
    run = tmp_path / "run.json"
    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(io.StringIO()):
        assert cli.main(["dynamics", "tendon_arm_dynamics", "--duration", "0.05", "--backbone-every", "10"]) in (0, None)
    run.write_text(out.getvalue())
    seen, problems, codes = _run_checked(monkeypatch, "workspace, render", [
        ["workspace", "tendon_arm", "--samples", "20", "--limit", "5", "-o", str(tmp_path / "ws")],
        ["render", str(run), "--scenario", "tendon_arm_dynamics", "--plot", str(tmp_path / "r")]])
    assert all(c in (0, None) for c in codes), codes
    assert "workspace.png" in seen and "tip.png" in seen and "backbone_shapes.png" in seen
    assert not problems, "\n".join(problems)
