"""The figure of a closed-loop run (``ClosedLoop.plot``), drawn without pyplot.

One row of axes per quantity, all on one time axis (seconds when the run has ``times``, else the step
index): the states, each input on its own axes (inputs never hide one another), the nodes of each decision
and, only when the run was timed, the solve times. An input of few levels is a step line while its switches
can be told apart; over a batch of loops, or where one loop switches more often than a line can show, it is
drawn as a map of how often each level is used over time. Legends sit beside the axes, never on the data.
"""
from __future__ import annotations

import math

import numpy as np

MAX_LEVELS = 8  # an input with at most this many values is drawn level by level
MAX_SWITCHES = 150  # level changes a step line shows readably across the figure's width
MAX_COLUMNS = 200  # time windows of a level map


def draw(run, title: str, state_names, input_names):
    """The ``Figure`` of ``run`` (one loop, or B loops when ``run.batched``)."""
    from matplotlib.figure import Figure

    batched = run.batched
    lead = (lambda a: np.asarray(a)) if batched else (lambda a: np.asarray(a)[None])
    states, inputs = lead(run.states).astype(float), lead(run.inputs).astype(float)  # [B, T+1, n], [B, T, m']
    B, T = inputs.shape[:2]
    axes = "B, " if batched else ""
    state_names = _names("state_names", state_names, states.shape[2], "x", f"states [{axes}T+1, n]")
    input_names = _names("input_names", input_names, inputs.shape[2], "u", f"inputs [{axes}T, m']")
    t = np.arange(T + 1) if run.times is None else np.asarray(run.times, float)
    solve_times = 1e3 * lead(run.solve_times).astype(float)
    timed = not batched and not np.all(np.isnan(solve_times))

    heights = [2.0] + [1.0] * len(input_names) + [1.2] + [1.0] * timed
    fig = Figure(figsize=(9, 1.1 * sum(heights) + 1.0), layout="constrained")
    ax = fig.subplots(len(heights), 1, sharex=True, gridspec_kw={"height_ratios": heights})
    _states(ax[0], t, states, state_names)
    maps = [_input(ax[1 + j], t, inputs[:, :, j], name) for j, name in enumerate(input_names)]
    mapped = [j for j, mesh in enumerate(maps) if mesh is not None]
    if mapped:  # one scale for every level map, beside the first
        w = math.ceil(T / MAX_COLUMNS)
        share = (f"share of the {B} loops" if B > 1 else "share of the steps") + (f"\nin windows of {w} steps"
                                                                                  if w > 1 else "")
        bar = fig.colorbar(maps[mapped[0]], cax=ax[1 + mapped[0]].inset_axes([1.01, 0.0, 0.02, 1.0]))
        bar.set_label(share, fontsize="small")
    held = np.flatnonzero(np.asarray(lead(run.held)).any(axis=0))
    if held.size:
        for j in range(len(input_names)):
            ax[1 + j].plot(t[held], np.full(held.size, 0.04), "rx", transform=ax[1 + j].get_xaxis_transform(),
                           label=None if j else ("a loop held" if B > 1 else "held") + " (no input found)")
        _legend(ax[1], 1.16 if 0 in mapped else 1.01)  # beside the colour scale, if the first input has it
    _nodes(ax[1 + len(input_names)], t, lead(run.nodes), lead(run.fallback_nodes))
    if timed:
        ax[-1].step(t[:-1], solve_times[0], where="post", lw=0.8)
        ax[-1].set_ylabel("solve time [ms]")
    ax[-1].set_xlabel("time [s]" if run.times is not None else "step k (no dt: simulate(..., dt=) draws seconds)")
    if title or B > 1:
        shares = ", input levels as shares" if mapped else ""
        fig.suptitle(title or f"{B} closed loops: median, 10-90 % band (extremes dotted){shares}")
    return fig


