"""fj.solve_batch over several processes of one JAX job (two local CPU
processes joined on 127.0.0.1 with gloo collectives), the devices argument,
firhc_jax.distributed and ``python -m firhc_jax batch``."""
import os
import subprocess
import sys
import time

import _distributed_worker as worker
import jax
import numpy as np
import pytest
from repository import ROOT, TESTS

import firhc_jax as fj
from firhc_jax import distributed
from firhc_jax._src.runtime.sharding import mesh_of
from firhc_jax.cli import main as cli_main
from firhc_jax.models.synthetic import benchmark_state

TIMEOUT = 300  # s for a whole job (a safety net: the job takes seconds, 2-3 min on a loaded 2-core machine)


def child_env(devices: int) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_") or k == "JAX_ENABLE_X64"}
    env.update(XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(TESTS), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return env


def run_all(commands, tmp_path, timeout=TIMEOUT):
    """Start every ``(argv, env)`` at once and wait for all; on a failure or
    the timeout kill every process still running (always, in ``finally``)."""
    procs, logs = [], []
    deadline = time.monotonic() + timeout
    try:
        for i, (argv, env) in enumerate(commands):
            log = open(tmp_path / f"proc{i}.log", "w+")
            logs.append(log)
            procs.append(subprocess.Popen([sys.executable, *argv], env=env, cwd=ROOT, stdout=log,
                                          stderr=subprocess.STDOUT))
        while True:
            codes = [p.poll() for p in procs]
            if all(c is not None for c in codes) or any(c not in (None, 0) for c in codes):
                break
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            p.wait()
    texts = []
    for log in logs:
        log.seek(0)
        texts.append(log.read())
        log.close()
    for i, p in enumerate(procs):
        assert p.returncode == 0, f"process {i} exit {p.returncode} (killed on timeout or another's failure):\n" \
                                  + texts[i][-3000:]


@pytest.mark.slow
def test_two_processes_give_the_single_process_result(tmp_path):
    """2 processes x 1 device: every process gets the whole batch's result, identical (costs, sequences, node
    counts) to 1 process x 2 devices; costs and sequences also match 1 process x 1 device. The same for the
    closed loops of simulate_batch."""
    port = distributed.free_port()
    script = str(TESTS / "_distributed_worker.py")
    run_all([([script, tmp_path / "p0.npz", f"127.0.0.1:{port}", "2", "0"], child_env(1)),
             ([script, tmp_path / "p1.npz", f"127.0.0.1:{port}", "2", "1"], child_env(1)),
             ([script, tmp_path / "ref.npz"], child_env(2))], tmp_path)
    p0, p1, ref = (np.load(tmp_path / f"{name}.npz") for name in ("p0", "p1", "ref"))
    np.testing.assert_array_equal(p0["devices"], [2, 2])
    np.testing.assert_array_equal(ref["devices"], [2, 1])
    assert p0["refused"] and p1["refused"]  # different X0 on the two processes: a ValueError on both
    assert p0["loops_refused"] and p1["loops_refused"]  # simulate_batch too
    one = {}
    for name, solve in worker.cases():  # this process: 1 device
        res = solve()
        one.update({f"{name}.{field}": np.asarray(getattr(res, field)) for field in fj.SearchResult._fields})
    for key in one:
        np.testing.assert_array_equal(p0[key], p1[key], err_msg=key)
        np.testing.assert_array_equal(p0[key], ref[key], err_msg=key)
        name, field = key.split(".")
        # On 1 device the pool shares its lanes between all rows: other node counts; costs may differ in the
        # last bit where XLA vectorises a transcendental differently for 5 and 10 rows per device.
        if field == "cost":
            np.testing.assert_allclose(p0[key], one[key], rtol=1e-14, atol=0, err_msg=key)
        elif field not in ("nodes", "iterations") or name in ("sdfs-vmap", "exhaustive"):
            np.testing.assert_array_equal(p0[key], one[key], err_msg=key)
    assert np.any(p0["sdfs.feasible"]) and not np.all(p0["sdfs.nodes"] == 0)
    # simulate_batch: each process ran its share of the loops (4 of 7, one padded), and got every loop; one
    # process of 2 devices runs 2 parts of 4 (7 padded to 8).
    assert list(p0["loops_ran"]) == [4] and list(p1["loops_ran"]) == [4] and list(ref["loops_ran"]) == [8]
    loops = worker.closed_loops()
    for field, value in loops._asdict().items():
        if value is None:
            continue
        key = f"loops.{field}"
        np.testing.assert_array_equal(p0[key], p1[key], err_msg=key)
        np.testing.assert_allclose(p0[key], np.asarray(value), rtol=1e-12, atol=1e-15, err_msg=key)
        np.testing.assert_allclose(ref[key], np.asarray(value), rtol=1e-12, atol=1e-15, err_msg=key)


@pytest.mark.slow
def test_batch_command_on_two_local_processes(tmp_path):
    """``python -m firhc_jax batch --launch-local 2``'s machinery (launch_local and the app on 2 processes)
    gives the costs and sequences of a single-process run of the same command."""
    X0 = np.asarray(benchmark_state()) + np.random.default_rng(0).normal(0, 0.3, (24, 3))
    distributed.save_states(tmp_path / "X0.npz", X0)
    args = ["batch", "--plant", "synthetic", "-N", "3", "--states", str(tmp_path / "X0.npz")]
    assert cli_main(args + ["--out", str(tmp_path / "one.npz")]) == 0
    done = distributed.launch_local(["-m", "firhc_jax", *args, "--out", tmp_path / "two.npz"], 2,
                                    timeout=TIMEOUT, env=child_env(1), capture=True, cwd=ROOT)
    assert [d.returncode for d in done] == [0, 0], [d.stderr[-2000:] for d in done]
    assert "2 devices (2 processes)" in done[0].stdout
    one, meta1 = distributed.load_result(tmp_path / "one.npz")
    two, meta2 = distributed.load_result(tmp_path / "two.npz")
    assert (meta1["processes"], meta2["processes"], meta2["devices"]) == (1, 2, 2) and meta2["seconds"] > 0
    np.testing.assert_array_equal(one.sequence, two.sequence)
    np.testing.assert_allclose(one.cost, two.cost, rtol=1e-14, atol=0)
    assert one.cost.shape == (24,) and np.all(one.feasible)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.mark.slow
def test_a_failure_in_any_process_ends_the_whole_job(tmp_path, monkeypatch, capfd):
    """``batch --launch-local 2`` where process 1 fails after joining the job (process 0 then waits for it in a
    collective, and process 1's normal exit would wait for process 0): the launcher returns 1 at once with a
    message naming the failed process, and no process is left."""
    for key, value in child_env(1).items():
        monkeypatch.setenv(key, value)
    for key in (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID):
        monkeypatch.delenv(key, raising=False)
    distributed.save_states(tmp_path / "X0.npz", np.random.default_rng(0).uniform(-1, 1, (4, 3)))
    argv = ["batch", "--problem", "_distributed_worker:fails_on_process_1", "--states", str(tmp_path / "X0.npz"),
            "--out", str(tmp_path / "r.npz"), "--timeout", str(TIMEOUT)]
    t0 = time.monotonic()
    assert cli_main(argv + ["--launch-local", "2"]) == 1
    assert time.monotonic() - t0 < TIMEOUT / 2  # ended by the failure, not by the timeout
    err = capfd.readouterr().err  # the processes write to the launcher's file descriptors
    assert "process 1 fails on purpose" in err and "the job failed (process 0 killed" in err and "process 1 exit 1" \
        in err, err[-3000:]
    assert not (tmp_path / "r.npz").exists()


@pytest.mark.slow
def test_launcher_stops_on_timeout_with_a_message(tmp_path, capsys):
    """``--timeout`` too short for the job: a message and exit status 1, not a TimeoutExpired traceback."""
    distributed.save_states(tmp_path / "X0.npz", np.zeros((2, 3)))
    argv = ["batch", "--plant", "synthetic", "-N", "2", "--states", str(tmp_path / "X0.npz"), "--out",
            str(tmp_path / "r.npz"), "--launch-local", "2", "--timeout", "0.5"]
    assert cli_main(argv) == 1
    assert "did not finish within 0.5 s (--timeout); every process was stopped" in capsys.readouterr().err


@pytest.mark.slow
def test_no_launched_process_outlives_the_launcher(tmp_path):
    """The launcher killed with SIGKILL (no Python clean-up runs): its processes die with it."""
    child = f"import os, time; open(os.path.join({str(tmp_path)!r}, os.environ['JAX_PROCESS_ID']), 'w')" \
            ".write(str(os.getpid())); time.sleep(120)"
    launcher = subprocess.Popen([sys.executable, "-c", f"from firhc_jax import distributed\n"
                                 f"distributed.launch_local(['-c', {child!r}], 2)"], cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while not all((tmp_path / i).exists() and (tmp_path / i).read_text() for i in "01"):
            assert time.monotonic() < deadline and launcher.poll() is None, "the processes did not start"
            time.sleep(0.05)
        pids = [int((tmp_path / i).read_text()) for i in "01"]
        launcher.kill()
        launcher.wait()
        deadline = time.monotonic() + 10
        while any(map(_alive, pids)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(map(_alive, pids)), pids
    finally:  # nothing left behind, whatever happened
        launcher.kill()
        for f in (tmp_path / i for i in "01"):
            if f.exists() and f.read_text() and _alive(pid := int(f.read_text())):
                os.kill(pid, 9)


def _refuse_to_solve(*args, **kwargs):
    raise AssertionError("solved before the arguments were checked")


@pytest.mark.parametrize("out, launch, match", [
    ("/proc/nope/r.npz", False, "cannot write --out /proc/nope/r.npz: No such file or directory"),
    ("/proc/nope/r.npz", True, "cannot write --out"),  # the launcher checks before it starts the processes
    (".", False, "--out . is a directory"),
    ("sub", False, "--out sub is a directory"),
    ("r", False, "must name an .npz file"),
    ("X0.npz/r.npz", False, "cannot write --out X0.npz/r.npz: X0.npz is not a directory")])
def test_batch_checks_out_before_any_work(tmp_path, monkeypatch, out, launch, match):
    """An unwritable or ambiguous ``--out`` is a one-line error before anything is solved (``--out .`` wrote
    ``..npz`` and reported ``-> .``), and nothing is written."""
    monkeypatch.setattr(fj, "solve_batch", _refuse_to_solve)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    distributed.save_states("X0.npz", np.zeros((2, 3)))
    argv = ["batch", "--plant", "synthetic", "-N", "2", "--states", "X0.npz", "--out", out]
    with pytest.raises(SystemExit, match=match):
        cli_main(argv + (["--launch-local", "2", "--timeout", "60"] if launch else []))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["X0.npz", "sub"] and not any((tmp_path / "sub").iterdir())


@pytest.mark.parametrize("problem, states, match", [
    ("nosuchmod:f", None, "--problem nosuchmod:f: cannot import 'nosuchmod'"),
    ("os:getcwd", None, "--problem os:getcwd must return a firhc_jax.Problem, got str"),
    ("os:nosuchname", None, "module 'os' has no 'nosuchname'"),
    ("firhc_jax.models.tanks:make_problem", None, "must be a function without arguments"),
    (None, np.array([["a", "b", "c"]]), "X0 must hold real numbers, got dtype <U1")])
def test_batch_refuses_bad_problems_and_states_clearly(tmp_path, monkeypatch, problem, states, match):
    monkeypatch.setattr(fj, "solve_batch", _refuse_to_solve)
    distributed.save_states(tmp_path / "X0.npz", np.zeros((2, 3)) if states is None else states)
    what = ["--problem", problem] if problem else ["--plant", "synthetic", "-N", "2"]
    with pytest.raises(SystemExit, match=match):
        cli_main(["batch", *what, "--states", str(tmp_path / "X0.npz"), "--out", str(tmp_path / "r.npz")])


def test_launcher_kills_the_job_when_a_process_fails(tmp_path):
    """Process 1 fails at once; process 0 would wait for it forever (here: sleep 60 s, twice the timeout): the
    launcher returns both, killed, instead of raising TimeoutExpired."""
    code = "import os, time, sys\nif os.environ['JAX_PROCESS_ID'] == '1': sys.exit(3)\ntime.sleep(60)"
    done = distributed.launch_local(["-c", code], 2, timeout=30, capture=True)
    assert [d.returncode for d in done][1] == 3 and done[0].returncode != 0
    with pytest.raises(subprocess.TimeoutExpired):
        distributed.launch_local(["-c", "import time; time.sleep(60)"], 2, timeout=1)


def test_default_devices_are_every_device_of_the_job():
    assert list(mesh_of(None).devices.flat) == jax.devices()
    assert list(mesh_of(tuple(jax.devices())).devices.flat) == jax.devices()


@pytest.mark.parametrize("devices, error, match", [
    ("cpu", TypeError, "devices must be a list of jax devices"),
    (0, TypeError, "devices must be a list"),
    ([0], TypeError, r"devices\[0\] must be a jax device"),
    (["cpu"], TypeError, r"devices\[0\] must be a jax device"),
    ([], ValueError, "devices is empty"),
    ("dup", ValueError, "more than once")])
def test_bad_devices_are_refused_clearly(devices, error, match):
    if devices == "dup":
        devices = [jax.devices()[0]] * 2
    p = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: x[0] ** 2, 2)
    with pytest.raises(error, match=match):
        fj.solve_batch(p, np.ones((3, 1)), devices=devices)


def test_a_bare_device_is_refused():
    p = fj.Problem(lambda x, u: x + u, np.array([-1.0, 1.0]), lambda x, u: x[0] ** 2, 2)
    with pytest.raises(TypeError, match="devices must be a list of jax devices"):
        fj.solve_batch(p, np.ones((3, 1)), devices=jax.devices()[0])


def test_npz_files_and_job_settings(tmp_path, monkeypatch):
    np.savez(tmp_path / "bad.npz", states=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="no array 'X0'"):
        distributed.load_states(tmp_path / "bad.npz")
    distributed.save_states(tmp_path / "flat.npz", np.zeros((2, 3)))
    np.testing.assert_array_equal(distributed.load_states(tmp_path / "flat.npz"), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="not a solve_batch result"):
        distributed.load_result(tmp_path / "flat.npz")
    for var in (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID):
        monkeypatch.delenv(var, raising=False)
    assert distributed.job_settings() is None
    assert distributed.initialize() is False  # nothing described: a single process, nothing done
    with pytest.raises(ValueError, match="needs the coordinator address"):
        distributed.job_settings("127.0.0.1:1234")
    with pytest.raises(ValueError, match=r"process_id must be an int in \[0, 1\]"):
        distributed.job_settings("127.0.0.1:1234", 2, 2)
    with pytest.raises(ValueError, match="host:port"):
        distributed.job_settings("localhost", 2, 0)
    monkeypatch.setenv(distributed.ENV_COORDINATOR, "10.0.0.1:99")
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "4")
    monkeypatch.setenv(distributed.ENV_PROCESS_ID, "3")
    assert distributed.job_settings() == ("10.0.0.1:99", 4, 3)
