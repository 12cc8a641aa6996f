"""fj.enable_compilation_cache: opt in, where it writes, what a second process reads, and the CLI's --no-cache."""
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

import firhc_jax as fj
from firhc_jax import cli
from firhc_jax._src.runtime.disk_cache import default_cache_path


def _python(code: str, **env) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=300, env={**os.environ, **env})
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()[-1]


def test_importing_the_library_leaves_the_cache_off():
    assert _python("import jax, firhc_jax; print(jax.config.jax_compilation_cache_dir)") == "None"


def test_the_default_folder_follows_xdg_cache_home(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_path() == tmp_path / "firhc_jax"
    monkeypatch.setenv("XDG_CACHE_HOME", "")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_path() == tmp_path / "home" / ".cache" / "firhc_jax"


def test_a_folder_that_cannot_be_written_is_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OSError, match="cannot use .*file/cache"):
        fj.enable_compilation_cache(blocker / "cache")


def test_compilations_land_in_the_folder(tmp_path):
    """The suite's own cache is swapped for a fresh folder, a search compiles into it, and the suite's comes back."""
    before = jax.config.jax_compilation_cache_dir
    try:
        assert fj.enable_compilation_cache(tmp_path) == tmp_path.resolve()
        prob = fj.Problem(lambda x, u: 0.7 * x + u, [-1.0, 0.25, 1.0], fj.quadratic_cost(1.0, 0.3), 3)
        fj.sdfs(prob, jnp.ones(1))
        assert any(tmp_path.iterdir())
    finally:
        if before is not None:
            fj.enable_compilation_cache(before)


@pytest.mark.slow
def test_a_second_process_reads_the_decision_from_the_cache(tmp_path):
    """Two fresh processes compile the same decision: the second finds every XLA compilation on disk."""
    code = f"""
        import json, jax, jax.numpy as jnp, firhc_jax as fj
        hits = []
        jax.monitoring.register_event_listener(lambda e, **kw: hits.append(e))
        fj.enable_compilation_cache({str(tmp_path)!r})
        prob = fj.Problem(lambda x, u: jnp.tanh(0.9 * x + u), [-1.0, 0.0, 1.0], fj.quadratic_cost(1.0, 0.2), 4)
        fj.FIRHC(prob).simulate(jnp.ones(1), 5)
        print(json.dumps({{"hits": hits.count("/jax/compilation_cache/cache_hits"),
                          "asked": hits.count("/jax/compilation_cache/compile_requests_use_cache")}}))
    """
    first = json.loads(_python(code))
    written = [f.name for f in tmp_path.iterdir() if f.name.endswith("-cache")]
    second = json.loads(_python(code))
    assert first["asked"] > 0 and first["hits"] == 0, first
    # every compilation long enough to keep (MIN_COMPILE_SECONDS), the closed loop's among them, is read back
    assert any(name.startswith("jit__lambda") for name in written), written
    assert second["asked"] == first["asked"] and second["hits"] == len(written), (first, second, written)


def test_every_command_takes_no_cache_and_uses_the_cache_unless_told(monkeypatch):
    parser = cli.build_parser()
    leaves = list(cli._leaves(parser))
    assert len(leaves) >= 8
    for command in leaves:
        keeps = command.get_default("uses_cache") is not False
        assert ("--no-cache" in command._option_string_actions) == keeps, command.prog
        assert keeps or command.prog.endswith(" cache"), command.prog  # only the command that lists the folder
    used = []
    monkeypatch.setattr(cli, "_use_compilation_cache", lambda: used.append(True))
    monkeypatch.setattr(cli, "build_parser", lambda: _parser_with(lambda args: 0))
    assert cli.main(["noop"]) == 0 and used == [True]
    assert cli.main(["noop", "--no-cache"]) == 0 and used == [True]


def _parser_with(func):
    import argparse

    parser = argparse.ArgumentParser()
    noop = parser.add_subparsers(dest="command").add_parser("noop")
    noop.set_defaults(func=func)
    noop.add_argument("--no-cache", action="store_true")
    return parser


def test_the_cli_keeps_a_folder_this_process_already_chose(tmp_path):
    before = jax.config.jax_compilation_cache_dir
    try:
        chosen = str(fj.enable_compilation_cache(tmp_path))
        cli._use_compilation_cache()
        assert jax.config.jax_compilation_cache_dir == chosen
    finally:
        if before is not None:
            fj.enable_compilation_cache(before)


@pytest.mark.slow
def test_no_cache_reads_and_writes_nothing_in_the_folder_the_environment_names(tmp_path):
    """A folder filled by a run, then every file in it damaged: a ``--no-cache`` run with
    ``JAX_COMPILATION_CACHE_DIR`` naming it leaves every file as it was, adds none and warns of none."""
    cache = tmp_path / "cache"
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache)}

    def tanks(*args):
        proc = subprocess.run([sys.executable, "-m", "firhc_jax", "tanks", "--seconds", "4", "--no-progress",
                               "--out", str(tmp_path / "out"), *args], capture_output=True, text=True, timeout=600,
                              env=env)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stderr

    tanks()
    files = sorted(p for p in cache.rglob("*") if p.is_file())
    assert any(p.suffix == ".jaxexport" for p in files) and any(p.name.endswith("-cache") for p in files), files
    for p in files:
        p.write_bytes(b"damaged")
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in files}
    stderr = tanks("--no-cache")
    assert "warning" not in stderr.lower(), stderr
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(cache.rglob("*")) if p.is_file()} == before
