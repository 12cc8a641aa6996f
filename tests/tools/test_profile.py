"""fj.profile and ``python -m firhc_jax profile MODULE:FUNCTION`` on a small user module written here."""
import importlib
import json
import sys

import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax._src.tools import profile as throughput
from firhc_jax.apps import profile as profile_app
from firhc_jax.apps.profile import load_case
from firhc_jax.cli import main

USER_MODULE = '''
import jax.numpy as jnp
import numpy as np
import firhc_jax as fj


def dynamics(x, u, p):
    return jnp.stack([0.9 * x[0] + 0.3 * u[0] + 0.1 * jnp.sin(x[1]), 0.8 * x[1] + 0.2 * u[0]])


def cost(x, u, p):
    return (x[0] - p["r"]) ** 2 + 0.5 * x[1] ** 2 + 0.01 * u[0] ** 2


def case():
    states = np.random.default_rng(0).uniform(-1, 1, (6, 2))
    return (fj.Problem(dynamics, jnp.array([-1.0, 0.0, 1.0]), cost, 3), states,
            {"r": np.linspace(-0.5, 0.5, 6)})


def two():
    return fj.Problem(lambda x, u: dynamics(x, u, None), jnp.array([-1.0, 1.0]), lambda x, u: x[0] ** 2, 2), \
        np.zeros((3, 2))


def wrong():
    return "not a case"


def boom():
    raise RuntimeError("no plant today")
'''
OPTIONS = dict(pop_widths=(1, 2), lanes=(4,), repeats=2)


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """The user's module ``fj_profile_user`` (importable from its folder) and its folder."""
    folder = tmp_path_factory.mktemp("user")
    (folder / "fj_profile_user.py").write_text(USER_MODULE)
    sys.path.insert(0, str(folder))
    yield importlib.import_module("fj_profile_user"), folder
    sys.path.remove(str(folder))
    sys.modules.pop("fj_profile_user", None)


def test_profile_rows_have_the_documented_keys_the_defaults_and_one_fastest(user):
    problem, states, params = user[0].case()
    rows = fj.profile(problem, states, params, **OPTIONS)
    assert [r["setting"] for r in rows] == ["sdfs pop_width=1", "sdfs pop_width=2", "exhaustive",
                                            "solve_batch default lanes", "solve_batch lanes=4"]
    assert [r["solver"] for r in rows] == ["sdfs", "sdfs", "exhaustive", "solve_batch", "solve_batch"]
    assert [r["default"] for r in rows] == [True, False, False, True, False]  # what a call without options gets
    assert [r["per_decision"] for r in rows] == [True, True, True, False, False]  # a controller's kind of call
    assert rows[3]["lanes"] is None and rows[4]["lanes"] == 4
    for r in rows:  # the first profile of this problem: every setting compiles, apart from the timed calls
        assert 0 < r["seconds_min"] <= r["seconds"] <= r["seconds_max"] < r["compile_s"] and r["states"] == 6
        assert r["nodes_per_second"] == pytest.approx(r["nodes"] / r["seconds"])
        assert r["solves_per_second"] == pytest.approx(6 / r["seconds"])
        assert r["us_per_iteration"] == pytest.approx(1e6 * r["seconds"] / r["iterations"])
    assert [r["fastest"] for r in rows].count(True) == 1
    best = max(rows, key=lambda r: r["solves_per_second"])
    assert best["fastest"] and best["within_noise"]
    assert rows.clear_winner == ([r["within_noise"] for r in rows].count(True) == 1)
    # The counts are the searches' own: fj.sdfs row by row, the whole tree for the exhaustive search.
    sdfs_nodes = sum(int(fj.sdfs(problem, x, params={"r": r}).nodes) for x, r in zip(states, params["r"], strict=True))
    assert rows[0]["nodes"] == sdfs_nodes and rows[2]["nodes"] == 6 * problem.tree_size()
    # What the rows rest on: the compiles (searches and callables) within the whole profile's time.
    assert rows.repeats == 2 and [c["callable"] for c in rows.node_costs] == ["dynamics", "stage_cost"]
    assert rows.compile_seconds == pytest.approx(sum(r["compile_s"] for r in rows)
                                                 + sum(c["compile_s"] for c in rows.node_costs))
    assert 0 < rows.compile_seconds < rows.seconds
    limited = fj.profile(problem, states, params, **OPTIONS, max_exhaustive_nodes=2 * problem.tree_size())
    assert next(r["states"] for r in limited if r["solver"] == "exhaustive") == 2
    only = fj.profile(problem, states, params, pop_widths=(2,), lanes=(), repeats=1)  # the default is added
    assert [(r["setting"], r["default"]) for r in only] == [("sdfs pop_width=1", True), ("sdfs pop_width=2", False),
                                                           ("exhaustive", False)]


