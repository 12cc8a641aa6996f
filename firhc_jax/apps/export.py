"""``python -m firhc_jax export APP``: an application's controller as C99 (``fj.export_c``).

    python -m firhc_jax export tanks --horizon 3 --out out/c-tanks
    python -m firhc_jax export inverter --horizon 2 --out out/c-inverter --compare 20

Writes ``firhc.h`` and ``firhc.c`` (``--name`` changes the prefix) for the application's controller as the
application builds it, with the default search (``"sdfs"`` at ``pop_width=1``): the hopper (its fallback,
observe, actuate and safe input), the three tanks (its fallback when a terminal box is set), the two-level
inverter (its switching penalty, per-decision reference as parameters) and the three-level inverter
(``LinearTracking``'s controller, the reference and disturbance as parameters). Prints the sizes and the
memory the generated code needs; with ``--compare K`` compiles it with ``cc`` and runs K decisions of the
application's closed loop through both the generated code and ``ctrl.step``, and reports any that differ.
"""
from __future__ import annotations

import shutil
import time

import numpy as np

from ._args import number, output_dir

APPS = ("hopper", "tanks", "inverter", "inverter3")
HELP = "write an application's controller as C99 (no Python, no XLA), and check it against the library"
DESCRIPTION = ("fj.export_c on an application's controller: NAME.h and NAME.c with NAME_solve, NAME_init and "
               "NAME_step, sized at export, C99 and libm only. --compare K compiles them with cc and compares K "
               "decisions of the application's closed loop with ctrl.step.")


def register(subparsers) -> None:
    """Add the ``export`` subcommand."""
    p = subparsers.add_parser("export", help=HELP, description=DESCRIPTION)
    p.add_argument("app", choices=APPS, help="the application whose controller is exported")
    p.add_argument("--horizon", "-N", type=number(int, 1, 12), default=2, metavar="N",
                   help="prediction horizon N (1-12, default 2)")
    p.add_argument("--out", type=output_dir, default="out/c", help="folder for the two files (default out/c)")
    p.add_argument("--name", default="firhc", help="prefix of the C symbols and files (default firhc)")
    p.add_argument("--max-nodes", type=number(int, 1), default=None,
                   help="node budget of a decision (default: none, every decision exact)")
    p.add_argument("--compare", type=number(int, 0, 10_000), default=0, metavar="K",
                   help="compile with cc and compare K closed-loop decisions with ctrl.step (default 0: none)")
    p.set_defaults(func=run)


def controller(app: str, horizon: int, max_nodes):
    """``(ctrl, params of each step or None, x0, u0, plant)`` of an application, as it builds them; for the
    three-level inverter ``ctrl`` is ``(LinearTracking, its controller)`` and the params its raw data."""
    import jax
    import jax.numpy as jnp

    import firhc_jax as fj

    budget = {} if max_nodes is None else {"max_nodes": max_nodes}
    if app == "hopper":
        from ..models import hopper as hm

        P = hm.HopperParams()
        ctrl = fj.FIRHC(hm.make_problem(horizon, P), fallback="unconstrained", observe=hm.observe,
                        actuate=lambda X, u: hm.actuate(X, u, P), u_safe=np.zeros(1), **budget)
        step = hm.make_plant(P)
        return ctrl, None, hm.initial_state(P), np.zeros(1), lambda X, u, t: step(jnp.asarray(X), jnp.asarray(u))
    if app == "tanks":
        from ..models import tanks

        problem = tanks.make_problem(horizon)
        dynamics = jax.jit(problem.dynamics)
        return fj.FIRHC(problem, **budget), None, tanks.initial_state(), None, \
            lambda x, u, t: dynamics(jnp.asarray(x), jnp.asarray(u))
    from ..models import inverter as two_level

    params = two_level.InverterParams()
    refs = two_level.horizon_references(params, 10_000, horizon)
    if app == "inverter":
        mem = two_level.make_problem(horizon, params)
        ctrl = fj.FIRHC(mem.problem, observe=mem.observe, **budget)
        steps = [{"ref": jnp.asarray(r), "lambda_u": jnp.asarray(0.1)} for r in refs[:100]]
        plant = jax.jit(two_level.make_plant(params))
    else:
        from ..models import three_level

        lt = three_level.make_problem(horizon, three_level.PARAMS)
        ctrl = fj.FIRHC(lt.problem, observe=lt.observe, warm_start=True, **budget)
        steps = [(r, np.zeros((horizon, lt.n))) for r in refs[:100]]  # the raw data the generated code maps
        plant = jax.jit(three_level.make_plant(three_level.PARAMS))
        return (lt, ctrl), steps, two_level.initial_currents(params), np.zeros(3), \
            lambda x, u, t: plant(jnp.asarray(x), jnp.asarray(u))
    return ctrl, steps, two_level.initial_currents(params), np.zeros(3), \
        lambda x, u, t: plant(jnp.asarray(x), jnp.asarray(u))


