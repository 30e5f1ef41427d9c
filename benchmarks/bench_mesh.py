"""A mesh obstacle's cost: the signed distance of a point through the mesh's
bounding-box tree against every triangle searched, as the mesh grows.

The mesh: a bumpy sphere (test/unit/test_contact.py ``bumpy_sphere``: not
convex, radius 50 mm +- 30 %), 8 4^k triangles. The points: 2000 within a
few millimetres of its surface (where contact points are when they touch),
half inside. Reported per point: the tree (4 triangles a leaf,
``engine.kernels.contact.MESH_LEAF``), every triangle (one leaf), and their
ratio; the tree's build (once per obstacle set, when the arrays are made);
and a figure of both against the triangles (``--out``, docs/figures/mesh_distance.png).

Run: PYTHONPATH=.:test/unit .venv/bin/python benchmarks/bench_mesh.py [--levels 2 3 4 5 6] [--out FILE.png]
"""

import argparse
import os
import time

import numpy as np

from _timing import fmt, machine, per_call
from soft_twin_core.engine.kernels import contact as kc
from soft_twin_core.robot.obstacles import obstacle_from_dict
from test_contact import bumpy_sphere


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--out", default="docs/figures/mesh_distance.png", help="the figure ('' for none)")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    print(f"# {machine()}, load {load:.2f} (1 min) on {os.cpu_count()} CPUs")
    print(f"{'triangles':>9} {'tree':>12} {'every one':>12} {'ratio':>7} {'build':>10}")
    rng = np.random.default_rng(1)
    rows = []
    for k in args.levels:
        V, F = bumpy_sphere(k)
        ob = obstacle_from_dict({"name": "rock", "type": "mesh", "vertices": V.tolist(), "faces": F.tolist()}, "r")
        u = rng.standard_normal((2000, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        theta, phi = np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])
        r = 0.05 * (1 + 0.3 * np.sin(3 * theta) * np.cos(2 * phi)) + rng.uniform(-0.003, 0.003, 2000)
        P = np.ascontiguousarray(u * r[:, None] + ob.a)
        d, n, H = np.empty(len(P)), np.empty((len(P), 3)), np.empty((len(P), 3, 3))
        times = []
        t0 = time.perf_counter()
        kc._obstacle_arrays.cache_clear()
        tree = kc.obstacle_arrays((ob,))
        build = time.perf_counter() - t0
        for arrays in (tree, kc.obstacle_arrays((ob,), len(ob.triangles))):
            kc.distance_arrays(arrays, 0, P, d, n, H)
            times.append(per_call(lambda: kc.distance_arrays(arrays, 0, P, d, n, H), repeat=3) / len(P))
        print(f"{len(ob.triangles):>9} {fmt(times[0]):>12} {fmt(times[1]):>12} {times[1] / times[0]:>6.0f}x "
              f"{fmt(build):>10}")
        rows.append((len(ob.triangles), *times))
    if args.out:
        plot(np.array(rows), args.out, load)


def plot(rows, out, load):
    """Time a point against the mesh's triangles, log-log, both searches."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.2), layout="constrained")
    ax.loglog(rows[:, 0], 1e6 * rows[:, 1], "o-", label="the mesh's box tree (4 triangles a leaf)")
    ax.loglog(rows[:, 0], 1e6 * rows[:, 2], "s-", label="every triangle")
    ax.set_xlabel("triangles of the mesh")
    ax.set_ylabel("signed distance of a point [us]")
    ax.set_title(f"A point near a bumpy sphere (not convex), load {load:.1f} on 2 cores", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"figure: {out}")


if __name__ == "__main__":
    main()
