"""Reliability at the controller's and the files' edges: a non-finite input found is never applied, saved runs
are read only when their declared shapes agree, messages name what the user wrote, helpers take what they say."""
import io
import zipfile

import jax.numpy as jnp
import numpy as np
import pytest

import firhc_jax as fj

CONTROLS = jnp.array([-1.0, 0.0, 1.0])


def _nan_first_input(x0, sequence):
    """The optimal sequence's first input, except NaN from states beyond 0.5."""
    return jnp.where(x0[0] > 0.5, jnp.nan, CONTROLS[jnp.maximum(sequence[0], 0)]).reshape(1)


NAN_INPUT = fj.Problem(lambda x, u: 0.5 * x + u, CONTROLS, fj.quadratic_cost(1.0, 0.0), 2,
                       first_input_of=_nan_first_input)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_non_finite_first_input_of_is_held_never_applied(compiled):
    ctrl = fj.FIRHC(NAN_INPUT)
    x0, u0 = jnp.array([1.0]), jnp.array([-0.25])
    with pytest.warns(RuntimeWarning, match=r"first input was not finite\) at 1 of 3 steps .* held"):
        run = ctrl.simulate(x0, 3, u0=u0, compiled=compiled)
    assert np.isfinite(np.asarray(run.inputs)).all() and np.isfinite(np.asarray(run.states)).all()
    np.testing.assert_array_equal(np.asarray(run.held), [True, False, False])
    assert float(run.inputs[0, 0]) == -0.25  # u0 held at step 0; from x = 0.25 an input is found again
    assert (np.asarray(run.plans[0]) == -1).all() and int(run.input_indices[0]) == -1
    assert np.isnan(float(run.stage_costs[0]))


def test_step_holds_the_safe_input_and_the_one_shot_call_raises_on_a_non_finite_input():
    x0 = jnp.array([1.0])
    ctrl = fj.FIRHC(NAN_INPUT, u_safe=jnp.array([0.0]))
    u, state, info = ctrl.step(ctrl.init(x0, jnp.array([1.0])), x0)
    assert float(u[0]) == 0.0 and bool(info.held) and (np.asarray(state.plan) == -1).all()
    with pytest.raises(fj.InfeasibleError, match=r"first_input_of returned a non-finite input \[nan\]"):
        ctrl(x0)
    u, _ = ctrl(jnp.array([0.2]))  # where first_input_of is finite the decision stands
    assert np.isfinite(float(u[0]))


# -- saved runs: ClosedLoop.load checks the declared shapes before reading ------------------------------------
LOOP = fj.FIRHC(fj.Problem(lambda x, u: jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]]), CONTROLS,
                           fj.quadratic_cost(jnp.array([1.0, 0.1]), jnp.zeros(2), 0.01), 3))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """The fields of a saved 6-step run (NumPy arrays) and the path of the file."""
    path = LOOP.simulate(jnp.array([1.0, 0.0]), 6, dt=0.1).save(tmp_path_factory.mktemp("run") / "run.npz")
    with np.load(path) as data:
        return {k: data[k] for k in data.files}, path


def _npy_header(shape, dtype) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                               "fortran_order": False, "shape": shape})
    return out.getvalue()


def test_load_refuses_a_header_declaring_more_data_than_the_file_holds(saved, tmp_path):
    """A 0.4 MB file whose states declare 400 MB: refused from the header, nothing allocated."""
    fields, _ = saved
    path = tmp_path / "crafted.npz"
    with zipfile.ZipFile(path, "w") as z:
        for name, a in fields.items():
            if name == "states":
                z.writestr("states.npy", _npy_header((50_000_001, 1), np.float64) + bytes(400_000))
            else:
                buf = io.BytesIO()
                np.save(buf, a)
                z.writestr(f"{name}.npy", buf.getvalue())
    with pytest.raises(ValueError, match=r"'states.npy' declares shape \(50000001, 1\) of float64 "
                                         r"\(400,000,008 bytes\) but holds 400,000 bytes"):
        fj.ClosedLoop.load(path)


def test_load_refuses_compressed_data_beyond_the_file_size(saved, tmp_path):
    """Deflated zeros: 1.6 MB of data in a file of a few kB (a zip bomb in small)."""
    fields, _ = saved
    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, **{**fields, "states": np.zeros((100_001, 2))})
    with pytest.raises(ValueError, match=r"declare 1,60\d,\d+ bytes of data, more than the file's"):
        fj.ClosedLoop.load(path)


