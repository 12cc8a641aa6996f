"""Hopping robot: physics of the plant and prediction model, desired energy, closed loop, CLI."""
import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import compiles_inside

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax.apps import hopper as app
from firhc_jax.models import hopper as hm

P = hm.HopperParams()
CLOSED = jnp.zeros(2)  # both valves closed


def test_orifice_constants_are_richer_hurmuzlu():
    assert P.C1 == pytest.approx(0.040418, abs=1e-6)
    assert P.C2 == pytest.approx(0.156174, abs=1e-6)
    assert P.P_crit == pytest.approx(0.528, abs=1e-3)


def test_orifice_flow_choked_below_critical_ratio_and_continuous():
    Pu = 6e5
    choked = P.C_f * P.A_v * P.C1 * Pu / math.sqrt(P.T)
    for ratio in (0.1, 0.3, 0.5):  # choked: independent of the downstream pressure
        assert float(hm.orifice_flow(Pu, ratio * Pu, P)) == pytest.approx(choked, rel=1e-12)
    eps = 1e-9
    below, above = (float(hm.orifice_flow(Pu, (P.P_crit + d) * Pu, P)) for d in (-eps, eps))
    assert above == pytest.approx(below, rel=1e-6)
    assert float(hm.orifice_flow(Pu, 0.9 * Pu, P)) < choked
    assert float(hm.orifice_flow(Pu, Pu, P)) == 0.0
    assert float(hm.orifice_flow(2e5, 3e5, P)) == -float(hm.orifice_flow(3e5, 2e5, P))


def test_power_is_the_float_power():
    x = np.geomspace(1e-6, 1e7, 2001)
    for a in (1.4, 1 / 1.4, 0.4 / 1.4, -0.4 / 1.4):
        np.testing.assert_allclose(np.asarray(hm.power(jnp.asarray(x), a)), x**a, rtol=1e-13, atol=0)


def test_stance_stiffness_matches_desired_gait():
    gait = hm.desired_energy(0.4, 0.2, P)
    assert P.stance_stiffness() == pytest.approx(P.M * (math.pi / gait.T2) ** 2, rel=0.01)


def test_desired_energy_paper_example():
    gait = hm.desired_energy(0.4, 0.2, P)
    assert gait.T2 == pytest.approx(0.161, abs=1e-3)
    assert gait.xdot_t1 == pytest.approx(0.981)
    assert gait.x_t1 == pytest.approx((P.M + P.m) * P.g / (P.M * (math.pi / gait.T2) ** 2))
    Pa, Pb = hm.nominal_pressures(gait.x_t1, P)
    assert gait.E_d == pytest.approx(float(hm.energy(gait.x_t1, gait.xdot_t1, Pa, Pb, P)))
    with pytest.raises(ValueError, match="T_air < T_hop"):
        hm.desired_energy(0.2, 0.4, P)


def test_orbit_energy_of_static_charge_is_eq20():
    """For the static charge the controller's E_d is eq. (20) at the exact lift-off stroke."""
    static = jnp.array([0.0, 0.0, P.P_a0, P.P_b0])
    x1 = float(hm.liftoff_stroke(P.P_a0 * P.V_mida**P.gamma, P.P_b0 * P.V_midb**P.gamma, P))
    Pa, Pb = hm.nominal_pressures(x1, P)
    assert float(hm.piston_force(Pa, Pb, P)) == pytest.approx(-P.m * P.g, abs=1e-9)
    assert float(hm.orbit_energy(static, 0.981, P)) == pytest.approx(float(hm.energy(x1, 0.981, Pa, Pb, P)))
    assert x1 == pytest.approx(hm.desired_energy(0.4, 0.2, P).x_t1, rel=0.02)  # eq. (18) linearises


def _stance_start():
    """Standing still, body pushed down at 0.5 m/s: a stance oscillation that never lifts the foot."""
    X = hm.static_state(P)
    X[1] = -0.5
    return jnp.asarray(X)


def test_plant_energy_conserved_over_a_stance():
    p = dataclasses.replace(P, b=0.0, b_ground=0.0)
    steps = int(round(2 * 0.1615 / 5e-5))  # a full stance oscillation
    traj = jax.jit(hm.simulate_open_loop, static_argnums=(2, 3, 4))(_stance_start(), CLOSED, p, 5e-5, steps)
    assert np.all(np.asarray(traj[:, 2]) < 0), "the foot must stay on the ground (no impact)"
    E = np.asarray(hm.plant_energy(traj, p))
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-6
    s = np.asarray(traj[:, 0] - traj[:, 2])
    assert s.min() < -0.02 and s.max() > 0.02  # it really oscillated


