"""A soft arm on a rigid pan-tilt unit (a tree robot file): the equilibrium
under joint commands and a tendon, the efforts the joints hold, the
stability of the equilibrium, then the pan joint swung by 0.3 rad in the
dynamics.

Run: python examples/tree_robot.py"""

from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
from soft_twin_core.solve.outputs import state_outputs

arm = load_mechanism("pan_tilt_arm")
eq = solve_equilibrium(arm, {"tendon_z_pos": 2.0}, positions={"pan": 0.4, "tilt": -0.3})
out = state_outputs(arm, eq.q, eq.lam, eq.inputs)
print(f"equilibrium: tool at {out.frames['tool'][:3, 3].round(4)} m; joint efforts "
      f"{ {k: round(v, 4) for k, v in eq.joint_efforts.items()} } N m; stable: {eq.stable} "
      f"(smallest reduced stiffness eigenvalue {eq.min_stiffness_eigenvalue:.3g})")
sim = MechanismSimulator(arm, dt=2e-3, q=eq.q)
for k in range(1, 6):
    sim.step({"tendon_z_pos": 2.0}, positions={"pan": 0.4 + 0.3 * min(1.0, k / 5), "tilt": -0.3}, n=50)
    tool = state_outputs(arm, sim.q, sim.lam, sim.inputs).frames["tool"][:3, 3]
    print(f"t = {sim.t:.2f} s: pan {0.4 + 0.3 * min(1.0, k / 5):.2f} rad, tool at {tool.round(4)} m, "
          f"pan effort {sim.joint_efforts()['pan']:+.4f} N m")
