"""fj.profile and ``python -m firhc_jax profile MODULE:FUNCTION`` on a small user module written here."""
import importlib
import json
import sys

import numpy as np
import pytest

import firhc_jax as fj
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
OPTIONS = dict(pop_widths=(1, 2), lanes=(4,), repeats=1)


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """The user's module ``fj_profile_user`` (importable from its folder) and its folder."""
    folder = tmp_path_factory.mktemp("user")
    (folder / "fj_profile_user.py").write_text(USER_MODULE)
    sys.path.insert(0, str(folder))
    yield importlib.import_module("fj_profile_user"), folder
    sys.path.remove(str(folder))
    sys.modules.pop("fj_profile_user", None)


def test_profile_rows_have_the_documented_keys_and_one_fastest(user):
    problem, states, params = user[0].case()
    rows = fj.profile(problem, states, params, **OPTIONS)
    assert [r["setting"] for r in rows] == ["sdfs pop_width=1", "sdfs pop_width=2", "exhaustive",
                                            "solve_batch lanes=4"]
    assert [r["solver"] for r in rows] == ["sdfs", "sdfs", "exhaustive", "solve_batch"]
    for r in rows:  # the first profile of this problem: every setting compiles, apart from the timed calls
        assert 0 < r["seconds"] < r["compile_s"] and r["states"] == 6
        assert r["nodes_per_second"] == pytest.approx(r["nodes"] / r["seconds"])
        assert r["solves_per_second"] == pytest.approx(6 / r["seconds"])
        assert r["us_per_iteration"] == pytest.approx(1e6 * r["seconds"] / r["iterations"])
    assert [r["fastest"] for r in rows].count(True) == 1
    assert max(rows, key=lambda r: r["solves_per_second"])["fastest"]
    # The counts are the searches' own: fj.sdfs row by row, the whole tree for the exhaustive search.
    sdfs_nodes = sum(int(fj.sdfs(problem, x, params={"r": r}).nodes) for x, r in zip(states, params["r"], strict=True))
    assert rows[0]["nodes"] == sdfs_nodes and rows[2]["nodes"] == 6 * problem.tree_size()
    limited = fj.profile(problem, states, params, **OPTIONS, max_exhaustive_nodes=2 * problem.tree_size())
    assert next(r["states"] for r in limited if r["solver"] == "exhaustive") == 2


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


def test_profile_command_prints_writes_and_names_the_fastest(user, tmp_path, capsys):
    out = tmp_path / "prof"
    assert main(["profile", "fj_profile_user:case", "--out", str(out), "--pop-widths", "1", "2", "--lanes", "4",
                 "--repeats", "1"]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "profile: sdfs pop_width=2 (compiling" in captured.err and "solve_batch lanes=4" in captured.err
    saved = json.loads((out / "profile.json").read_text())
    fastest = next(r["setting"] for r in saved["rows"] if r["fastest"])
    assert f"fastest: {fastest} (" in printed and "| sdfs pop_width=2 |" in printed
    assert saved["case"] == "fj_profile_user:case" and len(saved["rows"]) == 4
    assert (out / "profile.png").read_bytes()[:4] == b"\x89PNG"
    problem, states, params = load_case("fj_profile_user:two")  # (problem, states): no params
    assert isinstance(problem, fj.Problem) and states.shape == (3, 2) and params is None


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
