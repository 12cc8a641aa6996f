"""``python -m firhc_jax profile MODULE:FUNCTION``: expansion throughput of
your own problem on this machine (``fj.profile``).

    python -m firhc_jax profile mymodels:profile_case --out out/profile

``FUNCTION`` takes no arguments and returns ``(problem, states)`` or
``(problem, states, params)``: the problem, the ``[S, n]`` states to search
from (e.g. a closed loop's) and optional per-state parameters (leading axis
S). The command prints one row per search setting (the defaults marked,
the median and range of the interleaved runs), names the fastest or says
that there is no clear winner, splits a node's time into the problem's
callables, says how long compiling took, and writes ``profile.json`` (the
rows, the callables and the machine) and ``profile.png`` (solves/s, nodes/s
and ns per callable) into ``--out``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._args import number, output_dir
from ._user_code import import_user_module, user_code

MAX_LANES = 4096  # slots of one solve_batch: each holds a stack of sDFS nodes
MAX_REPEATS = 100
MAX_EXHAUSTIVE_NODES = 1_000_000_000  # once per repeat: minutes at the rates of docs/guide/batches.md
LEAVES = ("terminal", "terminal_cost")  # callables a search evaluates at depth N only


HELP = "time every search setting on your own problem and states; name the fastest, if one is"
DESCRIPTION = ("fj.profile on the problem and states returned by MODULE:FUNCTION (a function without "
               "arguments returning (problem, states) or (problem, states, params)): fj.sdfs at several "
               "pop widths and fj.exhaustive, one state per call, and fj.solve_batch at its default and at "
               "several lane counts, all states at once, interleaved over --repeats rounds; and each callable "
               "of the problem per node. Prints the table, the fastest setting (or no clear winner) and "
               "the time per callable; writes profile.json and profile.png into --out.")


def register(subparsers) -> None:
    """Add the ``profile`` subcommand."""
    p = subparsers.add_parser("profile", help=HELP, description=DESCRIPTION)
    p.add_argument("case", metavar="MODULE:FUNCTION", help="function returning (problem, states[, params])")
    p.add_argument("--out", type=output_dir, default=Path("out/profile"),
                   help="output folder (default out/profile), checked before any work")
    p.add_argument("--pop-widths", type=number(int, 1, 64), nargs="+", metavar="K", default=[1, 2, 4, 8],
                   help="fj.sdfs pop widths (default 1 2 4 8)")
    p.add_argument("--lanes", type=number(int, 1, MAX_LANES), nargs="+", metavar="L", default=[16, 64, 256],
                   help=f"fj.solve_batch lane counts (default 16 64 256, each at most {MAX_LANES})")
    p.add_argument("--repeats", type=number(int, 1, MAX_REPEATS), default=3,
                   help=f"timed rounds, each calling every setting once; median and range (default 3, at most "
                        f"{MAX_REPEATS})")
    p.add_argument("--max-exhaustive-nodes", type=number(int, 1, MAX_EXHAUSTIVE_NODES), default=10_000_000,
                   help=f"fj.exhaustive runs on evenly spaced states visiting at most this many nodes in all "
                        f"(default 10000000, at most {MAX_EXHAUSTIVE_NODES})")
    p.add_argument("--controller", action="store_true",
                   help="name the fastest of the settings that run one decision per call (fj.sdfs, fj.exhaustive): "
                        "what a FIRHC deciding once per sampling period runs; solve_batch is still timed")
    p.add_argument("--float32", action="store_true", help="float32 (default float64)")
    p.add_argument("--debug", action="store_true",
                   help="let an error in MODULE through with its traceback (default: one line)")
    p.set_defaults(func=run)


def load_case(spec: str, debug: bool = False):
    """``(problem, states, params)`` from ``MODULE:FUNCTION``; ``SystemExit``
    with a one-line message when it cannot be had (``debug``: the user's
    module's own exception and traceback)."""
    import firhc_jax as fj

    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise SystemExit(f"profile: expected MODULE:FUNCTION (e.g. mymodels:profile_case), got {spec!r}")
    mod = import_user_module(module, f"profile: cannot import module {module!r}:", debug)
    func = getattr(mod, name, None)
    if not callable(func):
        raise SystemExit(f"profile: module {module!r} has no function {name!r}")
    with user_code(f"profile: {spec}() raised", debug):
        case = func()
    if not isinstance(case, tuple) or len(case) not in (2, 3) or not isinstance(case[0], fj.Problem):
        got = type(case).__name__ if not isinstance(case, tuple) else f"a tuple of {len(case)}"
        raise SystemExit(f"profile: {spec}() must return (problem, states) or (problem, states, params) with "
                         f"problem a firhc_jax.Problem; got {got}")
    return case if len(case) == 3 else (*case, None)


def _number(v: float) -> str:
    """A rate or a time, short: 1,234 / 12.3 / 0.0123."""
    return f"{v:,.0f}" if v >= 100 else f"{v:.3g}"


def _short(v: float) -> str:
    """A tick or bar value in few characters: 20, 5k, 1.5M, 0.5."""
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if v >= scale:
            return f"{v / scale:.3g}{suffix}"
    return f"{v:.3g}"


def _rates(r: dict) -> tuple[float, float]:
    """The slowest and fastest run's solves per second."""
    return r["states"] / r["seconds_max"], r["states"] / r["seconds_min"]


def markdown(rows: list[dict]) -> str:
    lines = ["| setting | states | solves/s median | solves/s range | nodes/s | us/iteration | nodes | compile (s) | |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        notes = [n for n, on in (("default", r["default"]), ("fastest", r["fastest"]),
                                 ("within noise", r["within_noise"] and not r["fastest"])) if on]
        low, high = _rates(r)
        lines.append(f"| {r['setting']} | {r['states']} | {_number(r['solves_per_second'])} | {_number(low)} - "
                     f"{_number(high)} | {r['nodes_per_second']:.3g} | {r['us_per_iteration']:.2f} | {r['nodes']:,} | "
                     f"{r['compile_s']:.2f} | {', '.join(notes)} |")
    return "\n".join(lines)