def test_prediction_model_conserves_eq6():
    z = jnp.array([0.0, -0.9, P.P_a0, P.P_b0, 0.0])
    E0 = float(hm.model_energy(z, P))
    step = jax.jit(lambda z: hm.model_step(z, CLOSED, P, 0.005, 5))
    for _ in range(int(round(0.1615 / 0.005))):  # a compression period
        z = step(z)
        assert float(z[4]) == 0.0
    assert abs(float(hm.model_energy(z, P)) - E0) / E0 < 1e-6


def test_free_fall_lands_at_analytic_time():
    """Dropped at rest with the springs at their flight equilibrium, body and foot fall together."""
    h, dt = 0.05, 5e-5
    traj = np.asarray(jax.jit(hm.simulate_open_loop, static_argnums=(2, 3, 4))(
        jnp.asarray(hm.apex_state(P, h)), CLOSED, P, dt, 2200))
    t = np.arange(len(traj)) * dt
    airborne = traj[:, 2] > 0
    last = np.nonzero(airborne)[0][-1]  # the plant step in which the foot lands is (last, last + 1]
    t_land = math.sqrt(2 * h / P.g)
    assert t[last] < t_land <= t[last + 1]
    assert np.all(airborne[: last + 1])
    np.testing.assert_allclose(traj[: last + 1, 2], h - P.g * t[: last + 1] ** 2 / 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj[: last + 1, 0] - traj[: last + 1, 2], hm.flight_stroke(P), rtol=0, atol=1e-12)


def test_static_equilibrium_is_an_equilibrium():
    X = jnp.asarray(hm.static_state(P))
    rhs = np.asarray(hm.plant_rhs(X, CLOSED, P))
    assert np.all(np.abs(rhs[:4]) < 1e-9) and np.all(np.abs(rhs[4:]) < 1e-6)
    traj = np.asarray(jax.jit(hm.simulate_open_loop, static_argnums=(2, 3, 4))(X, CLOSED, P, 5e-5, 4000))
    assert np.max(np.abs(traj - np.asarray(X))[:, :4]) < 1e-12


@pytest.fixture(scope="module")
def sdfs_loop():
    """``(loop, X)`` of the sDFS closed loop of 0.6 s (120 periods, one hop) at horizon 4, a compiled scan run
    once for every test below that looks at it: one compiled loop and one fine trajectory serve them all."""
    # Horizon 4 keeps the exhaustive closed loop's compile short; docs/applications/hopper.md reports N = 5-8.
    loop, X, compile_s = app.simulate(0.6, 4, "sdfs", progress=False)
    assert compile_s is None
    return loop, X


@pytest.mark.slow
def test_closed_loop_sdfs_equals_exhaustive_and_hops(sdfs_loop):
    runs = {"sdfs": sdfs_loop, "exhaustive": app.simulate(0.6, 4, "exhaustive", progress=False)[:2]}
    np.testing.assert_array_equal(runs["sdfs"][1], runs["exhaustive"][1])
    np.testing.assert_array_equal(runs["sdfs"][0].inputs, runs["exhaustive"][0].inputs)
    loop, X = runs["sdfs"]
    m = app.hop_metrics(X)
    assert len(m["t_air"]) == 1 and m["t_air"][0] == pytest.approx(0.2, rel=0.05)
    assert np.all(np.asarray(loop.input_indices) >= 0)
    assert np.max(np.abs(X[:, 0] - X[:, 2])) < P.stroke / 2
    # The fine trajectory re-run from the recorded commands passes through the loop's samples.
    np.testing.assert_allclose(X[::hm.SUBSTEPS], np.asarray(loop.states), rtol=1e-14, atol=1e-12)
    c = hm.contact(np.asarray(loop.states[:-1]))
    assert 0 < np.count_nonzero(c) < len(c)
    nodes, cmd = np.asarray(loop.nodes), np.asarray(loop.inputs)
    assert np.all(nodes[c] <= 3 + 9 + 27 + 81)
    # In flight both valves are sealed and the search is the trivial one (greedy path, 3N nodes).
    assert np.all(cmd[~c] == 0) and np.all(nodes[~c] == 3 * 4) and np.all(np.asarray(loop.feasible)[~c])
    assert np.any(cmd[c, 1] != 0)  # valve b acts in contact