@pytest.mark.parametrize("field, bad", [("states", lambda a: a[:-1]), ("plans", lambda a: a[:, :2].T),
                                        ("held", lambda a: a.astype(np.float64)), ("times", lambda a: a[:3]),
                                        ("inputs", lambda a: a[:, 0])])
def test_load_refuses_fields_of_inconsistent_shapes(saved, tmp_path, field, bad):
    fields, _ = saved
    path = tmp_path / "bad.npz"
    np.savez(path, **{**fields, field: bad(fields[field])})
    with pytest.raises(ValueError, match=f"not a consistent ClosedLoop: {field} has shape"):
        fj.ClosedLoop.load(path)


def test_load_says_what_a_npy_file_or_another_file_is(saved, tmp_path):
    fields, path = saved
    assert fj.ClosedLoop.load(path).states.shape == (7, 2)  # the genuine file loads
    np.save(tmp_path / "states.npy", fields["states"])
    with pytest.raises(ValueError, match=r"is a \.npy file \(one array\); ClosedLoop.load reads the \.npz"):
        fj.ClosedLoop.load(tmp_path / "states.npy")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match="not an .npz archive"):
        fj.ClosedLoop.load(tmp_path / "notes.txt")
    np.savez(tmp_path / "objects.npz", **{**fields, "nodes": np.array([None] * 6, object)})
    with pytest.raises(ValueError, match="Python objects"):
        fj.ClosedLoop.load(tmp_path / "objects.npz")


def test_load_says_a_damaged_archive_is_damaged_in_one_line(saved, tmp_path):
    """One flipped byte inside the data of a member: its checksum fails as numpy reads it."""
    _, path = saved
    data = bytearray(open(path, "rb").read())
    with zipfile.ZipFile(path) as z:
        member = z.getinfo("states.npy")
    data[member.header_offset + 30 + len(member.filename) + len(member.extra) + member.file_size - 3] ^= 0xFF
    (tmp_path / "damaged.npz").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"damaged\.npz is a damaged \.npz archive \(Bad CRC-32 for file "
                                         r"'states\.npy'\); save the run again$"):
        fj.ClosedLoop.load(tmp_path / "damaged.npz")


def test_load_blames_inputs_of_four_axes_on_inputs(saved, tmp_path):
    fields, _ = saved
    np.savez(tmp_path / "four.npz", **{**fields, "inputs": fields["inputs"][None, None]})
    with pytest.raises(ValueError, match=r"not a consistent ClosedLoop: inputs has shape \(1, 1, 6, 1\), "
                                         r"expected \[T, m'\] \(one run\) or \[B, T, m'\] \(B runs\)"):
        fj.ClosedLoop.load(tmp_path / "four.npz")


@pytest.mark.parametrize("call", ["profile", "check_problem"])
def test_string_states_are_refused_naming_states(call):
    prob = fj.Problem(lambda x, u: 0.9 * x + u, CONTROLS, fj.quadratic_cost(1.0, 0.0), 2)
    fn = fj.profile if call == "profile" else fj.diagnostics.check_problem
    with pytest.raises(TypeError, match=r"^states must be a real numeric batch of states \[B, n\], got dtype <U1$"):
        fn(prob, np.array([["a"], ["b"]]))


def test_plot_names_the_curves_and_labels_the_time_axis_in_seconds(saved):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = plt.get_fignums()
    run = fj.ClosedLoop.load(saved[1])
    fig = run.plot(state_names=["position [m]", "speed [m/s]"], input_names=["force [N]"])
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["position [m]", "speed [m/s]"]
    assert fig.axes[1].get_ylabel() == "force [N]"  # each input on its own axes, named
    assert fig.axes[-1].get_xlabel() == "time [s]" and plt.get_fignums() == figures
    assert fig.axes[0].lines[0].get_xdata()[-1] == pytest.approx(0.6)  # seconds, not steps
    assert [t.get_text() for t in run._replace(times=None).plot().axes[0].get_legend().get_texts()] == \
        ["x[0]", "x[1]"]
    with pytest.raises(ValueError, match=r"state_names must name the run's 2 columns of states \[T\+1, n\], got 1"):
        run.plot(state_names=["position [m]"])
    with pytest.raises(TypeError, match="input_names must be a sequence of 1 strings"):
        run.plot(input_names="force")