def run(args) -> None:
    import jax

    import firhc_jax as fj

    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    ctrl, steps, x0, u0, plant = controller(args.app, args.horizon, args.max_nodes)
    params = None if steps is None else steps[0]
    tracker = None
    if isinstance(ctrl, tuple):  # LinearTracking: the generated code maps the raw data as lt.params does
        tracker, ctrl = ctrl
    exported = fj.export_c(tracker or ctrl, args.out, name=args.name, params=params, x0=x0)
    e = exported
    print(f"{args.app}, N = {args.horizon}: wrote {e.header} and {e.source} in {time.perf_counter() - t0:.1f} s")
    print(f"  state n = {e.state_size} (the plant's: {e.plant_state_size}), {e.num_controls} inputs of dimension "
          f"{e.input_size}, {e.num_params} parameters")
    print(f"  memory: {e.work_bytes:,} bytes of work arrays on the C stack per call, a controller state of "
          f"{e.state_bytes} bytes; no allocation")
    if not args.compare:
        return
    if shutil.which("cc") is None:
        raise SystemExit("--compare needs a C compiler (cc) on the PATH")
    lib = exported.compile()
    x, state, c_state = np.asarray(x0, float), ctrl.init(x0, u0), lib.init(x0, u0)
    differ = ties = 0
    for t in range(args.compare):
        p = None if steps is None else steps[t % len(steps)]
        u, state, info = ctrl.step(state, x, p if tracker is None else tracker.params(*p))
        code, c_u = lib.step(c_state, x, p)
        if not np.allclose(c_u, np.asarray(u), rtol=1e-9, atol=1e-12) or c_state.nodes != int(info.nodes):
            cost = float(info.result.cost)
            what = (f"the library applied {np.asarray(u).tolist()} ({int(info.nodes)} nodes, cost {cost:.12g}), the "
                    f"C code {c_u.tolist()} ({c_state.nodes} nodes, cost {c_state.cost:.12g}, code {code})")
            if np.isfinite(cost) and abs(c_state.cost - cost) <= 1e-9 * max(1.0, abs(cost)):
                # Sequences of equal cost (to rounding): either is optimal. The C state takes the library's
                # input and plan, so that the next decisions are compared from the same start.
                ties += 1
                print(f"  step {t}: a tie broken the other way: {what}")
                c_state.u[:] = np.asarray(state.u, float).tolist()
                c_state.plan[:] = np.asarray(state.plan).tolist()
            else:
                differ += 1
                print(f"  step {t}: {what}")
        x = np.asarray(plant(x, u, t))
    found = [f"{differ} differ"] if differ else []
    if ties:
        found.append(f"{ties} of equal cost (to 1e-9) went to another optimal input; the others are equal")
    print(f"  checked {args.compare} closed-loop decisions against ctrl.step: "
          + ("; ".join(found) if found else "all equal (inputs and node counts)"))
    if differ:
        raise SystemExit(1)