# summary.json of `hopper --horizon 4 --seconds 0.6` before the applications moved onto step/simulate with one
# timing helper and the hopper's controller into models/hopper.py (commit 4d3fbf9): the port changes no result.
BEFORE_PORT = dict(t_air_mean=0.19578668873782212, t2_mean=0.15775, t_hop_mean=None, hops=1, infeasible_steps=0,
                   unsolved_steps=0, contact_steps=60, control_steps=120, nodes_min=12, nodes_max=111,
                   nodes_mean=35.25, valve_a_charges=0, valve_b_supply=7, valve_b_exhaust=17,
                   stroke_min=-0.06392767607206921, stroke_max=0.03224553884092181, E_d=9.335522342489929)


@pytest.mark.slow
def test_cli_runs_the_timed_loop_of_the_compiled_one_and_writes_its_results(sdfs_loop, tmp_path, monkeypatch):
    """The CLI's timed closed loop (a Python loop of the compiled step) is the compiled scan's, bit for bit; every
    decision is timed; compile_time_s covers XLA's compilation of the decision, done before the timed loop; the
    summary is the one recorded before the port; the figures and the saved closed loop are written."""
    out = tmp_path / "hop"
    argv = ["hopper", "--horizon", "4", "--seconds", "0.6", "--out", str(out), "--no-progress"]
    code, seen, in_loop = compiles_inside(monkeypatch, fj.FIRHC, "_run", lambda: cli.main(argv))
    assert code == 0
    decision = max((c for c in seen if c not in in_loop), key=lambda c: c[1])  # (name, s) the longest before
    assert decision[0] not in {name for name, _ in in_loop}  # the timed loop never compiles the decision
    summary = json.loads((out / "summary.json").read_text())
    for key, value in BEFORE_PORT.items():
        assert summary[key] == (pytest.approx(value, rel=1e-12) if isinstance(value, float) else value), key
    assert summary["horizon"] == 4 and summary["solver"] == "sdfs" and summary["pop_width"] == 1
    assert summary["T2"] == pytest.approx(0.161, abs=1e-3)
    assert 0 < summary["solve_time_median_s"] <= summary["solve_time_max_s"]
    assert summary["compile_time_s"] >= decision[1]
    assert len(list(out.glob("hopper_fig*.png"))) == 5
    timed, (loop, _) = fj.ClosedLoop.load(out / "closed_loop.npz"), sdfs_loop
    for field in ("states", "inputs", "nodes", "plans"):
        np.testing.assert_array_equal(getattr(timed, field), getattr(loop, field), err_msg=field)
    assert np.all(np.isnan(np.asarray(loop.solve_times)))
    assert np.all(np.isfinite(timed.solve_times) & (timed.solve_times > 0))  # every decision timed
    np.testing.assert_allclose(timed.times, np.arange(121) * hm.CONTROL_PERIOD, rtol=1e-15)


@pytest.mark.slow
def test_figs_4_and_5_show_the_body_position_in_one_unit(sdfs_loop, tmp_path, monkeypatch):
    """Fig. 4's body displacement and Fig. 5's body position: the same numbers under the same unit."""
    import re

    from firhc_jax.apps import _plot

    figures, drawn = [], _plot.subplots
    monkeypatch.setattr(_plot, "subplots", lambda *a, **k: figures.append(drawn(*a, **k)) or figures[-1])
    loop, X = sdfs_loop
    app.figures(loop, X, P, str(tmp_path))
    (_, fig4), (_, fig5) = figures[:2]
    assert fig4.get_title() == "Fig. 4: displacements" and fig5.get_title().startswith("Fig. 5")
    unit4, = re.findall(r"\((\w+)\)", fig4.get_ylabel())
    unit5, = re.findall(r"\((\w+)\)", fig5.get_xlabel())
    assert unit4 == unit5 == "cm"
    body = next(line for line in fig4.get_lines() if line.get_label() == "body x")
    np.testing.assert_array_equal(fig5.get_lines()[0].get_xdata(), body.get_ydata())


@pytest.mark.parametrize("argv, message", [
    (["--horizon", "0"], "--horizon: must be an integer between 1 and 12"),
    (["--horizon", "six"], "--horizon: must be an integer"),
    (["--seconds", "-1"], "--seconds: must be a number between"),
    (["--seconds", "nan"], "--seconds: must be a number between"),
    (["--solver", "greedy"], "invalid choice"),
    (["--pop-width", "0"], "--pop-width: must be an integer between 1 and 64"),
])
def test_cli_rejects_bad_input(argv, message, capsys):
    with pytest.raises(SystemExit):
        cli.main(["hopper", *argv])
    assert message in capsys.readouterr().err


