"""fj.LinearTracking on the medium-voltage three-level converter on an RL grid (``firhc_jax.models.grid_converter``):
node counts of its two paths, and time against a sphere decoder, on the same closed-loop decisions.

The decisions: ``--steps`` closed-loop steps through the 0.2 -> 1 pu current step, ``lt.solve`` deciding,
each warm-started with the previous plan shifted by one step (its last input repeated), float64.

Sections (each prints a table):

* nodes: per N, the nodes of ``lt.solve`` (``shared_problem``, the model in the params) and of ``fj.sdfs`` on
  ``lt.problem`` (the model as constants) on every decision, and whether they are equal step by step (they
  must be: one search). ``tests/test_converter_nodes.py`` holds the N = 5 and 10 means as recorded here.
* peer: per N, each decision solved by ``lt.solve`` (eager, compiled first) and by the scalar Python sphere
  decoder of ``benchmarks/sphere_peer.py`` in turn (same J asserted), so both see the same load: totals,
  medians and their ratio; and where ``lt.solve``'s time goes: its nodes, its iterations (one batched
  expansion each), the time of a decision of N = 1 (one iteration: the cost before the first node) and the
  rest per iteration.

    python benchmarks/converter_bench.py [--sections nodes peer] [--horizons 5 10] [--steps 100]
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np
from sphere_peer import SphereDecoder

import firhc_jax as fj
from firhc_jax.models import grid_converter


def decisions(N: int, steps: int):
    """``(lt, records)``: the closed loop that ``lt.solve`` decides; a record per step holds the decision's
    arguments ``(x, u_prev, y_ref, d, warm_start)`` and ``lt.solve``'s result."""
    lt = grid_converter.make_problem(N)
    A, B, _ = grid_converter.model()
    Y, D = grid_converter.decision_data(steps, N)
    x, u, plan = grid_converter.initial_state(), np.zeros(3), np.full(N, -1, np.int32)
    records = []
    for k in range(steps):
        ws = np.concatenate([plan[1:], plan[-1:]])
        result = lt.solve(x, u, Y[k], D[k], warm_start=ws)
        records.append(((x, u, Y[k], D[k], ws), result))
        plan = np.asarray(result.sequence)
        u = lt.controls[plan[0]]
        x = A @ x + B @ u + D[k][0]
    return lt, records


def node_counts(N: int, steps: int):
    """``(nodes of lt.solve, nodes of fj.sdfs on lt.problem)`` ``[steps]`` on the same decisions; asserts that
    both find the same J."""
    lt, records = decisions(N, steps)
    search = jax.jit(lambda z, p, ws: fj.sdfs(lt.problem, z, params=p, warm_start=ws))
    ours, theirs = [], []
    for (x, u, y_ref, d, ws), solved in records:
        searched = search(lt.observe(x, u), lt.params(y_ref, d), np.where(ws >= 0, lt.class_of[ws], -1))
        assert float(solved.cost) == float(searched.cost), (float(solved.cost), float(searched.cost))
        ours.append(int(solved.nodes))
        theirs.append(int(searched.nodes))
    return np.array(ours), np.array(theirs)


def section_nodes(args):
    print(f"\n## Nodes per decision, {args.steps} closed-loop decisions (float64, deterministic)")
    print(f"{'N':>3} {'path':<28} {'nodes mean':>11} {'nodes max':>10}  note")
    for N in args.horizons:
        ours, theirs = node_counts(N, args.steps)
        same = "equal on every step" if np.array_equal(ours, theirs) else \
            f"DIFFERENT on {int(np.sum(ours != theirs))} steps"
        print(f"{N:>3} {'lt.solve (shared_problem)':<28} {ours.mean():>11,.2f} {ours.max():>10,d}")
        print(f"{N:>3} {'fj.sdfs(lt.problem)':<28} {theirs.mean():>11,.2f} {theirs.max():>10,d}  {same}")


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return out, time.perf_counter() - t0


def section_peer(args):
    print(f"\n## Time per decision against the sphere decoder, {args.steps} closed-loop decisions, each solved by "
          "both in turn (same J)")
    print(f"{'N':>3} {'lt.solve ms total':>17} {'median':>7} {'decoder ms total':>16} {'median':>7} "
          f"{'total ratio':>11} {'nodes mean':>10} {'iterations':>10} {'us/iteration':>12}")
    fixed = None
    for N in sorted(set(args.horizons) | {1}):
        lt, records = decisions(N, args.steps)
        A, B, _ = grid_converter.model()
        peer = SphereDecoder(A, B, lt.C, lt.Q, (-1.0, 0.0, 1.0), N, lt.lambda_u, lt.max_step)
        ours, theirs, iterations, nodes = [], [], [], []
        plan = None
        for (x, u, y_ref, d, ws), _ in records:
            result, s = timed(lt.solve, x, u, y_ref, d, warm_start=ws)
            ours.append(s)
            first = None if plan is None else np.concatenate([plan[1:], plan[-1:]])
            (J, plan), s = timed(peer.solve, x, u, y_ref, first, d)
            theirs.append(s)
            assert np.isclose(J, float(result.cost), rtol=1e-9), (J, float(result.cost))
            iterations.append(int(result.iterations))
            nodes.append(int(result.nodes))
        ours, theirs = np.array(ours) * 1e3, np.array(theirs) * 1e3
        if N == 1:
            fixed = np.median(ours)
        per_iteration = 1e3 * (ours.sum() - fixed * len(ours)) / max(np.sum(iterations) - len(ours), 1)
        print(f"{N:>3} {ours.sum():>17.1f} {np.median(ours):>7.3f} {theirs.sum():>16.1f} {np.median(theirs):>7.3f} "
              f"{ours.sum() / theirs.sum():>11.3f} {np.mean(nodes):>10,.0f} {np.mean(iterations):>10.1f} "
              f"{per_iteration if N > 1 else float('nan'):>12.1f}")
    print(f"(us/iteration: lt.solve's time less {fixed:.3f} ms a decision, the median decision at N = 1, which "
          "runs one iteration, over the iterations after the first)")


SECTIONS = {"nodes": section_nodes, "peer": section_peer}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", nargs="+", choices=sorted(SECTIONS), default=list(SECTIONS))
    ap.add_argument("--horizons", type=int, nargs="+", default=[5, 10])
    ap.add_argument("--steps", type=int, default=100)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(f"converter_bench: {platform.processor() or platform.machine()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}, float64; load average {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    for name in args.sections:
        SECTIONS[name](args)


if __name__ == "__main__":
    main()
