"""The default tendon arm: its equilibrium under a tendon tension and a tip
load, its backbone, and one second of its dynamics from rest.

Run: python examples/statics_and_dynamics.py (from the repository, or anywhere
soft_twin_core is installed)."""

from soft_twin_core import dynamics as dy
from soft_twin_core import kinematics as kin
from soft_twin_core import loads as ld
from soft_twin_core import statics as st
from soft_twin_core.model import load_model

model = load_model("tendon_arm")
eq = st.solve_statics(model, {"tendon_y_pos": 2.0}, ld.Loads(point=(ld.tip_load(model, force=(0, 0, -0.05)),)))
s, poses = kin.backbone(model, eq.q, points_per_section=10)
print(f"equilibrium: tip at {poses[-1][:3, 3].round(4)} m after {eq.iterations} Newton steps, "
      f"stable: {eq.stable}, support reaction {eq.base_wrench_world[:3].round(4)} N")
sim = dy.Simulator(model, dt=1e-3, actuation={"tendon_y_pos": 2.0})
sim.step(1000)
tip = kin.tip_pose(model, sim.state.q)[:3, 3]
print(f"dynamics: after {sim.state.t:.2f} s from rest the tip is at {tip.round(4)} m "
      f"({1e3 * abs(tip - poses[-1][:3, 3]).max():.1f} mm from the loaded equilibrium: no tip load here)")