@pytest.mark.slow
def test_bound_is_admissible_and_keeps_the_closed_loop(sdfs_loop):
    """The bound passes the exhaustive check on contact states, an inflated one is caught, and sDFS with it,
    warm-started from two candidates, drives the same closed loop with fewer nodes. The contact bound's
    premise holds: with valve b closed (side a idle) one period moves e = E - E_d by at most PASSIVE_DRIFT;
    where side a could charge, the bound claims nothing (0)."""
    from firhc_jax._src.tools.diagnostics import check_lower_bound

    plain, _ = sdfs_loop
    warm, _, _ = app.simulate(0.6, 4, "sdfs", P, progress=False, bound=True, warm=True)
    np.testing.assert_array_equal(np.asarray(warm.stage_costs), np.asarray(plain.stage_costs))
    assert np.asarray(warm.nodes).sum() < 0.85 * np.asarray(plain.nodes).sum()
    S = np.asarray(plain.states[:-1])
    Zall = jnp.asarray(np.asarray(jax.vmap(lambda X: hm.observe(X, None))(S[hm.contact(S)])))
    Z = Zall[::4]
    problem = hm.make_problem(4, P, bound=True)
    assert check_lower_bound(problem, Z, max_steps=2) == []
    inflated = problem.replace(lower_bound=lambda z, s: problem.lower_bound(z, s) + 1.0)
    assert check_lower_bound(inflated, Z, max_steps=1)  # caught wherever the band is reachable in one step

    v = hm.liftoff_velocity(P)
    fallback = hm.make_problem(4, P, bound=True, terminal=False)
    three = jnp.int32(3)

    @jax.jit
    def probe(Z):
        def err(z):
            return hm.model_energy(z, P) - hm.orbit_energy(z, v, P)

        def one_step(z):  # exact optimum of one unconstrained step
            return jnp.min(jax.vmap(lambda u: fallback.stage_cost(fallback.dynamics(z, u[None]), u[None]))(
                jnp.asarray(hm.VALVE_B)))

        closed = jax.vmap(lambda z: problem.dynamics(z, jnp.zeros(1)))(Z)
        frozen = Z.at[:, 4].set(1.0)  # lifted off where it stands
        return dict(moved=jnp.abs(jax.vmap(err)(closed) - jax.vmap(err)(Z)),
                    bound=jax.vmap(lambda z: problem.lower_bound(z, three))(Z),
                    low_a=jax.vmap(lambda z: problem.lower_bound(z, three))(Z.at[:, 2].multiply(0.98)),
                    e_frozen=jnp.abs(jax.vmap(err)(frozen)),
                    fallback=jax.vmap(lambda z: fallback.lower_bound(z, jnp.int32(1)))(jnp.concatenate([Z, frozen])),
                    exact=jax.vmap(one_step)(jnp.concatenate([Z, frozen])))

    r = {k: np.asarray(a) for k, a in probe(Zall).items()}
    assert np.all(r["moved"] <= hm.PASSIVE_DRIFT)
    assert np.all((r["bound"] > 0) & (r["bound"] <= hm.OPEN_COST))  # contact: at most one opening's worth
    assert np.all(r["low_a"] == 0)  # side a's law would charge: the bound must not rely on conservation
    # The fallback's bound (no terminal set) claims no +inf: admissible on contact states and on frozen
    # (lifted-off) ones outside the band, where the constrained bound's +inf would be wrong.
    assert fallback.terminal is None and np.any(r["e_frozen"] > hm.ENERGY_TOL)
    assert np.all(r["fallback"] <= r["exact"])


def test_warm_candidate_takes_the_unshifted_plan_when_the_shifted_one_misses_the_band(sdfs_loop):
    from firhc_jax._src.search.nodes import rollout_cost

    loop, _ = sdfs_loop
    S = np.asarray(loop.states)
    problem = hm.make_problem(4, P, bound=True)
    previous = np.array([0, 0, 0, 1], np.int32)  # step 28's plan: exhaust for three periods
    z = hm.observe(jnp.asarray(S[29]), None)

    @jax.jit
    def probe(z, previous):
        shifted = jnp.concatenate([previous[1:], previous[-1:]])
        return (rollout_cost(problem, z, shifted, jnp.float64)[0], rollout_cost(problem, z, previous, jnp.float64)[0],
                app.warm_candidate(problem, z, previous), app.warm_candidate(problem, z, jnp.full(4, -1, jnp.int32)))

    c_shifted, c_previous, warm, none = probe(z, jnp.asarray(previous))
    assert np.isinf(c_shifted) and np.isfinite(c_previous)
    np.testing.assert_array_equal(warm, previous)
    np.testing.assert_array_equal(none, -1)  # no previous plan: no warm start