# -- messages name what the user wrote ------------------------------------------------------------------------
def test_a_warm_start_out_of_range_is_reported_in_the_users_indices():
    """Five inputs of three effects (three classes): the message speaks of the five inputs."""
    controls = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [2, 0]], float)
    lt = fj.LinearTracking(np.eye(1), np.array([[1.0, 1.0]]), controls, 3)
    assert lt.num_classes == 3
    with pytest.raises(ValueError, match=r"warm_start indices must lie in \[0, 5\) .* got \[7, 7, 7\]"):
        lt.solve(np.zeros(1), np.zeros(2), np.zeros((3, 1)), warm_start=[7, 7, 7])
    assert bool(lt.solve(np.zeros(1), np.zeros(2), np.zeros((3, 1)), warm_start=[4, 4, 4]).feasible)


def test_a_negative_terminal_cost_is_blamed_on_terminal_cost():
    prob = fj.Problem(lambda x, u: 0.9 * x + u, CONTROLS, fj.quadratic_cost(1.0, 0.0), 2,
                      terminal_cost=lambda x: x[0] - 5.0)
    with pytest.raises(ValueError, match="terminal_cost"):
        fj.sdfs(prob, jnp.ones(1))
    found = fj.diagnostics.check_problem(prob, jnp.array([[1.0], [9.0]]))
    assert [(v.state, v.source) for v in found] == [(0, "terminal_cost")] and found[0].value == -4.0
    negative_stage = prob.replace(stage_cost=lambda x, u: x[0], terminal_cost=None)
    assert [(v.state, v.source) for v in fj.diagnostics.check_problem(negative_stage, jnp.array([[-9.0]]))] == \
        [(0, "stage_cost")]



def test_a_negative_stage_cost_beside_a_nan_one_is_reported():
    """From x = 0.3 the log cost is log 0.8 < 0 for one input and NaN for the other (the search discards that
    node and raises on the negative cost): the check reports the negative cost."""
    prob = fj.Problem(lambda x, u: x + u, jnp.array([0.5, -1.0]), lambda x, u: jnp.log(x[0]), 2)
    with pytest.raises(ValueError, match="negative"):
        fj.sdfs(prob, jnp.array([0.3]))
    found = fj.diagnostics.check_problem(prob, jnp.array([[0.3], [2.0]]))
    assert [(v.state, v.source) for v in found] == [(0, "stage_cost")]
    np.testing.assert_allclose(found[0].value, np.log(0.8))

# -- helpers take what they say ---------------------------------------------------------------------------------
def _bounded(bound):
    return fj.Problem(lambda x, u, p: x + u, CONTROLS, lambda x, u, p: (x[0] - p["t"][0]) ** 2, 2,
                      lower_bound=bound)


def test_check_lower_bound_takes_per_state_params_as_solve_batch_does():
    """State i is checked with params[i]: a bound too high for state 1's row only is caught there only."""
    states = jnp.array([[0.0], [0.5], [-1.0]])
    rows = {"t": jnp.array([[0.0], [3.0], [-1.0]]), "b": jnp.array([0.0, 50.0, 0.0])}
    problem = _bounded(lambda x, s, p: p["b"])
    found = fj.diagnostics.check_lower_bound(problem, states, params=rows)
    assert sorted({(v.state, v.source) for v in found}) == [(1, "lower_bound")] and len(found) == 2
    assert fj.diagnostics.check_lower_bound(problem, states, params=rows, per_state=True) == found
    shared = {"t": jnp.array([3.0]), "b": jnp.asarray(0.0)}  # one pytree for every state, as before
    assert fj.diagnostics.check_lower_bound(problem, states, params=shared) == []
    assert fj.diagnostics.check_problem(problem, states, params=rows) == []
    ambiguous = _bounded(lambda x, s, p: jnp.min(p["b"])).replace(  # sums fit both forms with S = 3
        stage_cost=lambda x, u, p: (x[0] - jnp.sum(p["t"])) ** 2)
    with pytest.raises(ValueError, match="pass per_state=True or per_state=False"):
        fj.diagnostics.check_lower_bound(ambiguous, states, params=rows)
    with pytest.raises(ValueError, match="neither as one pytree for every state .* nor as one row per state"):
        fj.diagnostics.check_lower_bound(problem, states, params={"t": jnp.zeros((2, 1)), "b": jnp.zeros(2)})