def node_table(profile) -> str:
    """Each callable's ns per child, and the default one-state search's ns per node for comparison."""
    total = sum(c["ns"] for c in profile.node_costs)
    lines = [f"| callable (vmapped over {profile.node_costs[0]['children']:,} children) | ns per child median | "
             "range | share |", "|---|---:|---:|---:|"]
    for c in profile.node_costs:
        leaves = " (leaves only)" if c["callable"] in LEAVES else ""
        lines.append(f"| {c['callable']}{leaves} | {c['ns']:.3g} | {c['ns_min']:.3g} - {c['ns_max']:.3g} | "
                     f"{c['ns'] / total:.0%} |")
    one = next((r for r in profile if r["solver"] == "sdfs" and r["default"]), None)
    if one is not None and one["nodes"]:
        lines.append(f"\na node of {one['setting']} takes {1e9 * one['seconds'] / one['nodes']:.3g} ns in all "
                     "(the callables above, and the search's own work)")
    return "\n".join(lines)


def verdict(profile) -> str:
    """The fastest setting, against the default of its kind, or "no clear winner"."""
    rows = list(profile)
    best = next(r for r in rows if r["fastest"])
    default = next((r for r in rows if r["default"] and r["solver"] == best["solver"]),
                   next(r for r in rows if r["default"]))
    rate = f"{_number(best['solves_per_second'])} solves/s"
    if profile.for_controller:
        rate += ", of the settings of one decision per call, as a controller decides"
    if profile.repeats == 1:
        return (f"fastest: {best['setting']} ({rate} in one run; with one run per setting the noise is not "
                "measured: --repeats 3 or more tells whether it wins clearly)")
    if not profile.clear_winner:
        tied = [r["setting"] for r in rows if r["within_noise"] and not r["fastest"]]
        return (f"no clear winner: {best['setting']} ({rate} median) is within the noise of {', '.join(tied)} "
                f"(their runs' ranges overlap over {profile.repeats} rounds)")
    versus = "" if default is best else (f", {best['solves_per_second'] / default['solves_per_second']:.2f}x "
                                         f"{default['setting']}, the default")
    return (f"fastest: {best['setting']} ({rate}, {best['nodes_per_second']:.3g} nodes/s{versus}; its slowest of "
            f"{profile.repeats} runs beats every other setting's fastest)")


