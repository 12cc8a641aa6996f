"""``python -m firhc_jax bench tables|throughput``: the paper's Tables 2 and 3
on this implementation, and node-expansion throughput profiles.

Method (both commands): the closed loop is run once with sDFS to record the
states at which the controller searches; every search variant is then timed
on those same states, one compiled search per state (``block_until_ready``),
after a warm-up call whose time is reported as compile time. A cell's time is
the median over repeats of the summed search times, and every ratio is taken
between timings of the same process. Exact searches visit the same states
whichever search drives the loop (tested), so this is the paper's experiment.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._args import number, output_dir
from ._machine import machine
from ._status import stage

# The paper's figures: Point A, Point B max and min (Table 2) or max and mean (Table 3), Point C (sDFS time /
# ES time, %).
PAPER_B = {"hopper": "min", "tanks": "mean"}
PAPER = {
    "hopper": {5: (363, 363, 15, 7.0), 6: (1092, 1044, 18, 4.1), 7: (3279, 2208, 21, 2.3), 8: (9840, 4380, 24, 1.1)},
    "tanks": {3: (5219, 2516, 595, 16.0), 4: (88740, 13396, 1377, 3.1), 5: (1508597, 44608, 3009, 0.6),
              6: (25646166, 124066, 7310, None)},
}
HORIZONS = {"hopper": (5, 6, 7, 8), "tanks": (3, 4, 5, 6)}
SECONDS = {"hopper": 2.0, "tanks": 200.0}  # the paper's closed loops
QUICK_SECONDS = {"hopper": 0.5, "tanks": 20.0}
SMOKE = ("SMOKE RUN (--quick): a few short runs, timed once, to check that the command works; its figures mean "
         "nothing")
MAX_REPEATS = 100
MAX_ES_NODES = 1e9  # nodes, spent once per repeat: about 8 minutes at the tanks' 0.47 us a node
POP_WIDTHS = (1, 2, 4, 8, 16)
BATCHES = (1, 8, 64, 512)


class Case(NamedTuple):
    """One plant at one horizon: the problem and the states the closed loop searched at."""

    plant: str
    horizon: int
    problem: object  # fj.Problem
    states: np.ndarray  # [S, n]
    reference: np.ndarray  # [S, N] int sDFS solution at each state (warm starts shift it)


def hopper_case(horizon: int, seconds: float = 2.0, bound: bool = False) -> Case:
    from ..models import hopper as hm
    from ._hopper import controller

    params = hm.HopperParams()
    steps = max(1, int(round(seconds / hm.CONTROL_PERIOD)))
    loop = controller(horizon, params, "sdfs").simulate(hm.initial_state(params), steps, hm.make_plant(params))
    states = np.asarray(loop.states[:-1])
    searched = jax.vmap(lambda X: hm.observe(X, None))(states[hm.contact(states)])  # model states in contact
    return _case("hopper", hm.make_problem(horizon, params, bound), searched)


def tanks_case(horizon: int, seconds: float = 200.0, bound: bool = False) -> Case:
    import firhc_jax as fj

    from ..models import tanks as model

    problem = model.make_problem(horizon, bound=bound)  # the same closed loop with or without the bound
    loop = fj.FIRHC(problem).simulate(model.initial_state(), int(seconds // model.TankParams().ts))
    return _case("tanks", problem, np.asarray(loop.states[:-1]))


def synthetic_case(horizon: int, count: int = 8, work: int = 0) -> Case:
    from ..models.synthetic import SyntheticParams, benchmark_state, make_problem

    rng = np.random.default_rng(0)
    states = np.asarray(benchmark_state()) * (1 + 0.2 * rng.standard_normal((count, 3)))
    return _case(f"synthetic(work={work})", make_problem(horizon, SyntheticParams(17, work)), states)


def _case(plant, problem, states) -> Case:
    import firhc_jax as fj

    states = np.asarray(states)
    solve = jax.jit(lambda x: fj.sdfs(problem, x).sequence)
    reference = np.stack([np.asarray(solve(jnp.asarray(x))) for x in states])
    return Case(plant, problem.horizon, problem, states, reference)


# ---------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------

class Timing(NamedTuple):
    seconds: float  # median over repeats of the summed search times
    compile_s: float  # first call minus a typical one
    slowest: float  # the slowest single search (s), its fastest repeat
    nodes: np.ndarray  # [S] nodes per state
    iterations: np.ndarray  # [S] loop iterations per state


def variants(case: Case, pop_widths=POP_WIDTHS) -> dict[str, Callable]:
    """name -> jitted ``fn(x, warm) -> SearchResult`` for every search compared."""
    import firhc_jax as fj

    p = case.problem
    out = {
        "sdfs": lambda x, w: fj.sdfs(p, x),
        "sdfs warm": lambda x, w: fj.sdfs(p, x, warm_start=w),
        "exhaustive dfs": lambda x, w: fj.exhaustive(p, x, method="dfs"),
        "exhaustive levels": lambda x, w: fj.exhaustive(p, x),
    }
    for k in pop_widths[1:]:
        out[f"sdfs K={k}"] = lambda x, w, k=k: fj.sdfs(p, x, pop_width=k)
    return {name: jax.jit(fn) for name, fn in out.items()}


def time_search(fn, case: Case, rows: np.ndarray, repeats: int) -> Timing:
    """Time ``fn`` on ``case.states[rows]``, warm-started from the previous state's solution shifted."""
    warm = np.concatenate([case.reference[:, 1:], case.reference[:, -1:]], axis=1)
    warm = np.concatenate([warm[-1:], warm[:-1]])  # state i gets state i-1's solution, shifted
    args = [(jnp.asarray(case.states[i]), jnp.asarray(warm[i], jnp.int32)) for i in rows]
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args[0]))
    first = time.perf_counter() - t0
    totals, results = [], []
    each = np.full(len(args), np.inf)
    for _ in range(repeats):
        total, results = 0.0, []
        for i, a in enumerate(args):
            t0 = time.perf_counter()
            results.append(jax.block_until_ready(fn(*a)))
            dt = time.perf_counter() - t0
            total += dt
            each[i] = min(each[i], dt)
        totals.append(total)
    seconds = statistics.median(totals)
    return Timing(seconds, max(first - seconds / len(args), 0.0), float(each.max()),
                  np.array([int(r.nodes) for r in results]), np.array([int(r.iterations) for r in results]))


