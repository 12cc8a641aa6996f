"""fj.LinearTracking (the sphere decoder as sDFS with the cost-to-go bound) against the plain sDFS.

Sections (each prints a table; every search is exact unless a row says "capped"):

* inverter: the three-level inverter closed loop (``firhc_jax.models.three_level``,
  lambda_u = 0.1, max_step = 1) for each N: nodes and time per decision of
  LinearTracking, then the plain sDFS (``plain_problem``: the 27 switch
  states as children, no bound, the same warm start) on the same decisions,
  capped at ``--plain-max-nodes``; both pop ``three_level.pop_width(N)``
  nodes an iteration, as the app does.
* granularity: one node per step (M = 27 children) against one node per leg
  (3 levels each), both in the decoder's own coordinates (state: the N m
  partial sums of V U - h), against LinearTracking's form (state [x, u, du]);
  then the decoder form against LinearTracking where F is rank deficient.
* thermal: four rooms, N = 10, calm states near the set point
  (``firhc_jax.models.thermal``), LinearTracking against the plain sDFS (capped).
* batch: ``fj.solve_batch`` over B inverter states at N = 10: states/s and nodes/s.
* tradeoff: THD and switching frequency of the inverter closed loop per N, lambda_u swept.

    python benchmarks/sphere_bench.py [--sections inverter granularity thermal batch] [--horizons 1 2 3 5 8 10]
"""
from __future__ import annotations

import argparse
import functools
import operator
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import firhc_jax as fj
from firhc_jax._src.linear.factor import psd_factor
from firhc_jax.models import inverter, thermal, three_level


