"""One shape for models and apps: every model's factory is ``make_problem(horizon, params=<Model>Params(),
**options)`` (and ``make_plant(params=...)`` where it has a plant), the old names warn and build the same
problem; the applications fill in one run skeleton (``apps/_run.py``) and none imports another."""
import argparse
import ast
import json
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax.apps import _run
from firhc_jax.apps import example as example_app
from firhc_jax.models import hopper, inverter, pumping, spacecraft, synthetic, tanks, thermal, three_level

MODELS = (hopper, tanks, inverter, three_level, thermal, pumping, synthetic, spacecraft)
PARAMS = {hopper: hopper.HopperParams, tanks: tanks.TankParams, inverter: inverter.InverterParams,
          three_level: three_level.ThreeLevelParams, thermal: thermal.ThermalParams,
          pumping: pumping.PumpingParams, synthetic: synthetic.SyntheticParams,
          spacecraft: spacecraft.SpacecraftParams}
PLANTS = (hopper, tanks, inverter, three_level, thermal, pumping, spacecraft)


def _evaluations(problem: fj.Problem, x, p):
    """Every callable of ``problem`` at ``x`` for every input (and step index 0, ``steps_left`` 1): the numbers
    two equal problems share bit for bit."""
    extra = ((jnp.int32(0),) if problem.step_index else ()) + (() if p is None else (p,))
    last = () if p is None else (p,)
    controls = jnp.asarray(problem.controls)
    nexts = jax.vmap(lambda u: problem.dynamics(x, u, *extra))(controls)
    out = {"controls": controls, "next": nexts,
           "stage": jax.vmap(lambda z, u: problem.stage_cost(z, u, *extra))(nexts, controls)}
    for name, call in (("terminal", lambda f, z: f(z, *last)), ("terminal_cost", lambda f, z: f(z, *last)),
                       ("lower_bound", lambda f, z: f(z, jnp.int32(1), *last)),
                       ("constraint", lambda f, z: jax.vmap(lambda u: f(z, u, *extra))(controls))):
        if getattr(problem, name) is not None:
            out[name] = call(getattr(problem, name), x)
    return out


def test_every_model_has_the_same_factory_signature():
    """``make_problem(horizon, params=<Model>Params(), ...)`` with the model's own parameter record as the
    default, and ``make_plant(params=...)`` with the same default wherever the model has a plant."""
    import inspect

    for module in MODELS:
        signature = inspect.signature(module.make_problem)
        names = list(signature.parameters)
        assert names[:2] == ["horizon", "params"], (module.__name__, names)
        assert signature.parameters["horizon"].default is inspect.Parameter.empty, module.__name__
        assert isinstance(signature.parameters["params"].default, PARAMS[module]), module.__name__
    for module in PLANTS:
        plant = inspect.signature(module.make_plant).parameters
        assert list(plant)[0] == "params" and isinstance(plant["params"].default, PARAMS[module]), module.__name__


def test_the_hopper_factory_relaxes_and_bounds_as_asked():
    P = hopper.HopperParams()
    bounded = hopper.make_problem(3, P, bound=True)
    relaxed = hopper.make_problem(3, P, bound=True, terminal=False)
    assert relaxed.terminal is None and relaxed.lower_bound is not bounded.lower_bound
    assert hopper.make_problem(3, P, terminal=False).terminal is None
    assert hopper.make_problem(3, P, bound=True) is bounded