def subset(case: Case, max_nodes: float) -> np.ndarray:
    """Evenly spaced state indices so that an exhaustive search visits at most ``max_nodes`` in all;
    empty when even one state's tree exceeds it (the exhaustive columns are then skipped)."""
    per_state = case.problem.tree_size()
    if per_state > max_nodes:
        return np.zeros(0, int)
    count = int(max(1, min(len(case.states), max_nodes // per_state)))
    return np.unique(np.linspace(0, len(case.states) - 1, count).round().astype(int))


# ---------------------------------------------------------------------------
# Tables 2 and 3
# ---------------------------------------------------------------------------

def table_row(case: Case, repeats: int, max_es_nodes: float, pop_widths=POP_WIDTHS) -> dict:
    fns = variants(case, pop_widths)
    every = np.arange(len(case.states))
    some = subset(case, max_es_nodes)
    full = {name: _announced(name, fn, case, every, repeats)
            for name, fn in fns.items() if not name.startswith("exhaustive")}
    tree = case.problem.tree_size()
    sd = full["sdfs"]
    S, s = len(every), len(some)
    if s:
        part = {name: _announced(name, fns[name], case, some, repeats)
                for name in ("sdfs", "exhaustive dfs", "exhaustive levels")}
        assert np.all(part["exhaustive levels"].nodes == tree) and np.all(part["exhaustive dfs"].nodes == tree)
        es = {"C_dfs_pct": 100 * part["sdfs"].seconds / part["exhaustive dfs"].seconds,
              "C_levels_pct": 100 * part["sdfs"].seconds / part["exhaustive levels"].seconds,
              "dfs_ms": 1e3 * part["exhaustive dfs"].seconds / s,
              "levels_ms": 1e3 * part["exhaustive levels"].seconds / s}
    else:  # one exhaustive search alone would exceed the node budget: no Point C (say so, never guess)
        part = {}
        es = {"C_dfs_pct": None, "C_levels_pct": None, "dfs_ms": None, "levels_ms": None}
    widths = {k: full["sdfs" if k == 1 else f"sdfs K={k}"].seconds for k in pop_widths}
    best_k = min(widths, key=widths.get)
    return {
        "plant": case.plant, "N": case.horizon, "steps": S, "es_steps": s,
        "A": tree, "B_max": int(sd.nodes.max()), "B_min": int(sd.nodes.min()), "B_mean": float(sd.nodes.mean()),
        **es, "sdfs_ms": 1e3 * sd.seconds / S, "sdfs_max_ms": 1e3 * sd.slowest,
        "us_per_iteration": 1e6 * sd.seconds / sd.iterations.sum(),
        "warm_nodes_mean": float(full["sdfs warm"].nodes.mean()), "warm_ms": 1e3 * full["sdfs warm"].seconds / S,
        "best_pop_width": best_k, "best_pop_width_ms": 1e3 * widths[best_k] / S,
        "compile_s": {name: round(t.compile_s, 3) for name, t in {**full, **part}.items()},
    }


def _announced(name: str, fn, case: Case, rows: np.ndarray, repeats: int) -> Timing:
    """``time_search``, saying on stderr which search it compiles and times."""
    with stage(f"{case.plant} N = {case.horizon}: {name} (compiling, then {repeats} x {len(rows)} searches)"):
        return time_search(fn, case, rows, repeats)


def tables_markdown(rows: list[dict], bound: bool = False, quick: bool = False) -> str:
    """Tables 2 and 3 of ``rows``; ``quick``: of a smoke run, labelled as one above each table."""
    lines = []
    seconds = QUICK_SECONDS if quick else SECONDS
    for plant, title in (("hopper", f"Table 2: hopper, {seconds['hopper']:g} s closed loop"),
                         ("tanks", f"Table 3: three tanks, {seconds['tanks']:g} s closed loop")):
        mine = [r for r in rows if r["plant"] == plant]
        if not mine:
            continue
        stat = PAPER_B[plant]
        lines += [f"### {title}{', sDFS with the lower bound (docs/guide/bounds.md)' if bound else ''}", "",
                  *([f"**{SMOKE}.**", ""] if quick else []),
                  f"| N | A ours (paper) | B max/{stat} ours (paper) | B {'min' if stat == 'mean' else 'mean'} | "
                  "C vs ES-dfs ours (paper) | C vs ES-levels "
                  "| sDFS ms/step | ES-dfs ms | ES-levels ms | us/iter | warm nodes / ms | fastest K (ms) | ES steps |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in mine:
            paper = PAPER[plant].get(r["N"])
            pa, pb, pcs = "-", "-", "-"
            if paper:
                pa, pb = f"{paper[0]:,}", f"{paper[1]:,}/{paper[2]:,}"
                pcs = f"{paper[3]}%" if paper[3] is not None else "-"
            no_es = "over budget" if r["C_dfs_pct"] is None else None

            def es(key, spec, unit="", r=r, no_es=no_es):
                return no_es or f"{format(r[key], spec)}{unit}"

            second, other = (f"{r['B_min']:,}", f"{r['B_mean']:.0f}") if stat == "min" else \
                (f"{r['B_mean']:,.0f}", f"{r['B_min']:,}")
            lines.append(
                f"| {r['N']} | {r['A']:,} ({pa}) | {r['B_max']:,}/{second} ({pb}) | "
                f"{other} | {es('C_dfs_pct', '.2f', '%')} ({pcs}) | {es('C_levels_pct', '.2f', '%')} | "
                f"{r['sdfs_ms']:.3f} | {es('dfs_ms', '.2f')} | {es('levels_ms', '.2f')} | "
                f"{r['us_per_iteration']:.2f} | "
                f"{r['warm_nodes_mean']:.0f} / {r['warm_ms']:.3f} | "
                f"{r['best_pop_width']} ({r['best_pop_width_ms']:.3f}) | {r['es_steps']}/{r['steps']} |")
        lines.append("")
    lines += [
        "A: exhaustive nodes per step (checked equal to the nodes both exhaustive searches computed). "
        "B: sDFS (pop_width 1, the paper's algorithm) nodes per step over the run; the paper gives the maximum "
        "and minimum for the hopper (Table 2), the maximum and mean for the tanks (Table 3). "
        "C: total sDFS search time / total exhaustive search time on the same steps, against the exhaustive "
        "depth-first search on the sDFS machinery (like for like with the paper) and against the vectorised "
        "level-by-level search (our strongest baseline). ES steps: the steps the exhaustive searches were timed "
        "on (evenly spaced when the full run would take too long; none, and no Point C: 'over budget', when one "
        "exhaustive search alone exceeds --max-es-nodes); the sDFS time in C is over the same steps. "
        "warm: sDFS seeded with the previous step's solution shifted. fastest K: the pop_width with the least "
        "total time. Compile times are in the JSON output.", ""]
    return "\n".join(lines)


def run_tables(args) -> int:

    # --quick: Table 3 at its first horizon only (about 6 compilations), unless --plants says otherwise.
    asked = args.plants or (["tanks"] if args.quick else ["hopper", "tanks"])
    plants = [p for p in ("hopper", "tanks") if p in asked]
    chosen = {"hopper": args.hopper_horizons, "tanks": args.tanks_horizons}
    todo = [(p, n) for p in plants
            for n in (chosen[p] or (HORIZONS[p][:1] if args.quick else HORIZONS[p]))]
    widths = tuple(args.pop_widths) if args.pop_widths else (POP_WIDTHS[:1] if args.quick else POP_WIDTHS)
    if widths[0] != 1 or len(set(widths)) != len(widths):
        raise SystemExit(f"bench tables: --pop-widths must start with 1 (the paper's sDFS) and not repeat, "
                         f"got {widths}")
    rows = []
    with tqdm(total=len(todo), desc="tables", file=sys.stderr) as bar:
        for plant, n in todo:
            with stage(f"{plant} N = {n}: the closed loop that gives the states searched"):
                seconds = (QUICK_SECONDS if args.quick else SECONDS)[plant]
                case = (hopper_case(n, seconds, args.bound) if plant == "hopper"
                        else tanks_case(n, seconds, args.bound))
            rows.append(table_row(case, 1 if args.quick else args.repeats, args.max_es_nodes, widths))
            bar.update(1)
    text = (f"{SMOKE}.\n\n" if args.quick else "") + f"Measured on {machine()}, float64, " \
        f"{time.strftime('%Y-%m-%d')}.\n\n" + tables_markdown(rows, args.bound, args.quick)
    _write(args.out, "tables-bound" if args.bound else "tables", text, rows)
    print(text)
    return 0


# ---------------------------------------------------------------------------
# Throughput profile
# ---------------------------------------------------------------------------

def profile_case(case: Case, repeats: int, batches, max_es_nodes: float, pop_widths=POP_WIDTHS) -> list[dict]:
    """Nodes/s and us/iteration per search, and batched (vmap) solves/s and nodes/s
    (the batched exhaustive search only for batches within ``max_es_nodes`` nodes)."""
    import firhc_jax as fj

    fns = variants(case, pop_widths)
    rows_idx = np.arange(len(case.states))
    out = []
    names = ["sdfs" if k == 1 else f"sdfs K={k}" for k in pop_widths] + ["exhaustive dfs", "exhaustive levels"]
    for name in names:
        t = _announced(name, fns[name], case, rows_idx, repeats)
        out.append({"plant": case.plant, "N": case.horizon, "search": name, "batch": 1,
                    "pop_width": int(name.split("=")[1]) if "K=" in name else (1 if name == "sdfs" else None),
                    "nodes_per_s": t.nodes.sum() / t.seconds, "solves_per_s": len(rows_idx) / t.seconds,
                    "us_per_iteration": None if name == "exhaustive levels" else 1e6 * t.seconds / t.iterations.sum()})
    p = case.problem
    for name, solve in (("sdfs", lambda x: fj.sdfs(p, x)), ("exhaustive levels", lambda x: fj.exhaustive(p, x))):
        batched = jax.jit(jax.vmap(solve))
        for b in batches:
            if name != "sdfs" and b * p.tree_size() > max_es_nodes:
                continue
            X = jnp.asarray(case.states[np.arange(b) % len(case.states)])
            with stage(f"{case.plant} N = {case.horizon}: jax.vmap of {name} over {b} states (compiling)"):
                jax.block_until_ready(batched(X))
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                r = jax.block_until_ready(batched(X))
                times.append(time.perf_counter() - t0)
            t = statistics.median(times)
            out.append({"plant": case.plant, "N": case.horizon, "search": f"vmap {name}", "batch": b,
                        "pop_width": 1 if name == "sdfs" else None, "nodes_per_s": float(np.sum(r.nodes)) / t,
                        "solves_per_s": b / t, "us_per_iteration": None})
    return out


def horizon_sweep(make: Callable[[int], Case], horizons, repeats: int, max_es_nodes: float) -> list[dict]:
    """Time per step against horizon for sDFS and both exhaustive searches."""
    out = []
    for n in horizons:
        case = make(n)
        fns = variants(case, POP_WIDTHS[:1])
        rows = subset(case, max_es_nodes)
        for name in ("sdfs", "exhaustive dfs", "exhaustive levels"):
            t = _announced(name, fns[name], case, rows, repeats)
            out.append({"plant": case.plant, "N": n, "search": name, "ms_per_step": 1e3 * t.seconds / len(rows)})
    return out


def _integer_log_axis(axis, values) -> None:
    """A log axis of counts labelled with the counts themselves ("2", not "2x10^0"), and nothing between them."""
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator, StrMethodFormatter

    axis.set_major_locator(FixedLocator(sorted(set(values))))
    axis.set_major_formatter(StrMethodFormatter("{x:,.0f}"))
    axis.set_minor_locator(NullLocator())
    axis.set_minor_formatter(NullFormatter())


def _value_log_axis(axis) -> None:
    """A log axis of measured values labelled where matplotlib labels one, in plain numbers ("0.2", "20,000", not
    "2x10^-1")."""
    from matplotlib.ticker import LogFormatter

    class Plain(LogFormatter):
        def __call__(self, x, pos=None):
            return "" if not super().__call__(x, pos) else f"{x:,.0f}" if x >= 10 else f"{x:.3g}"

    axis.set_major_formatter(Plain())
    axis.set_minor_formatter(Plain(labelOnlyBase=False))


def plot_profile(profile: list[dict], sweep: list[dict], out: Path, smoke: bool = False) -> list[Path]:
    """``throughput.png`` and ``time_vs_horizon.png`` in ``out``; ``smoke``: titled as a smoke run's."""
    from ._plot import subplots

    paths = []
    plants = sorted({r["plant"] for r in profile})
    fig, (ax1, ax2) = subplots(1, 2, figsize=(11, 4))
    for plant in plants:
        pw = [r for r in profile if r["plant"] == plant and r["search"].startswith("sdfs")]
        ax1.plot([r["pop_width"] for r in pw], [r["nodes_per_s"] for r in pw], "o-", label=plant)
        for name in ("vmap sdfs", "vmap exhaustive levels"):
            bt = [r for r in profile if r["plant"] == plant and r["search"] == name]
            ax2.plot([r["batch"] for r in bt], [r["nodes_per_s"] for r in bt], "o-" if "sdfs" in name else "s--",
                     label=f"{plant}: jax.vmap of {'fj.sdfs' if 'sdfs' in name else 'fj.exhaustive (levels)'}")
    ax1.set(xscale="log", yscale="log", xlabel="pop_width K", ylabel="nodes / s", title="sDFS, one state at a time")
    ax2.set(xscale="log", yscale="log", xlabel="batch size B", ylabel="nodes / s", title="vmap over B states")
    for ax in (ax1, ax2):
        _integer_log_axis(ax.xaxis, [x for line in ax.get_lines() for x in line.get_xdata()])
        _value_log_axis(ax.yaxis)
    ax1.legend(fontsize=8)
    ax2.legend(fontsize=7)
    _smoke_title(fig, smoke)
    fig.tight_layout()
    paths.append(out / "throughput.png")
    fig.savefig(paths[-1], dpi=100)

    fig, axes = subplots(1, len({r["plant"] for r in sweep}), figsize=(11, 4), squeeze=False)
    for ax, plant in zip(axes[0], sorted({r["plant"] for r in sweep}), strict=True):
        for name, style in (("sdfs", "o-"), ("exhaustive dfs", "s--"), ("exhaustive levels", "^:")):
            rs = [r for r in sweep if r["plant"] == plant and r["search"] == name]
            ax.plot([r["N"] for r in rs], [r["ms_per_step"] for r in rs], style, label=name)
        ax.set(yscale="log", xlabel="horizon N", ylabel="ms per decision (median)", title=plant)
        ax.xaxis.get_major_locator().set_params(integer=True)
        _value_log_axis(ax.yaxis)
        ax.legend(fontsize=8)
    _smoke_title(fig, smoke)
    fig.tight_layout()
    paths.append(out / "time_vs_horizon.png")
    fig.savefig(paths[-1], dpi=100)
    return paths


def _smoke_title(fig, smoke: bool) -> None:
    if smoke:
        fig.suptitle(SMOKE, color="tab:red", fontsize=9)


def run_throughput(args) -> int:

    repeats = 1 if args.quick else args.repeats
    if args.quick:
        cases = [lambda: synthetic_case(3, count=4)]
        sweep_plan = [(lambda n: synthetic_case(n, count=2), (2, 3))]
        batches, widths = (1, 8), POP_WIDTHS[:2]
    else:
        cases = [lambda: hopper_case(6), lambda: tanks_case(4, 40.0), lambda: synthetic_case(5),
                 lambda: synthetic_case(5, work=50)]
        sweep_plan = [(lambda n: hopper_case(n, 0.5), (4, 5, 6, 7, 8)), (lambda n: tanks_case(n, 40.0), (3, 4, 5)),
                      (lambda n: synthetic_case(n), (3, 4, 5))]
        batches, widths = BATCHES, POP_WIDTHS
    profile, sweep = [], []
    with tqdm(total=len(cases) + len(sweep_plan), desc="throughput", file=sys.stderr) as bar:
        for make in cases:
            profile += profile_case(make(), repeats, batches, args.max_es_nodes, widths)
            bar.update(1)
        for make, horizons in sweep_plan:
            sweep += horizon_sweep(make, horizons, repeats, args.max_es_nodes)
            bar.update(1)
    lines = [*([f"**{SMOKE}.**", ""] if args.quick else []), f"Measured on {machine()}, float64.", "",
             "| plant | N | search | batch | nodes/s | solves/s | us/iteration |", "|---|---|---|---|---|---|---|"]
    for r in profile:
        us = f"{r['us_per_iteration']:.2f}" if r["us_per_iteration"] else ""
        lines.append(f"| {r['plant']} | {r['N']} | {r['search']} | {r['batch']} | {r['nodes_per_s']:,.0f} | "
                     f"{r['solves_per_s']:,.1f} | {us} |")
    lines += ["", "| plant | N | search | ms/step |", "|---|---|---|---|"]
    lines += [f"| {r['plant']} | {r['N']} | {r['search']} | {r['ms_per_step']:.3f} |" for r in sweep]
    text = "\n".join(lines) + "\n"
    paths = plot_profile(profile, sweep, args.out, smoke=args.quick)
    _write(args.out, "throughput", text, profile + sweep)
    print(text)
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _write(out: Path, stem: str, markdown: str, rows: list[dict]) -> None:
    (out / f"{stem}.md").write_text(markdown)
    (out / f"{stem}.json").write_text(json.dumps(rows, indent=1, default=float))
    keys = sorted({k for r in rows for k in r if not isinstance(r[k], dict)})
    with open(out / f"{stem}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {out / (stem + '.md')}, .json, .csv")


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="the paper's Tables 2 and 3, and throughput profiles",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="bench_command", metavar="WHAT", required=True)
    for name, func, help_ in (("tables", run_tables, "Tables 2 (hopper) and 3 (tanks), paper figures beside ours"),
                              ("throughput", run_throughput, "nodes/s by pop_width and batch size; time vs horizon")):
        q = sub.add_parser(name, help=help_, description=help_)
        q.add_argument("--quick", action="store_true",
                       help="a smoke run: short runs, few cases, timed once; labelled so, its figures mean nothing")
        q.add_argument("--out", type=output_dir, default=f"out/bench-{name}", help="output folder")
        q.add_argument("--repeats", type=number(int, 1, MAX_REPEATS), default=3,
                       help=f"timing repeats, median taken (default 3, at most {MAX_REPEATS})")
        q.add_argument("--max-es-nodes", type=number(float, 0, MAX_ES_NODES), default=3e7,
                       help=f"exhaustive searches are timed on evenly spaced steps visiting at most this many "
                            f"nodes in all (default 3e7; 0: none; at most {MAX_ES_NODES:g})")
        if name == "tables":
            q.add_argument("--plants", nargs="+", choices=("hopper", "tanks"), default=None,
                           help="which tables: hopper (Table 2), tanks (Table 3); default both (--quick: tanks)")
            q.add_argument("--hopper-horizons", type=number(int, 1, 12), nargs="+", metavar="N",
                           help="hopper horizons (default 5 6 7 8; --quick: the first)")
            q.add_argument("--tanks-horizons", type=number(int, 1, 8), nargs="+", metavar="N",
                           help="tanks horizons (default 3 4 5 6; --quick: the first)")
            q.add_argument("--pop-widths", type=number(int, 1, 64), nargs="+", metavar="K",
                           help="sDFS pop widths timed, the first must be 1 (default 1 2 4 8 16; --quick: 1)")
            q.add_argument("--bound", action="store_true",
                           help="sDFS variants with the applications' lower bounds (docs/guide/bounds.md); the "
                                "exhaustive searches are unchanged")
        q.set_defaults(func=_prepared(func))


def _prepared(func):
    """``func`` run in float64, into its output folder (created first)."""
    def run(args):
        jax.config.update("jax_enable_x64", True)
        args.out.mkdir(parents=True, exist_ok=True)
        return func(args)
    return run