def timed(fn, *args, budget=0.02, repeats=3):
    """``fn(*args)`` and its wall time: the fastest of up to ``repeats`` runs while they total under ``budget``
    seconds (the machine is shared: the minimum of a few runs is the least noisy figure of a short call)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        took = time.perf_counter() - t0
        best = min(best, took)
        budget -= took
        if budget <= 0:
            break
    return out, best


def shifted(seq):
    """The previous optimum shifted by one step, last input repeated (all -1 stays none)."""
    return np.where(seq[0] >= 0, np.concatenate([seq[1:], seq[-1:]]), -1)


def plain_problem(lt):
    """The plain sDFS of ``lt``'s problem, as a user writes it without LinearTracking: every input of
    ``lt.controls`` a child (no classes), state ``[x, u, u - u_prev]``, no bound, lt's weights (the squared
    switching term: the L1 one where every step is 0 or 1, max_step = 1); params: ``lt.params(y_ref, d)``
    or a dict of the two. Returns ``(problem, observe(x, u_prev))``."""
    A, B, C, Q = (jnp.asarray(a) for a in (lt.A, lt.B, lt.C, lt.Q))
    n, m, lambda_u, max_step = lt.n, lt.m, lt.lambda_u, lt.max_step

    def data(p):
        return (p["y_ref"], p["d"]) if isinstance(p, dict) else (p.y_ref, p.d)

    def dynamics(z, u, k, p):
        return jnp.concatenate([A @ z[:n] + B @ u + data(p)[1][k], u, u - z[n:n + m]])

    def stage_cost(z, u, k, p):
        e, du = data(p)[0][k] - C @ z[:n], z[n + m:]
        return jnp.maximum(e @ Q @ e, 0.0) + lambda_u * (du @ du)

    def constraint(z, u, k, p):
        return jnp.all(jnp.abs(z[n + m:]) <= max_step)

    prob = fj.Problem(dynamics, lt.controls, stage_cost, lt.horizon,
                      constraint=None if lt.max_step is None else constraint, step_index=True)
    return prob, lambda x, u_prev: jnp.concatenate([jnp.asarray(x), jnp.asarray(u_prev), jnp.zeros(lt.m)])


def inverter_loop(N, steps, lambda_u, plain_cap=None, plain_every=1):
    """The LinearTracking closed loop from the reference at t = 0, each decision jitted (compiled first) and
    timed; with ``plain_cap``, every ``plain_every``-th decision is also solved by the plain sDFS
    (``plain_problem``: no classes, no bound; the same warm start, at most ``plain_cap`` nodes), right after
    it, so that both see the same machine load. Returns the tracker and per-decision records."""
    lt = three_level.make_problem(N, lambda_u=lambda_u)
    A, B = three_level.model()
    refs = inverter.horizon_references(three_level.PARAMS, steps, N)  # [T, N, 2]
    K = three_level.pop_width(N)  # the app's, for both searches
    ours = jax.jit(lambda z, p, ws: fj.sdfs(lt.problem, z, params=p, warm_start=ws, pop_width=K))
    plain, plain_observe = plain_problem(lt)
    base = jax.jit(lambda z, p, ws, cap: fj.sdfs(plain, z, params=p, warm_start=ws, max_nodes=cap, pop_width=K))
    x, u = inverter.reference(three_level.PARAMS, 0.0), np.zeros(3)
    seq = inputs = np.full(N, -1, np.int32)  # the last plan: classes, and the inputs they stand for
    rec = {key: [] for key in ("z", "p", "ws", "ws_inputs", "nodes", "s", "seq", "plain_nodes", "plain_s",
                               "plain_complete", "plain_index")}
    for k in range(steps):
        z, p, ws = jax.block_until_ready((lt.observe(jnp.asarray(x), u), lt.params(jnp.asarray(refs[k])),
                                          jnp.asarray(shifted(seq))))  # ready: the timings hold the searches only
        ws_inputs = jnp.asarray(shifted(inputs))
        if k == 0:
            timed(ours, z, p, ws)  # compile
        res, s = timed(ours, z, p, ws)
        seq, inputs = np.asarray(res.sequence), np.asarray(lt.sequence(z, res.sequence, p))
        for key, v in (("z", z), ("p", p), ("ws", ws), ("ws_inputs", ws_inputs), ("nodes", int(res.nodes)),
                       ("s", s), ("seq", seq)):
            rec[key].append(v)
        if plain_cap is not None and k % plain_every == 0:
            zp = plain_observe(x, u)
            if k == 0:
                timed(base, zp, p, ws_inputs, plain_cap)
            other, s = timed(base, zp, p, ws_inputs, plain_cap)
            if bool(other.complete):  # both exact: the same optimal cost
                assert np.isclose(float(other.cost), float(res.cost), rtol=1e-9), (k, float(other.cost), res.cost)
            for key, v in (("plain_nodes", int(other.nodes)), ("plain_s", s), ("plain_complete", bool(other.complete)),
                           ("plain_index", k)):
                rec[key].append(v)
        u = np.asarray(res.first_input)
        x = A @ x + B @ u
    return lt, rec


def stats(nodes, seconds):
    nodes, ms = np.asarray(nodes), np.asarray(seconds) * 1e3
    return f"{nodes.mean():>11,.0f} {nodes.max():>11,d} {np.median(ms):>9.3f} {ms.max():>9.2f}"


def section_inverter(args):
    print(f"\n## Three-level inverter closed loop, lambda_u = {args.lambda_u}, max_step = 1 "
          f"({args.steps} decisions up to N = {args.full_until}, then {args.long_steps}; plain sDFS on every "
          f"decision up to N = {args.full_until}, then on {args.plain_long} of them, capped at "
          f"{args.plain_max_nodes:,} nodes)")
    print(f"{'N':>3} {'search':<14} {'nodes mean':>11} {'nodes max':>11} {'ms median':>9} {'ms max':>9}  note")
    for N in args.horizons:
        long = N > args.full_until
        steps = args.long_steps if long else args.steps
        cap = args.plain_max_nodes if N <= args.plain_until else None
        every = max(1, steps // args.plain_long) if long else 1
        lt, rec = inverter_loop(N, steps, args.lambda_u, cap, every)
        print(f"{N:>3} {'LinearTracking':<14} {stats(rec['nodes'], rec['s'])}  {steps} decisions")
        if cap is None:
            continue
        idx = rec["plain_index"]
        capped = len(idx) - sum(rec["plain_complete"])
        note = f"{len(idx)} decisions" + (f", {capped} capped (their counts are lower bounds)" if capped else "")
        ratio_n = np.sum(rec["plain_nodes"]) / np.sum(np.asarray(rec["nodes"])[idx])
        ratio_t = np.sum(rec["plain_s"]) / np.sum(np.asarray(rec["s"])[idx])
        print(f"{N:>3} {'plain sDFS':<14} {stats(rec['plain_nodes'], rec['plain_s'])}  {note}; plain/ours: "
              f"nodes {ratio_n:.2f}x, time {ratio_t:.2f}x")


# -- granularity: the decoder's own coordinates ---------------------------------------------------------------------

def decoder_factor(lt):
    """``(V [Nm, Nm] lower triangular, G [R, n+m+N(p+n)])`` with J = c + ||V U - h||^2,
    h = (Qf^T G data)[::-1], c = ||Qperp^T G data||^2 (QR of F with its columns reversed)."""
    A, B, C, N = lt.A, lt.B, lt.C, lt.horizon
    n, m, p = lt.n, lt.m, lt.p
    sq = psd_factor("Q", lt.Q)
    powers = [np.linalg.matrix_power(A, i) for i in range(N + 1)]
    R = N * (p + m)
    F, G = np.zeros((R, N * m)), np.zeros((R, n + m + N * (p + n)))
    for k in range(N):
        r = slice(k * p, (k + 1) * p)
        for j in range(k + 1):
            F[r, j * m:(j + 1) * m] = sq @ C @ powers[k - j] @ B
            G[r, n + m + N * p + j * n:n + m + N * p + (j + 1) * n] = -sq @ C @ powers[k - j]
        G[r, :n] = -sq @ C @ powers[k + 1]
        G[r, n + m + k * p:n + m + (k + 1) * p] = sq
        r = slice(N * p + k * m, N * p + (k + 1) * m)
        F[r, k * m:(k + 1) * m] = np.sqrt(lt.lambda_u) * np.eye(m)
        if k:
            F[r, (k - 1) * m:k * m] = -np.sqrt(lt.lambda_u) * np.eye(m)
        else:
            G[r, n:n + m] = np.sqrt(lt.lambda_u) * np.eye(m)
    Qf, Rf = np.linalg.qr(F[:, ::-1], mode="complete")
    Nm = N * m
    return Rf[:Nm][::-1, ::-1], (Qf[:, :Nm].T @ G)[::-1], Qf[:, Nm:].T @ G


def decoder_problem(lt, per_component):
    """The decoder's search: state [r (Nm: V U - h so far), c, last input (m), its change (m)];
    one node per step (controls [27, 3]) or per leg (levels [3, 1], depth N m)."""
    V, _, _ = decoder_factor(lt)
    N, m = lt.horizon, lt.m
    Nm = N * m

    def dynamics(z, u, k):
        u = u.astype(z.dtype)
        if per_component:
            comp = k % m
            last = z[Nm + 1:Nm + 1 + m]
            r = z[:Nm] + jax.lax.dynamic_slice(jnp.asarray(V, z.dtype), (jnp.int32(0), k), (Nm, 1))[:, 0] * u[0]
            return jnp.concatenate([r, z[Nm:Nm + 1], last.at[comp].set(u[0]), (u[0] - last[comp]) * jnp.ones(m)])
        r = z[:Nm] + jax.lax.dynamic_slice(jnp.asarray(V, z.dtype), (jnp.int32(0), k * m), (Nm, m)) @ u
        return jnp.concatenate([r, z[Nm:Nm + 1], u, u - z[Nm + 1:Nm + 1 + m]])

    def stage_cost(z, u, k):
        rows = jnp.sum(jax.lax.dynamic_slice(z, (k * (1 if per_component else m),), (1 if per_component else m,)) ** 2)
        return rows + jnp.where(k == 0, z[Nm], 0.0)

    def constraint(z, u, k):
        return jnp.all(jnp.abs(z[Nm + 1 + m:]) <= lt.max_step)

    controls = np.array([[-1.0], [0.0], [1.0]]) if per_component else lt.controls
    return fj.Problem(dynamics, controls, stage_cost, Nm if per_component else N,
                      constraint=None if lt.max_step is None else constraint, step_index=True)


def decoder_decide(lt, per_component):
    """jitted ``decide(z, p, ws)`` of the decoder form from LinearTracking's state and params: the state
    [-h, c, u_prev, 0] (h, c from x, u_prev, y_ref, d) and, per leg, the warm start leg by leg."""
    prob = decoder_problem(lt, per_component)
    _, Wh, We = decoder_factor(lt)

    def decide(z, p, ws):
        data = jnp.concatenate([z[:lt.n + lt.m], p.y_ref.ravel(), p.d.ravel()])
        e = jnp.asarray(We) @ data
        z0 = jnp.concatenate([-jnp.asarray(Wh) @ data, (e @ e)[None], z[lt.n:lt.n + lt.m], jnp.zeros(lt.m)])
        if per_component:  # digits of the product order (three levels per leg)
            legs = jnp.stack([ws // 9, ws // 3 % 3, ws % 3], axis=1).reshape(-1)
            ws = jnp.where(jnp.repeat(ws, 3) >= 0, legs, -1)
        return fj.sdfs(prob, z0, warm_start=ws, max_nodes=50_000_000)

    return jax.jit(decide)


def section_granularity(args):
    print(f"\n## Granularity and state, three-level inverter, lambda_u = {args.lambda_u}, the first "
          f"{args.granularity_steps} decisions of the closed loop, each solved by the three forms in turn")
    print(f"{'N':>3} {'form':<28} {'nodes mean':>11} {'nodes max':>11} {'ms median':>9} {'ms max':>9} "
          f"{'iterations':>10} {'us/iter':>8}")
    for N in args.granularity_horizons:
        lt, rec = inverter_loop(N, args.granularity_steps, args.lambda_u)
        forms = {"decoder form, node per step": decoder_decide(lt, False),
                 "decoder form, node per leg": decoder_decide(lt, True),
                 "LinearTracking (per step)": jax.jit(lambda z, p, ws, lt=lt: fj.sdfs(lt.problem, z, params=p,
                                                                                      warm_start=ws))}
        out = {name: ([], [], []) for name in forms}
        for k in range(len(rec["z"])):
            for name, decide in forms.items():
                ws = rec["ws"] if name.startswith("LinearTracking") else rec["ws_inputs"]  # classes or inputs
                if k == 0:
                    timed(decide, rec["z"][0], rec["p"][0], ws[0])
                res, s = timed(decide, rec["z"][k], rec["p"][k], ws[k])
                for lst, v in zip(out[name], (int(res.nodes), s, int(res.iterations)), strict=True):
                    lst.append(v)
        for name, (nodes, secs, its) in out.items():
            print(f"{N:>3} {name:<28} {stats(nodes, secs)} {np.mean(its):>10.1f} "
                  f"{np.sum(secs) / np.sum(its) * 1e6:>8.2f}")
    # A rank-deficient F: no switching penalty and fewer outputs than inputs (the thermal process).
    N = args.rank_horizon
    lt = thermal.make_problem(N, lambda_u=0.0)
    X, U = thermal.calm_states(args.rank_states, np.random.default_rng(0))
    _, _, d = thermal.model()
    p = lt.params(np.broadcast_to(thermal.ThermalParams().set_point, (N, 2)), np.broadcast_to(d, (N, 4)))
    V, _, _ = decoder_factor(lt)
    zero = int(np.sum(np.all(np.abs(V) < 1e-12 * np.abs(V).max(), axis=1)))
    print(f"\n## Rank-deficient F: thermal process, lambda_u = 0, N = {N}, {args.rank_states} calm states "
          f"({zero} of {V.shape[0]} rows of V are zero; decoder capped at 50,000,000 nodes)")
    print(f"{'form':<28} {'nodes mean':>11} {'nodes max':>11} {'ms median':>9} {'ms max':>9}")
    ws = jnp.full(N, -1, jnp.int32)
    forms = {"decoder form, node per step": decoder_decide(lt, False),
             "LinearTracking": jax.jit(lambda z, p, ws: fj.sdfs(lt.problem, z, params=p, warm_start=ws)),
             "plain sDFS": jax.jit(lambda z, p, ws: fj.sdfs(plain, z, params=p, warm_start=ws))}
    plain, plain_observe = plain_problem(lt)
    out = {name: ([], []) for name in forms}
    for i, (x, u) in enumerate(zip(X, U, strict=True)):
        z = lt.observe(jnp.asarray(x), u)
        costs = []
        for name, decide in forms.items():
            zi = plain_observe(x, u) if name == "plain sDFS" else z
            if i == 0:
                timed(decide, zi, p, ws)
            res, s = timed(decide, zi, p, ws)
            out[name][0].append(int(res.nodes))
            out[name][1].append(s)
            costs.append(float(res.cost))
        assert np.allclose(costs, costs[0], rtol=1e-9), costs
    for name, (nodes, secs) in out.items():
        print(f"{name:<28} {stats(nodes, secs)}")


def section_thermal(args):
    N = args.thermal_horizon
    lt = thermal.make_problem(N, lambda_u=args.thermal_lambda_u)
    X, U = thermal.calm_states(args.thermal_states, np.random.default_rng(0))
    _, _, d = thermal.model()
    p = lt.params(np.broadcast_to(thermal.ThermalParams().set_point, (N, 2)), np.broadcast_to(d, (N, 4)))
    plain, plain_observe = plain_problem(lt)
    ours = jax.jit(lambda z: fj.sdfs(lt.problem, z, params=p))
    base = jax.jit(lambda z, cap: fj.sdfs(plain, z, params=p, max_nodes=cap))
    print(f"\n## Thermal process, N = {N}, lambda_u = {args.thermal_lambda_u}, {args.thermal_states} calm states "
          f"(within 0.05 K of the steady state at the set point; plain sDFS capped at {args.thermal_max_nodes:,})")
    print(f"{'search':<14} {'nodes mean':>11} {'nodes max':>11} {'ms median':>9} {'ms max':>9}  note")
    rows = {"LinearTracking": ([], [], []), "plain sDFS": ([], [], [])}
    for i, (x, u) in enumerate(zip(X, U, strict=True)):
        z, zp = lt.observe(jnp.asarray(x), u), plain_observe(x, u)
        if i == 0:
            timed(ours, z)
            timed(base, zp, args.thermal_max_nodes)
        r1, s1 = timed(ours, z)
        r2, s2 = timed(base, zp, args.thermal_max_nodes)
        if bool(r2.complete):
            assert np.isclose(float(r1.cost), float(r2.cost), rtol=1e-9), i
        for name, r, s in (("LinearTracking", r1, s1), ("plain sDFS", r2, s2)):
            rows[name][0].append(int(r.nodes))
            rows[name][1].append(s)
            rows[name][2].append(bool(r.complete))
    for name, (nodes, secs, complete) in rows.items():
        capped = len(complete) - sum(complete)
        print(f"{name:<14} {stats(nodes, secs)}  {f'{capped} capped' if capped else 'all complete'}")


def section_batch(args):
    N, B = 10, args.batch
    lt = three_level.make_problem(N, lambda_u=args.lambda_u)
    rng = np.random.default_rng(0)
    phase = rng.uniform(0, 1 / three_level.PARAMS.frequency, B)
    X = inverter.reference(three_level.PARAMS, phase) + rng.uniform(-1.0, 1.0, (B, 2))
    U = three_level.SWITCH_STATES[rng.integers(0, 27, B)]
    t = phase[:, None] + np.arange(1, N + 1) * three_level.PARAMS.ts
    Z, P = jax.vmap(lt.observe)(jnp.asarray(X), jnp.asarray(U)), lt.params(inverter.reference(three_level.PARAMS, t))
    print(f"\n## Batch: {B} inverter states (reference phase uniform, current within 1 A of it, u_prev random), "
          f"N = {N}, fj.solve_batch (pool, {args.lanes} lanes)")
    print(f"{'search':<14} {'rows':>6} {'s':>8} {'states/s':>9} {'nodes/s':>12} {'nodes mean':>11}  note")
    plain, plain_observe = plain_problem(lt)
    Zp = jax.vmap(plain_observe)(jnp.asarray(X), jnp.asarray(U))
    for name, prob, rows, cap in (("LinearTracking", lt.problem, B, None),
                                  ("LinearTracking", lt.problem, args.batch_plain, None),
                                  ("plain sDFS", plain, args.batch_plain, args.plain_max_nodes)):
        z = (Zp if prob is plain else Z)[:rows]
        p = jax.tree_util.tree_map(operator.itemgetter(slice(0, rows)), P)
        run = functools.partial(fj.solve_batch, prob, z, params=p, lanes=args.lanes, max_nodes=cap)
        jax.block_until_ready(run())  # compiles for these shapes (a batch of other rows would compile again)
        res, s = timed(run)
        nodes = np.asarray(res.nodes)
        capped = int(np.sum(~np.asarray(res.complete)))
        print(f"{name:<14} {rows:>6} {s:>8.2f} {rows / s:>9.1f} {nodes.sum() / s:>12,.0f} {nodes.mean():>11,.0f}  "
              f"{f'{capped} capped' if capped else 'all complete'}")


def section_tradeoff(args):
    """THD against switching frequency per N, lambda_u swept: the closed loop as one compiled FIRHC scan per N
    (``shared_problem``: the model, lambda_u with it, is in the params, so every lambda_u reuses it)."""
    from firhc_jax.apps import inverter_three_level as app

    steps = args.steps
    A, B = three_level.model()
    i0 = jnp.asarray(inverter.initial_currents(three_level.PARAMS))

    def plant(x, u, p):  # one function for every run: one compiled closed loop per N
        return jnp.asarray(A) @ x + jnp.asarray(B) @ u

    print(f"\n## Distortion against switching frequency, {steps} decisions per run (compiled closed loop)")
    print(f"{'N':>3} {'lambda_u':>8} {'THD %':>6} {'f_sw Hz':>8} {'nodes mean':>11} {'nodes max':>10} {'s':>7}")
    for N in args.tradeoff_horizons:
        refs = jnp.asarray(inverter.horizon_references(three_level.PARAMS, steps, N))
        shared = three_level.make_problem(N)
        ctrl = fj.FIRHC(shared.shared_problem, observe=shared.observe, warm_start=True)
        for lam in args.tradeoff_lambdas:
            lt = three_level.make_problem(N, lambda_u=lam)
            t0 = time.perf_counter()
            run = jax.block_until_ready(ctrl.simulate(i0, steps, plant, params=lt.params(refs, with_model=True),
                                                      u0=jnp.zeros(3), dt=three_level.PARAMS.ts))
            s = time.perf_counter() - t0
            out = app.summarize(app.InverterRun(run, inverter.reference(three_level.PARAMS, run.times), np.nan), N, lam)
            print(f"{N:>3} {lam:>8g} {out['thd'] * 100:>6.2f} {out['switching_frequency_hz']:>8.0f} "
                  f"{out['nodes_mean']:>11,.0f} {out['nodes_max']:>10,d} {s:>7.1f}", flush=True)


SECTIONS = {"inverter": section_inverter, "granularity": section_granularity, "thermal": section_thermal,
            "batch": section_batch, "tradeoff": section_tradeoff}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", nargs="+", choices=sorted(SECTIONS), default=list(SECTIONS))
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 2, 3, 5, 8, 10, 15, 20])
    ap.add_argument("--lambda-u", type=float, default=0.1)
    ap.add_argument("--steps", type=int, default=1600, help="decisions (2 fundamental periods = 1600)")
    ap.add_argument("--full-until", type=int, default=10, help="longer horizons run --long-steps decisions")
    ap.add_argument("--long-steps", type=int, default=100)
    ap.add_argument("--plain-until", type=int, default=15, help="plain sDFS only up to this N")
    ap.add_argument("--plain-long", type=int, default=20, help="decisions the plain sDFS solves beyond --full-until")
    ap.add_argument("--plain-max-nodes", type=int, default=5_000_000)
    ap.add_argument("--granularity-horizons", type=int, nargs="+", default=[5, 8])
    ap.add_argument("--granularity-steps", type=int, default=200)
    ap.add_argument("--rank-horizon", type=int, default=6)
    ap.add_argument("--rank-states", type=int, default=6)
    ap.add_argument("--thermal-horizon", type=int, default=10)
    ap.add_argument("--thermal-lambda-u", type=float, default=thermal.LAMBDA_U)
    ap.add_argument("--thermal-states", type=int, default=20)
    ap.add_argument("--thermal-max-nodes", type=int, default=20_000_000)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--batch-plain", type=int, default=512, help="rows both searches solve (the first ones)")
    ap.add_argument("--lanes", type=int, default=256)
    ap.add_argument("--tradeoff-horizons", type=int, nargs="+", default=[1, 3, 5, 10])
    ap.add_argument("--tradeoff-lambdas", type=float, nargs="+", default=[0.1, 1, 3, 10, 30, 100])
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(f"sphere_bench: {platform.processor() or platform.machine()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}, float64; a 2-core machine shared with other jobs: times are noisy")
    for name in args.sections:
        SECTIONS[name](args)


if __name__ == "__main__":
    main()