def _log_axis(ax, values) -> None:
    """A log axis with a readable label on every tick: 1-2-5 steps over a few decades, decades beyond."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    low, high = min(values), max(values)
    subs = (1.0, 2.0, 5.0) if high / low < 1e3 else (1.0,)
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=subs))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: _short(v)))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlim(low / 2, high * 3)  # room for the values written beside the bars


def figure(profile, title: str):
    """A ``Figure``: solves/s (the range of the runs as error bars) and nodes/s per setting, each value written
    beside its bar, the fastest highlighted, the defaults named; below, each callable's ns per child."""
    from matplotlib.patches import Patch

    from ._plot import subplots

    rows = list(profile)
    fig, axes = subplots(2, 2, figsize=(12, 0.45 * (len(rows) + len(profile.node_costs)) + 3.0),
                         gridspec_kw={"height_ratios": [len(rows), max(len(profile.node_costs), 2)]})
    (ax1, ax2), (ax3, ax4) = axes
    names = [r["setting"] + (" (default)" if r["default"] and "default" not in r["setting"] else "") for r in rows]
    colors = ["tab:red" if r["fastest"] else "tab:blue" for r in rows]
    rates = [r["solves_per_second"] for r in rows]
    low, high = zip(*(_rates(r) for r in rows), strict=True)
    ax1.barh(names, rates, color=colors, xerr=[np.subtract(rates, low), np.subtract(high, rates)], capsize=3)
    for y, (r, end) in enumerate(zip(rows, high, strict=True)):
        noise = " (within noise)" if r["within_noise"] and not r["fastest"] else ""
        ax1.text(end * 1.1, y, _short(r["solves_per_second"]) + noise, va="center", fontsize=8)
    _log_axis(ax1, list(low) + list(high))
    if any(r["within_noise"] and not r["fastest"] for r in rows):
        ax1.set_xlim(right=max(high) * 15)  # room for "(within noise)"
    ax1.set_xlabel(f"solves / s (median; bars: range of {profile.repeats} runs)")
    nodes = [r["nodes_per_second"] for r in rows]
    ax2.barh(names, nodes, color=colors)
    for y, v in enumerate(nodes):
        ax2.text(v * 1.1, y, _short(v), va="center", fontsize=8)
    _log_axis(ax2, nodes)
    ax2.set_xlabel("nodes / s (median)")
    ax2.set_yticklabels([])
    costs = profile.node_costs
    ns = [c["ns"] for c in costs]
    ax3.barh([c["callable"] + (" (leaves)" if c["callable"] in LEAVES else "") for c in costs], ns, color="tab:gray",
             xerr=[np.subtract(ns, [c["ns_min"] for c in costs]), np.subtract([c["ns_max"] for c in costs], ns)],
             capsize=3)
    for y, c in enumerate(costs):
        ax3.text(c["ns_max"] * 1.1, y, f"{c['ns']:.3g}", va="center", fontsize=8)
    _log_axis(ax3, [c["ns_min"] for c in costs] + [c["ns_max"] for c in costs])
    ax3.set_xlabel(f"ns per child, each callable vmapped over {costs[0]['children']:,} children")
    for ax in (ax1, ax2, ax3):
        ax.invert_yaxis()
        ax.grid(axis="x", alpha=0.3)
    ax4.axis("off")
    ax4.text(0.0, 0.5, f"{verdict(profile)}\n\ncompiling: {profile.compile_seconds:.1f} s of the "
             f"{profile.seconds:.1f} s this profile took", wrap=True, va="center", fontsize=9)
    fig.legend(handles=[Patch(color="tab:red", label="fastest (most solves / s)"),
                        Patch(color="tab:blue", label="the other settings")], fontsize=8, loc="lower center",
               ncol=2, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.3 / fig.get_figheight(), 1, 1))  # 0.3 in below the axes for the legend
    return fig


def run(args) -> int:
    """Profile the case named by ``args.case``; returns the exit status."""
    import jax

    jax.config.update("jax_enable_x64", not args.float32)
    problem, states, params = load_case(args.case, args.debug)
    args.out.mkdir(parents=True, exist_ok=True)  # writable: checked by output_dir when the arguments were parsed
    from .. import profile
    from ._machine import machine

    try:
        result = profile(problem, states, params, pop_widths=args.pop_widths, lanes=args.lanes,
                         repeats=args.repeats, max_exhaustive_nodes=args.max_exhaustive_nodes, progress=True,
                         for_controller=args.controller)
    except (TypeError, ValueError) as e:  # states or params the search refuses: its message, no traceback
        raise SystemExit(f"profile: {e}") from None
    where = f"{machine()}, {'float32' if args.float32 else 'float64'}"
    title = f"{args.case}: N = {problem.horizon}, M = {problem.num_controls}, {len(states)} states; {where}"
    exhaustive = next((r["states"] for r in result if r["solver"] == "exhaustive"), 0)
    print(f"# {title}\n\n{markdown(result)}\n\n{verdict(result)}\n")
    subset = (f"fj.exhaustive on {exhaustive} of them" if exhaustive else "fj.exhaustive on none: one tree is larger")
    print(f"Each row's figures rest on its states column ({len(states)} states; {subset}, see "
          f"--max-exhaustive-nodes), every setting timed {result.repeats} times, interleaved with the "
          f"others. Compiling took {result.compile_seconds:.1f} s of the {result.seconds:.1f} s this profile "
          f"took.\n\n{node_table(result)}\n")
    (args.out / "profile.json").write_text(json.dumps(
        {"case": args.case, "machine": where, "rows": result, "node_costs": result.node_costs,
         "repeats": result.repeats, "clear_winner": result.clear_winner,
         "compile_seconds": result.compile_seconds, "seconds": result.seconds}, indent=1))
    figure(result, title).savefig(args.out / "profile.png", dpi=100)
    print(f"wrote {args.out / 'profile.json'}, {args.out / 'profile.png'}")
    return 0