def _timed(setting: str, states: int, low: float, high: float, default: bool = False) -> dict:
    """A row of ``fj.profile`` with the keys its marks and its report read."""
    return {"setting": setting, "solver": "solve_batch", "states": states, "seconds_min": low, "seconds_max": high,
            "solves_per_second": states / ((low + high) / 2), "nodes_per_second": 1e6, "default": default,
            "per_decision": setting.startswith("sdfs"), "fastest": False, "within_noise": False}


def test_a_difference_inside_the_noise_is_no_clear_winner():
    """Two runs of the same work under load (ranges overlap): no winner; a setting whose slowest run beats
    every other's fastest wins clearly. Ranges are compared per state (exhaustive times a subset)."""
    same = [_timed("default", 100, 1.0, 2.0, True), _timed("lanes=64", 100, 0.6, 1.1),
            _timed("exhaustive", 10, 1.0, 1.2)]
    throughput._mark(same, False)
    assert [r["fastest"] for r in same] == [False, True, False]
    assert [r["within_noise"] for r in same] == [True, True, False]  # 1.0 / 100 <= 1.1 / 100; 1.0 / 10 is not
    assert not throughput.Profile(same, [], 3, 1.0, 2.0).clear_winner
    assert profile_app.verdict(throughput.Profile(same, [], 3, 1.0, 2.0)).startswith(
        "no clear winner: lanes=64 (118 solves/s median) is within the noise of default (their runs' ranges overlap")
    apart = [_timed("default", 100, 1.2, 2.0, True), _timed("lanes=64", 100, 0.6, 1.1)]
    throughput._mark(apart, False)
    assert [r["within_noise"] for r in apart] == [False, True]
    assert throughput.Profile(apart, [], 3, 1.0, 2.0).clear_winner
    assert profile_app.verdict(throughput.Profile(apart, [], 3, 1.0, 2.0)).startswith(
        "fastest: lanes=64 (118 solves/s, 1e+06 nodes/s, 1.88x default, the default; its slowest of 3 runs beats")
    assert not throughput.Profile(apart, [], 1, 1.0, 2.0).clear_winner  # one run each: no noise measured


def test_for_a_controller_the_fastest_is_among_the_rows_of_one_decision_per_call():
    """A batch of every state at once can beat one decision per call per state, but a controller decides once
    per sampling period: asked for a controller, profile names the fastest row it can use."""
    rows = [_timed("sdfs pop_width=1", 100, 1.0, 1.2, True), _timed("sdfs pop_width=4", 100, 0.5, 0.6),
            _timed("solve_batch default lanes", 100, 0.1, 0.12, True)]
    throughput._mark(rows, True)
    assert [r["fastest"] for r in rows] == [False, True, False]
    assert [r["within_noise"] for r in rows] == [False, True, False]
    result = throughput.Profile(rows, [], 3, 1.0, 2.0, for_controller=True)
    assert result.clear_winner
    assert profile_app.verdict(result).startswith(
        "fastest: sdfs pop_width=4 (182 solves/s, of the settings of one decision per call, as a controller decides")
    for r in rows:
        r["fastest"] = r["within_noise"] = False
    throughput._mark(rows, False)  # every row: the batch
    assert [r["fastest"] for r in rows] == [False, False, True]


def test_node_costs_time_each_callable_as_a_search_evaluates_it():
    def bound(x, steps_left):
        return 0.01 * steps_left * x[0] ** 2

    problem = fj.Problem(lambda x, u: 0.9 * x + u, np.array([-1.0, 0.0, 1.0]), lambda x, u: x[0] ** 2, 3,
                         terminal=lambda x: x[0] < 2.0, lower_bound=bound, terminal_cost=lambda x: 2.0 * x[0] ** 2,
                         constraint=lambda x, u: x[0] > -5.0)
    states = np.linspace(-1.0, 1.0, 5)[:, None]
    rows = fj.profile(problem, states, pop_widths=(1,), lanes=(), repeats=1)
    costs = rows.node_costs
    assert [c["callable"] for c in costs] == ["dynamics", "stage_cost", "constraint", "lower_bound", "terminal",
                                              "terminal_cost"]
    assert all(0 < c["ns_min"] <= c["ns"] <= c["ns_max"] and c["children"] == 5462 * 3 for c in costs)
    # Each timed function is the callable it is named after, over every state times every input.
    parts = throughput._node_parts(problem)
    x = np.linspace(-1.0, 1.0, 4)[:, None]
    xs = np.asarray(parts["dynamics"](x, None, None))
    np.testing.assert_allclose(xs, 0.9 * x[:, None, :] + problem.controls[None])
    np.testing.assert_allclose(parts["stage_cost"](x, xs, None), xs[..., 0] ** 2)
    np.testing.assert_array_equal(parts["constraint"](x, xs, None), xs[..., 0] > -5.0)
    np.testing.assert_allclose(parts["lower_bound"](x, xs, None), 0.02 * xs[..., 0] ** 2)  # N - 1 steps left
    np.testing.assert_array_equal(parts["terminal"](x, xs, None), xs[..., 0] < 2.0)
    np.testing.assert_allclose(parts["terminal_cost"](x, xs, None), 2.0 * xs[..., 0] ** 2)