def test_pumping_params_reach_every_callable():
    """Twice the tank areas: every level moves half as far in an hour (the flows depend on the level only)."""
    base, wide = pumping.PumpingParams(), pumping.PumpingParams(area=tuple(2 * a for a in pumping.AREA))
    x, on, demand = np.asarray(pumping.INITIAL_LEVELS), np.array([1.0, 1.0, 0.0]), np.array([30.0, 20.0])
    moved = [np.asarray(pumping.make_plant(p)(jnp.asarray(x), jnp.asarray(on), jnp.asarray(demand))) - x
             for p in (base, wide)]
    np.testing.assert_allclose(moved[1], moved[0] / 2, rtol=1e-12)
    hours = jax.tree_util.tree_map(lambda a: jnp.asarray(a[0]), pumping.horizon_params(*pumping.forecast(4), 1, 3))
    problems = [pumping.make_problem(3, p, bound="target") for p in (base, wide)]
    nexts = [np.asarray(q.dynamics(jnp.asarray(x), jnp.asarray(on), jnp.int32(0), hours)) - x for q in problems]
    np.testing.assert_allclose(nexts[1], nexts[0] / 2, rtol=1e-12)
    low = jnp.full(2, 1.0)  # far below the target: the bound grows with the water missing, so with the area
    assert float(problems[1].lower_bound(low, jnp.int32(3), hours)) > float(problems[0].lower_bound(low, jnp.int32(3),
                                                                                                      hours))
    with pytest.raises(TypeError, match="params must be a PumpingParams"):
        pumping.make_problem(3, {"area": (1.0, 1.0)})


def test_the_three_level_plant_with_two_levels_used_is_the_two_level_plant():
    """Legs at -1/+1 apply -Vdc/2 / +Vdc/2, the two-level inverter's 0/1 legs less a common mode that the
    Clarke transform removes: ``three_level.make_plant`` is ``inverter.make_plant`` for the same circuit."""
    params = three_level.ThreeLevelParams()
    assert params == three_level.PARAMS and params.vdc == 400.0 and params.steps_per_cycle == 800
    three, two = three_level.make_plant(params), inverter.make_plant(params)
    i = jnp.asarray([3.0, -7.0])
    for s in inverter.SWITCH_STATES:
        np.testing.assert_allclose(three(i, jnp.asarray(2 * s - 1)), two(i, jnp.asarray(s)), rtol=1e-9, atol=1e-9)


def test_the_thermal_plant_holds_its_steady_state():
    """``calm_states`` draws around the state that the least heater duty holds: the plant keeps that state
    under that duty (a duty in [0, 1] is the mean of the on/off inputs)."""
    params = thermal.ThermalParams()
    A, B, d = thermal.model(params)
    inv = np.linalg.inv(np.eye(4) - A)
    duty = np.linalg.lstsq(thermal.OUTPUTS @ inv @ B, np.asarray(params.set_point) - thermal.OUTPUTS @ inv @ d,
                           rcond=None)[0]
    steady = inv @ (B @ duty + d)
    np.testing.assert_allclose(thermal.make_plant(params)(jnp.asarray(steady), jnp.asarray(duty)), steady,
                               rtol=1e-12)
    np.testing.assert_allclose(thermal.OUTPUTS @ steady, params.set_point, rtol=1e-12)


def _imports(path: Path) -> set:
    """The absolute names of every module ``path`` imports (relative imports resolved in its own package)."""
    package = "firhc_jax." + path.parent.name
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package if node.level == 1 else "firhc_jax"
                base = f"{parent}.{base}" if base else parent
            names.add(base)
            names.update(f"{base}.{a.name}" for a in node.names)
    return names


def test_no_app_imports_another_and_no_model_builds_a_controller():
    apps = Path(cli.__file__).parent / "apps"
    commands = set(cli._APPS)
    for name in commands:
        path = apps / f"{name.rsplit('.', 1)[1]}.py"
        assert not (_imports(path) & (commands - {name})), f"{path.name} imports another command"
    for path in (Path(cli.__file__).parent / "models").glob("*.py"):
        assert "fj.FIRHC(" not in path.read_text(), path.name