def _states(ax, t, states, names) -> None:
    if states.shape[0] == 1:
        ax.plot(t, states[0], label=names, lw=0.9)
    else:
        for j, name in enumerate(names):
            _band(ax, t, states[:, :, j], name, f"C{j % 10}", steps=False)
    ax.set_ylabel("states" if states.shape[0] == 1 else f"states ({states.shape[0]} loops)")
    _legend(ax)


def _input(ax, t, values, name: str):
    """One input ``values`` ``[B, T]`` on ``ax``: its level map (returned) where a line would not do."""
    levels = np.unique(values)
    discrete = levels.size <= MAX_LEVELS
    if discrete and (values.shape[0] > 1 or np.count_nonzero(np.diff(values[0])) > MAX_SWITCHES):
        return _level_map(ax, t, values, levels, name)
    if values.shape[0] == 1:
        ax.step(t[:-1], values[0], where="post", lw=0.9)
    else:
        _band(ax, t[:-1], values, name, "C0", steps=True)
        _legend(ax)
    if discrete:
        ax.set_yticks(levels, [f"{v:g}" for v in levels])
    ax.set_ylabel(name)
    return None


def _level_map(ax, t, values, levels, name: str):
    """How often ``values`` ``[B, T]`` take each of ``levels``, per step or per window of steps."""
    T = values.shape[1]
    w = math.ceil(T / MAX_COLUMNS)
    starts = np.arange(0, T, w)
    counts = (values[:, :, None] == levels).sum(axis=0)  # [T, L] loops at each level, step by step
    share = np.add.reduceat(counts, starts, axis=0) / (values.shape[0] * np.diff(np.append(starts, T)))[:, None]
    mesh = ax.pcolormesh(t[np.append(starts, T)], np.arange(levels.size + 1) - 0.5, share.T, cmap="Blues",
                         vmin=0.0, vmax=1.0, shading="flat")
    ax.set_yticks(np.arange(levels.size), [f"{v:g}" for v in levels])
    ax.set_ylabel(name)
    return mesh


def _nodes(ax, t, nodes, fallback) -> None:
    if nodes.shape[0] == 1:
        ax.step(t[:-1], nodes[0], where="post", lw=0.8, label="constrained search")
        if fallback.any():
            ax.step(t[:-1], (nodes + fallback)[0], where="post", lw=0.8, label="with the fallback")
            _legend(ax)
    else:
        _band(ax, t[:-1], (nodes + fallback).astype(float), "nodes per decision", "C0", steps=True)
        _legend(ax)
    ax.set_ylabel("nodes")


def _legend(ax, x: float = 1.01) -> None:
    """The legend beside ``ax`` (its left edge at ``x`` axes widths), off the data."""
    ax.legend(loc="upper left", bbox_to_anchor=(x, 1.0), borderaxespad=0.0, fontsize="small")


def _band(ax, x, values, name: str, color: str, steps: bool) -> None:
    """The median of ``values`` ``[B, len(x)]`` over the loops, its 10-90 % band and its extremes;
    ``steps``: held over each step (inputs, nodes) rather than joined (states)."""
    low, mid, high = np.percentile(values, [10, 50, 90], axis=0)
    draw = {"drawstyle": "steps-post"} if steps else {}
    ax.plot(x, mid, color=color, label=f"{name} (median)", **draw)
    ax.fill_between(x, low, high, color=color, alpha=0.25, linewidth=0, step="post" if steps else None)
    ax.plot(x, values.min(axis=0), color=color, linestyle=":", linewidth=0.8, **draw)
    ax.plot(x, values.max(axis=0), color=color, linestyle=":", linewidth=0.8, **draw)


def _names(arg: str, names, count: int, symbol: str, what: str) -> list[str]:
    """``count`` curve labels: the user's, checked, else ``symbol[i]``."""
    if names is None:
        return [f"{symbol}[{i}]" for i in range(count)]
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"{arg} must be a sequence of {count} strings, got {names!r}")
    names = list(names)
    if len(names) != count:
        raise ValueError(f"{arg} must name the run's {count} columns of {what}, got {len(names)}: {names}")
    return names
