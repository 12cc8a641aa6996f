"""``python -m firhc_jax profile MODULE:FUNCTION``: expansion throughput of
your own problem on this machine (``fj.profile``).

    python -m firhc_jax profile mymodels:profile_case --out out/profile

``FUNCTION`` takes no arguments and returns ``(problem, states)`` or
``(problem, states, params)``: the problem, the ``[S, n]`` states to search
from (e.g. a closed loop's) and optional per-state parameters (leading axis
S). The command prints one row per search setting, names the fastest, and
writes ``profile.json`` (the rows and the machine) and ``profile.png``
(solves/s and nodes/s per setting) into ``--out``.
"""
from __future__ import annotations

import json
import platform
from pathlib import Path

from ._args import number, output_dir
from ._user_code import import_user_module, user_code

MAX_LANES = 4096  # slots of one solve_batch: each holds a stack of sDFS nodes
MAX_REPEATS = 100
MAX_EXHAUSTIVE_NODES = 1_000_000_000  # once per repeat: minutes at the rates of docs/guide/batches.md


HELP = "time every search setting on your own problem and states; name the fastest"
DESCRIPTION = ("fj.profile on the problem and states returned by MODULE:FUNCTION (a function without "
               "arguments returning (problem, states) or (problem, states, params)): fj.sdfs at several "
               "pop widths and fj.exhaustive, one state per call, and fj.solve_batch at several lane "
               "counts, all states at once. Prints the table and the fastest setting; writes "
               "profile.json and profile.png into --out.")


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
                   help=f"timed calls per setting, median (default 3, at most {MAX_REPEATS})")
    p.add_argument("--max-exhaustive-nodes", type=number(int, 1, MAX_EXHAUSTIVE_NODES), default=10_000_000,
                   help=f"fj.exhaustive runs on evenly spaced states visiting at most this many nodes in all "
                        f"(default 10000000, at most {MAX_EXHAUSTIVE_NODES})")
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


def markdown(rows: list[dict]) -> str:
    lines = ["| setting | states | solves/s | nodes/s | us/iteration | nodes | compile (s) | |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['setting']} | {r['states']} | {r['solves_per_second']:,.1f} | "
                     f"{r['nodes_per_second']:.3g} | {r['us_per_iteration']:.2f} | {r['nodes']:,} | "
                     f"{r['compile_s']:.2f} | {'fastest' if r['fastest'] else ''} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str) -> None:
    """Solves/s and nodes/s per setting, the fastest highlighted."""
    from matplotlib.patches import Patch
    from matplotlib.ticker import NullFormatter

    from ._plot import subplots

    fig, (ax1, ax2) = subplots(1, 2, figsize=(11, 0.45 * len(rows) + 1.8))
    names = [r["setting"] for r in rows]
    colors = ["tab:red" if r["fastest"] else "tab:blue" for r in rows]
    for ax, key, label in ((ax1, "solves_per_second", "solves / s"), (ax2, "nodes_per_second", "nodes / s")):
        ax.barh(names, [r[key] for r in rows], color=colors)
        ax.set(xscale="log", xlabel=label)
        ax.xaxis.set_minor_formatter(NullFormatter())  # decades only: minor labels overlap
        ax.invert_yaxis()
    ax2.set_yticklabels([])
    fig.legend(handles=[Patch(color="tab:red", label="fastest (most solves / s)"),
                        Patch(color="tab:blue", label="the other settings")], fontsize=8, loc="lower center",
               ncol=2, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.3 / fig.get_figheight(), 1, 1))  # 0.3 in below the axes for the legend
    fig.savefig(path, dpi=100)


def run(args) -> int:
    """Profile the case named by ``args.case``; returns the exit status."""
    import jax

    jax.config.update("jax_enable_x64", not args.float32)
    problem, states, params = load_case(args.case, args.debug)
    args.out.mkdir(parents=True, exist_ok=True)  # writable: checked by output_dir when the arguments were parsed
    from .. import profile
    from ..distributed import usable_cores

    try:
        rows = profile(problem, states, params, pop_widths=args.pop_widths, lanes=args.lanes, repeats=args.repeats,
                       max_exhaustive_nodes=args.max_exhaustive_nodes, progress=True)
    except (TypeError, ValueError) as e:  # states or params the search refuses: its message, no traceback
        raise SystemExit(f"profile: {e}") from None
    best = next(r for r in rows if r["fastest"])
    machine = (f"{platform.machine()}, {usable_cores()} usable cores, {jax.devices()[0].platform}, "
               f"jax {jax.__version__}, {'float32' if args.float32 else 'float64'}")
    title = f"{args.case}: N = {problem.horizon}, M = {problem.num_controls}, {len(states)} states; {machine}"
    print(f"# {title}\n\n{markdown(rows)}\n")
    print(f"fastest: {best['setting']} ({best['solves_per_second']:,.1f} solves/s, "
          f"{best['nodes_per_second']:.3g} nodes/s)")
    (args.out / "profile.json").write_text(json.dumps({"case": args.case, "machine": machine, "rows": rows},
                                                      indent=1))
    plot(rows, args.out / "profile.png", title)
    print(f"wrote {args.out / 'profile.json'}, {args.out / 'profile.png'}")
    return 0