def test_models_and_apps_import_only_public_names():
    """Models and the command line are written as a user would write them: no private module, and no model
    imports an application."""
    root = Path(cli.__file__).parent
    for folder in ("models", "apps"):
        for path in (root / folder).glob("*.py"):
            private = {name for name in _imports(path) if "._src" in name or name.startswith("firhc_jax._")}
            assert not private, f"{folder}/{path.name} imports {sorted(private)}"
            if folder == "models":
                assert not {n for n in _imports(path) if n.startswith("firhc_jax.apps")}, path.name


class _Run(NamedTuple):
    loop: fj.ClosedLoop


class _Pendulum(_run.App):
    """The smallest application: the example's pendulum, three steps, one figure."""

    name = "pendulum_test"
    help = "a test"
    description = "a test"

    def add_arguments(self, parser):
        parser.add_argument("--steps", type=int, default=3)

    def variant(self, args):
        return _Fails() if args.steps == 0 else self

    def simulate(self, args):
        ctrl = fj.FIRHC(example_app.make_problem(3), fallback="unconstrained")
        return _Run(ctrl.simulate(jnp.array([0.6, 0.0]), args.steps, progress=not args.no_progress))

    def summarize(self, args, run):
        return {"steps": args.steps, "final": np.asarray(run.loop.states[-1]).tolist()}

    def plot(self, args, run, summary):
        path = Path(args.out) / "figure.txt"
        path.write_text("drawn")
        return [path]

    def report(self, args, summary):
        return f"ran {summary['steps']} steps"

    def exit_status(self, summary):
        return 3


class _Fails(_Pendulum):
    def simulate(self, args):
        raise RuntimeError("the variant ran")


def test_the_run_skeleton_writes_the_summary_the_closed_loop_and_the_figures(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    app = _Pendulum()
    app.register(parser.add_subparsers())
    args = parser.parse_args(["pendulum_test"])
    args.check(args)  # the default folder is the variant's, set when the options are checked
    assert str(args.out) == "out/pendulum_test" and args.no_progress is False
    args = parser.parse_args(["pendulum_test", "--out", str(tmp_path / "run"), "--no-progress"])
    args.check(args)
    assert args.func(args) == 3  # the app's exit status
    out = tmp_path / "run"
    summary = json.loads((out / "summary.json").read_text())
    loop = fj.ClosedLoop.load(out / "closed_loop.npz")
    assert summary["steps"] == 3 and loop.states.shape == (4, 2)
    assert summary["final"] == np.asarray(loop.states[-1]).tolist() and (out / "figure.txt").read_text() == "drawn"
    said = capsys.readouterr()
    assert said.err.startswith(f"writing summary.json, closed_loop.npz and the figures to {out} ...")
    assert "ran 3 steps" in said.out and str(out / "figure.txt") in said.out
    with pytest.raises(RuntimeError, match="the variant ran"):  # variant() picks the App that runs
        args.func(parser.parse_args(["pendulum_test", "--steps", "0", "--out", str(tmp_path / "other")]))


def test_every_closed_loop_command_is_an_app_with_out_and_no_progress():
    parser = cli.build_parser()
    for command in ("example", "hopper", "tanks", "inverter"):
        module = __import__(f"firhc_jax.apps.{command}", fromlist=["APP"])
        assert isinstance(module.APP, _run.App) and module.register == module.APP.register
        args = parser.parse_args([command])
        args.check(args)
        assert str(args.out) == f"out/{command}" and args.no_progress is False and args.func == module.APP.run
    from firhc_jax.apps import inverter as inverter_app
    from firhc_jax.apps import inverter_three_level

    three = parser.parse_args(["inverter", "--levels", "3"])
    assert inverter_app.APP.variant(three) is inverter_three_level.APP
    three.check(three)  # its own folder: a three-level run does not overwrite a two-level one
    assert str(three.out) == "out/inverter-3level"
    assert str(parser.parse_args(["inverter", "--levels", "3", "--out", "out/x"]).out) == "out/x"
    assert inverter_app.APP.variant(parser.parse_args(["inverter"])) is inverter_app.APP