def test_profile_refuses_bad_arguments(user):
    problem, states, params = user[0].case()
    with pytest.raises(ValueError, match="pop_widths"):
        fj.profile(problem, states, params, pop_widths=(0,))
    with pytest.raises(ValueError, match="nothing to profile"):
        fj.profile(problem, states, params, pop_widths=(), lanes=())
    with pytest.raises(ValueError, match="leading axis"):
        fj.profile(problem, states, {"r": np.zeros(5)})
    with pytest.raises(TypeError, match="problem must be"):
        fj.profile("tanks", states)


def test_profile_command_prints_what_each_figure_rests_on(user, tmp_path, capsys):
    out = tmp_path / "prof"
    assert main(["profile", "fj_profile_user:case", "--out", str(out), "--pop-widths", "1", "2", "--lanes", "4",
                 "--repeats", "2", "--max-exhaustive-nodes", str(3 * 39)]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "profile: sdfs pop_width=2 (compiling)" in captured.err and "solve_batch lanes=4" in captured.err
    # Interleaved: round 1 starts with the first setting, round 2 with the second.
    assert captured.err.index("round 1 of 2, sdfs pop_width=1") < captured.err.index("round 1 of 2, sdfs pop_width=2")
    assert captured.err.index("round 2 of 2, sdfs pop_width=2") < captured.err.index("round 2 of 2, sdfs pop_width=1")
    saved = json.loads((out / "profile.json").read_text())
    fastest = next(r["setting"] for r in saved["rows"] if r["fastest"])
    verdict = f"fastest: {fastest} (" if saved["clear_winner"] else f"no clear winner: {fastest} ("
    assert verdict in printed and "| sdfs pop_width=2 |" in printed
    defaults = [line for line in printed.splitlines() if line.startswith(("| sdfs pop_width=1 | 6 |",
                                                                           "| solve_batch default lanes | 6 |"))]
    assert len(defaults) == 2 and all(line.rstrip(" |").split("| ")[-1].startswith("default") for line in defaults)
    assert "6 states; fj.exhaustive on 3 of them" in printed and "every setting timed 2 times, interleaved" in printed
    assert f"Compiling took {saved['compile_seconds']:.1f} s of the {saved['seconds']:.1f} s" in printed
    assert "| dynamics |" in printed and "| stage_cost |" in printed and "a node of sdfs pop_width=1 takes" in printed
    assert saved["case"] == "fj_profile_user:case" and len(saved["rows"]) == 5 and saved["repeats"] == 2
    assert [c["callable"] for c in saved["node_costs"]] == ["dynamics", "stage_cost"]
    assert (out / "profile.png").read_bytes()[:4] == b"\x89PNG"
    problem, states, params = load_case("fj_profile_user:two")  # (problem, states): no params
    assert isinstance(problem, fj.Problem) and states.shape == (3, 2) and params is None


def test_profile_figure_labels_its_log_axes_and_writes_each_value(tmp_path):
    """Rates within one decade (where a log axis has a single decade tick): every axis still carries several
    labelled ticks, each bar its value, the defaults their names and the callables their ns per child."""
    from matplotlib.figure import Figure

    rows = [dict(_timed(name, 50, low, 1.2 * low), solver="sdfs", nodes_per_second=rate, default=name.endswith("1"))
            for name, low, rate in (("sdfs pop_width=1", 0.010, 4e5), ("sdfs pop_width=2", 0.013, 3e5))]
    throughput._mark(rows, False)
    costs = [{"callable": c, "ns": ns, "ns_min": ns, "ns_max": 1.1 * ns, "children": 16384, "compile_s": 0.1}
             for c, ns in (("dynamics", 575.0), ("lower_bound", 661.0), ("terminal", 80.0))]
    fig = profile_app.figure(throughput.Profile(rows, costs, 3, 12.0, 30.0), "two settings")
    assert isinstance(fig, Figure)
    fig.savefig(tmp_path / "profile.png")  # lays the figure out
    rates, nodes, callables = fig.axes[:3]
    for ax in (rates, nodes, callables):
        low, high = ax.get_xlim()
        labelled = [t for t in ax.get_xticklabels() if t.get_text() and low <= t.get_position()[0] <= high]
        assert ax.get_xscale() == "log" and len(labelled) >= 3, [t.get_text() for t in labelled]
    assert [t.get_text() for t in rates.get_yticklabels()] == ["sdfs pop_width=1 (default)", "sdfs pop_width=2"]
    written = [t.get_text() for t in rates.texts]
    assert written[0] == "4.55k" and written[1].startswith("3.5k")  # 50 states / 11 ms, 50 / 14.3 ms
    assert [t.get_text() for t in nodes.texts] == ["400k", "300k"]
    assert [t.get_text() for t in callables.texts] == ["575", "661", "80"]
    assert [t.get_text() for t in callables.get_yticklabels()] == ["dynamics", "lower_bound", "terminal (leaves)"]
    assert "compiling: 12.0 s of the 30.0 s" in fig.axes[3].texts[0].get_text()


@pytest.mark.parametrize("case, message", [
    ("fj_profile_user", "expected MODULE:FUNCTION"),
    ("no_such_module_xyz:case", "cannot import module 'no_such_module_xyz'"),
    ("fj_profile_user:missing", "has no function 'missing'"),
    ("fj_profile_user:wrong", r"must return \(problem, states\)"),
    ("fj_profile_user:boom", "raised RuntimeError: no plant today")])
def test_profile_command_refuses_a_bad_case_with_a_message(user, tmp_path, case, message):
    with pytest.raises(SystemExit, match=message):
        main(["profile", case, "--out", str(tmp_path)])


def test_profile_command_refuses_an_unwritable_out_before_importing(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    with pytest.raises(SystemExit) as e:
        main(["profile", "no_such_module_xyz:case", "--out", str(a_file)])
    assert e.value.code == 2 and "exists and is not a folder" in capsys.readouterr().err


def _late_cost_problem(lower_bound=None):
    """Every sequence pays only at its last step, so that a search without a bound prunes almost nothing."""
    import jax.numpy as jnp

    return fj.Problem(lambda x, u, k: 0.9 * x + u, jnp.array([-0.5, 0.0, 0.5]),
                      lambda x, u, k: jnp.where(k == 6, 10.0 + jnp.sum(x**2), 0.0), 7, step_index=True,
                      lower_bound=lower_bound)


def test_profile_warns_when_a_search_without_a_bound_prunes_little():
    states = np.random.default_rng(1).uniform(-1, 1, (2, 1))
    with pytest.warns(UserWarning, match="lower_bound=\"auto\""):
        rows = fj.profile(_late_cost_problem(), states, pop_widths=(1,), lanes=(), repeats=1,
                          max_exhaustive_nodes=1)
    assert rows.bound is None and len(rows.advice) == 1
    assert rows[0]["nodes"] / 2 > throughput.UNPRUNED_SHARE * _late_cost_problem().tree_size()


def test_profile_times_the_search_with_and_without_the_bound():
    states = np.random.default_rng(1).uniform(-1, 1, (2, 1))
    rows = fj.profile(_late_cost_problem("auto"), states, pop_widths=(1,), lanes=(), repeats=1,
                      max_exhaustive_nodes=1)
    bound = rows.bound
    assert set(bound) == {"seconds", "seconds_without", "nodes", "nodes_without", "slowdown"}
    assert bound["nodes"] == rows[0]["nodes"] and bound["nodes_without"] > 2 * bound["nodes"]
    assert bound["slowdown"] == pytest.approx(bound["seconds"] / bound["seconds_without"])
    assert "lower_bound" in [c["callable"] for c in rows.node_costs]
    costly = dict(bound, slowdown=throughput.BOUND_SLOWDOWN + 0.1)
    assert "costs more than its pruning saves" in throughput._advice(_late_cost_problem("auto"), list(rows),
                                                                         costly)[0]
    assert throughput._advice(_late_cost_problem("auto"), list(rows), dict(bound, slowdown=1.0)) == []
