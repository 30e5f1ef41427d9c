"""The default tendon arm (a classic rod: a one-member mechanism): its
equilibrium under a tendon tension and a tip load, its backbone and the
support's reaction, then one second of its dynamics from rest. The same
calls take a tree robot (examples/tree_robot.py).

Run: python examples/statics_and_dynamics.py (from the repository, or anywhere
soft_twin_core is installed)."""

from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.solve.constrained import FrameLoad, MechanismSimulator, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs

arm = load_mechanism("tendon_arm")
tip_load = FrameLoad("tip", [0.0, 0.0, -0.05, 0.0, 0.0, 0.0], "world")          # 50 mN down, world axes
eq = solve_equilibrium(arm, {"tendon_y_pos": 2.0}, point_loads=[tip_load])
out = state_outputs(arm, eq.q, eq.lam, eq.inputs, points_per_section=10)
backbone = out.members[0].poses                                               # (N, 4, 4) world poses
print(f"equilibrium: tip at {out.frames['tip'][:3, 3].round(4)} m after {eq.iterations} Newton steps, "
      f"stable: {eq.stable}, {len(backbone)} backbone poses, support reaction {out.base_wrench[:3].round(4)} N")
sim = MechanismSimulator(arm, dt=1e-3)
sim.step({"tendon_y_pos": 2.0}, n=1000)
tip = state_outputs(arm, sim.q, sim.lam, sim.inputs).frames["tip"][:3, 3]
print(f"dynamics: after {sim.t:.2f} s from rest the tip is at {tip.round(4)} m "
      f"({1e3 * abs(tip - out.frames['tip'][:3, 3]).max():.1f} mm from the loaded equilibrium: no tip load here)")
