"""fj.LinearTracking on the medium-voltage three-level converter on an RL grid (``firhc_jax.models.grid_converter``):
node counts of its two paths, and time against a sphere decoder, on the same closed-loop decisions.

The decisions: ``--steps`` closed-loop steps through the 0.2 -> 1 pu current step, ``lt.solve`` deciding,
each warm-started with the previous plan shifted by one step (its last input repeated), float64.

Sections (each prints a table):

* nodes: per N (``--node-horizons``), the nodes of ``lt.solve`` (``shared_problem``, the model in the params)
  and of ``fj.sdfs`` on ``lt.problem`` (the model as constants) on every decision, and whether they are equal
  step by step (they must be: one search). ``tests/linear/test_converter_nodes.py`` holds the N = 5 and 10 means as
  recorded here.
* peer: per N (``--horizons``), each decision timed as ``lt.solve`` (eager, compiled first) takes it, then
  solved by the scalar Python sphere decoder of ``benchmarks/sphere_peer.py`` (same J asserted; up to
  ``--decoder-until``), so both see the same load: totals,
  medians and their ratio; and where ``lt.solve``'s time goes: its nodes, its iterations (one batched
  expansion each), the time of a decision of N = 1 (one iteration: the cost before the first node) and the
  rest per iteration; then the same decisions through ``lt.solve(..., engine="c")`` (same J and nodes
  asserted) and their ratios to the decoder.

    python benchmarks/converter_bench.py [--sections nodes peer] [--node-horizons 5 10] [--horizons 5 10 12]
        [--steps 100] [--decoder-until 12] [--publish]
"""
from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from _results import machine, published
from sphere_peer import SphereDecoder

import firhc_jax as fj
from firhc_jax.models import grid_converter


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return out, time.perf_counter() - t0


class Decoder:
    """The sphere decoder of ``benchmarks/sphere_peer.py`` on ``lt``'s decisions, its own previous plan shifted as
    its first radius; asserts the same J as ``lt.solve``."""

    def __init__(self, lt):
        A, B, _ = grid_converter.model()
        self.decoder = SphereDecoder(A, B, lt.C, lt.Q, (-1.0, 0.0, 1.0), lt.horizon, lt.lambda_u, lt.max_step)
        self.plan = None

    def __call__(self, arguments, result):
        x, u, y_ref, d, _ = arguments
        first = None if self.plan is None else np.concatenate([self.plan[1:], self.plan[-1:]])
        J, self.plan = self.decoder.solve(x, u, y_ref, first, d)
        assert np.isclose(J, float(result.cost), rtol=1e-9), (J, float(result.cost))


def decisions(N: int, steps: int, decoder: bool = False):
    """``(lt, records)``: the closed loop that ``lt.solve`` decides (compiled first); a record per step holds the
    decision's arguments ``(x, u_prev, y_ref, d, warm_start)``, ``lt.solve``'s result and its wall time, and
    with ``decoder`` the wall time of the ``Decoder`` solving the same decision right after (the same load)."""
    lt = grid_converter.make_problem(N)
    peer = Decoder(lt) if decoder else None
    A, B, _ = grid_converter.model()
    Y, D = grid_converter.decision_data(steps, N)
    x, u, plan = grid_converter.initial_state(), np.zeros(3), np.full(N, -1, np.int32)
    timed(lt.solve, x, u, Y[0], D[0], warm_start=plan)  # compiles
    timed(lt.solve, x, u, Y[0], D[0], warm_start=plan, engine="c")  # generates and compiles the C
    records = []
    for k in range(steps):
        ws = np.concatenate([plan[1:], plan[-1:]])
        arguments = (x, u, Y[k], D[k], ws)
        result, seconds = timed(lt.solve, *arguments[:4], warm_start=ws)
        in_c, c_seconds = timed(lt.solve, *arguments[:4], warm_start=ws, engine="c")
        assert np.isclose(float(in_c.cost), float(result.cost), rtol=1e-9) and int(in_c.nodes) == int(result.nodes)
        records.append((arguments, result, seconds, c_seconds)
                       + (() if peer is None else timed(peer, arguments, result)[1:]))
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
    for (x, u, y_ref, d, ws), solved, *_ in records:
        searched = search(lt.observe(x, u), lt.params(y_ref, d), np.where(ws >= 0, lt.class_of[ws], -1))
        assert float(solved.cost) == float(searched.cost), (float(solved.cost), float(searched.cost))
        ours.append(int(solved.nodes))
        theirs.append(int(searched.nodes))
    return np.array(ours), np.array(theirs)


