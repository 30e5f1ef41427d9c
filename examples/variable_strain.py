"""Variable-strain segments: the default tendon arm with each segment's
strain a Legendre series of order 2 (config/robots/gvs_arm.yaml, 27
coordinates) against the same arm with one strain per section (PCS: the
file's 2 sections a segment, and 6, as many as the GVS arm integrates
over). It prints each one's tip under a tendon tension and its own weight,
the basis's coordinates, and writes a figure of the bending strain along
the arm (variable_strain.png in the working folder).

Run: python examples/variable_strain.py (from the repository, or anywhere
soft_twin_core is installed)."""

import numpy as np

from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.robot.model import find_file, model_from_dict, read_yaml_file
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.solve.constrained import basis_coordinates, make_inputs, solve_equilibrium
from soft_twin_core.solve.outputs import section_strains, state_outputs


def arm_with(sections):
    """The default arm (PCS) with ``sections`` per segment."""
    d = read_yaml_file(find_file("tendon_arm", "robots"))
    for seg in d["segments"]:
        seg["sections"] = sections
    return from_robot_model(model_from_dict(d))


u = {"tendon_y_pos": 2.0, "tendon_z_pos": 1.0}                    # N
arms = {"PCS, 2 sections a segment": arm_with(2), "PCS, 6 sections a segment": arm_with(6),
        "Legendre order 2 on 6 sections": load_mechanism("gvs_arm")}
fig_data = {}
for label, arm in arms.items():
    eq = solve_equilibrium(arm, u)
    tip = state_outputs(arm, eq.q, eq.lam, make_inputs(arm, u)).frames["tip"][:3, 3]
    n_coords = arm.tree.nv if arm.basis is None else arm.basis.shape[1]
    print(f"{label:32s} {n_coords:3d} coordinates, tip at {tip.round(4)} m")
    lengths = np.array([arm.tree.joints[j].section.length for j in arm.members[0].joints])
    s_mid = np.cumsum(lengths) - 0.5 * lengths
    fig_data[label] = (s_mid, section_strains(arm, eq.q)[:, 4], lengths)
gvs = arms["Legendre order 2 on 6 sections"]
z = basis_coordinates(gvs, solve_equilibrium(gvs, u).q)
print("its coordinates:", ", ".join(f"{n.split('/', 1)[1]} = {v:.3f}" for n, v in
                                     zip(gvs.coordinate_names, z) if n.endswith("bending_y/0")
                                     or n.endswith("bending_y/1")))

import matplotlib                                                  # noqa: E402 (only for the figure)
matplotlib.use("Agg")
import matplotlib.pyplot as plt                                    # noqa: E402

fig, ax = plt.subplots(figsize=(7, 3.5))
for (label, (s_mid, kappa, lengths)), style in zip(fig_data.items(), ("-", "--", ":")):
    edges = np.concatenate([[0.0], np.cumsum(lengths)])
    ax.stairs(kappa, edges, label=label, linewidth=1.6, linestyle=style)
# the GVS arm's continuous field: each segment's Legendre series of its coordinates
start, k = 0.0, 0
for sb in gvs.strain_bases:
    L = sum(gvs.tree.joints[j].section.length for j in sb.joints)
    x = np.linspace(0.0, 1.0, 50)
    n_modes = len(gvs.tree.joints[sb.joints[0]].section.modes)
    fields = []
    for a in range(n_modes):
        phi = sb.basis.values(a, x)
        fields.append(phi.T @ z[k:k + len(phi)])
        k += len(phi)
    ax.plot(start + L * x, fields[1], color="k", linewidth=0.8,                  # bending_y (modes: torsion, y, z)
            label="its field, order 2" if start == 0.0 else None)
    start += L
ax.set_xlabel("arc length s [m]")
ax.set_ylabel("bending strain about y [1/m]")
ax.set_title("Tendon arm under 2 N + 1 N: the strain each model carries")
ax.legend(fontsize=8)
fig.tight_layout()
fig.savefig("variable_strain.png", dpi=120)
print("wrote variable_strain.png")