def section_nodes(args):
    print(f"\n## Nodes per decision, {args.steps} closed-loop decisions (float64, deterministic)")
    print(f"{'N':>3} {'path':<28} {'nodes mean':>11} {'nodes max':>10}  note")
    for N in args.node_horizons:
        ours, theirs = node_counts(N, args.steps)
        same = "equal on every step" if np.array_equal(ours, theirs) else \
            f"DIFFERENT on {int(np.sum(ours != theirs))} steps"
        print(f"{N:>3} {'lt.solve (shared_problem)':<28} {ours.mean():>11,.2f} {ours.max():>10,d}")
        print(f"{N:>3} {'fj.sdfs(lt.problem)':<28} {theirs.mean():>11,.2f} {theirs.max():>10,d}  {same}")


def section_peer(args):
    print(f"\n## Time per decision against the sphere decoder, {args.steps} closed-loop decisions, lt.solve deciding "
          f"and timed, the decoder right after on the same decision (same J), up to N = {args.decoder_until}")
    print(f"{'N':>3} {'lt.solve ms total':>17} {'median':>7} {'decoder ms total':>16} {'median':>7} "
          f"{'total ratio':>11} {'nodes mean':>10} {'nodes max':>10} {'iterations':>10} {'us/iteration':>12} "
          f"{'engine c ms total':>17} {'median':>7} {'c/decoder total':>15} {'c/decoder median':>16}")
    fixed = None
    for N in sorted(set(args.horizons) | {1}):
        _, records = decisions(N, args.steps, decoder=N <= args.decoder_until)
        ours, in_c = np.array([r[2] for r in records]) * 1e3, np.array([r[3] for r in records]) * 1e3
        theirs = np.array([r[4] for r in records if len(r) > 4]) * 1e3
        iterations = [int(r[1].iterations) for r in records]
        nodes = [int(r[1].nodes) for r in records]
        if N == 1:
            fixed = np.median(ours)
        per_iteration = 1e3 * (ours.sum() - fixed * len(ours)) / max(np.sum(iterations) - len(ours), 1)
        peer_cols = (f"{theirs.sum():>16.1f} {np.median(theirs):>7.3f} {ours.sum() / theirs.sum():>11.3f}"
                     if len(theirs) else f"{'not run':>16} {'':>7} {'':>11}")
        c_ratios = (f"{in_c.sum() / theirs.sum():>15.3f} {np.median(in_c) / np.median(theirs):>16.3f}"
                    if len(theirs) else f"{'':>15} {'':>16}")
        print(f"{N:>3} {ours.sum():>17.1f} {np.median(ours):>7.3f} {peer_cols} {np.mean(nodes):>10,.0f} "
              f"{max(nodes):>10,d} {np.mean(iterations):>10.1f} {per_iteration if N > 1 else float('nan'):>12.1f} "
              f"{in_c.sum():>17.1f} {np.median(in_c):>7.3f} {c_ratios}", flush=True)
    print(f"(us/iteration: lt.solve's time less {fixed:.3f} ms a decision, the median decision at N = 1, which "
          "runs one iteration, over the iterations after the first; engine c: lt.solve(..., engine=\"c\") on the "
          "same decision, right after)")


SECTIONS = {"nodes": section_nodes, "peer": section_peer}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", nargs="+", choices=sorted(SECTIONS), default=list(SECTIONS))
    ap.add_argument("--node-horizons", type=int, nargs="+", default=[5, 10], help="the nodes section's")
    ap.add_argument("--horizons", type=int, nargs="+", default=[5, 10, 12], help="the peer section's")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--decoder-until", type=int, default=12, help="the decoder solves the decisions up to this N")
    ap.add_argument("--publish", action="store_true", help="also write the tables to benchmarks/results/converter.md")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    with published("converter", args.publish, "python benchmarks/converter_bench.py --publish"):
        print(f"converter_bench: {machine()}, float64")
        for name in args.sections:
            SECTIONS[name](args)


if __name__ == "__main__":
    main()
