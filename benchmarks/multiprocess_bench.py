"""``fj.solve_batch`` over processes against over devices of one process.

    python benchmarks/multiprocess_bench.py            # tanks N=4 and synthetic N=4, B = 4096 (a few minutes)
    python benchmarks/multiprocess_bench.py --quick    # synthetic N=4, B = 256, one repeat (seconds)

Three layouts of the same batch, each run as ``python -m firhc_jax batch``
(firhc_jax/apps/batch.py) in fresh processes:

* 1 process x 1 device;
* 1 process x 2 devices (``XLA_FLAGS=--xla_force_host_platform_device_count=2``);
* 2 processes x 1 device (one JAX job on 127.0.0.1, gloo CPU collectives,
  ``firhc_jax.distributed.launch_local``).

The states are drawn (fixed seed, with replacement) from the closed-loop
states of ``benchmarks/batch_bench.py`` and written once to an ``.npz``.
Every layout makes a first (compiling) call, then ``--repeats`` timed calls;
the table shows their median (process 0's clock; the processes start each
call together, and the time includes the all-gather that gives every process
the whole result). "same as 1 x 2" compares every field (costs, sequences,
node counts) bit for bit; "same as 1 x 1" compares costs (to 1e-12) and
sequences: the pool's node counts depend on which rows share a device.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
LAYOUTS = (("1 x 1", 1, 1), ("1 x 2", 1, 2), ("2 x 1", 2, 1))  # (name, processes, devices per process)


def make_states(plant: str, horizon: int, batch: int, path: Path) -> None:
    """Closed-loop states of ``plant``, ``batch`` rows drawn with replacement, as ``X0`` in ``path``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    from batch_bench import closed_loop_states

    from firhc_jax._src.tools.distributed import save_states

    _, states = closed_loop_states(plant, horizon)
    save_states(path, states[np.random.default_rng(1).integers(0, len(states), batch)])


def run_layout(plant: str, horizon: int, states: Path, out: Path, processes: int, devices: int, repeats: int,
               timeout: float):
    from firhc_jax._src.tools.distributed import launch_local, load_result

    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    args = ["-m", "firhc_jax", "batch", "--plant", plant, "-N", str(horizon), "--states", str(states),
            "--out", str(out), "--repeats", str(repeats)]
    if processes == 1:
        subprocess.run([sys.executable, *args], env=env, cwd=ROOT, check=True, timeout=timeout, capture_output=True)
    else:
        done = launch_local(args, processes, env=env, timeout=timeout, capture=True, cwd=ROOT)
        for i, d in enumerate(done):
            if d.returncode != 0:
                raise RuntimeError(f"process {i} failed ({d.returncode}):\n{d.stderr[-3000:]}")
    return load_result(out)


def same(a, b, fields) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True) for f in fields)


def measure(plant: str, horizon: int, batch: int, repeats: int, timeout: float, tmp: Path) -> list[dict]:
    states = tmp / f"{plant}.npz"
    make_states(plant, horizon, batch, states)
    runs = {name: run_layout(plant, horizon, states, tmp / f"{plant}_{p}x{d}.npz", p, d, repeats, timeout)
            for name, p, d in LAYOUTS}
    one, two = runs["1 x 1"][0], runs["1 x 2"][0]
    rows = []
    for name, _, _ in LAYOUTS:
        r, meta = runs[name]
        seconds = float(meta["seconds"])
        finite = np.isfinite(one.cost)
        rows.append({
            "plant": f"{plant} (N={horizon})", "layout": name, "B": batch, "seconds": seconds,
            "first_s": float(meta["first_seconds"]), "solves_per_s": batch / seconds,
            "nodes_per_s": float(np.sum(r.nodes, dtype=np.int64)) / seconds,
            "nodes": int(np.sum(r.nodes, dtype=np.int64)),
            "speedup": float(runs["1 x 1"][1]["seconds"]) / seconds,
            "same_as_1x2": same(r, two, r._fields),
            "same_as_1x1": bool(np.array_equal(r.sequence, one.sequence) and np.array_equal(finite, np.isfinite(r.cost))
                                and np.allclose(r.cost[finite], one.cost[finite], rtol=1e-12, atol=0))})
        print(f"# {plant} {name}: {seconds * 1e3:.0f} ms", file=sys.stderr, flush=True)
    return rows


def markdown(rows) -> str:
    lines = ["| plant | processes x devices | B | time (median) | first call | solves/s | nodes/s | speedup | "
             "nodes | same as 1 x 2 (all fields) | same costs and sequences as 1 x 1 |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        lines.append(f"| {r['plant']} | {r['layout']} | {r['B']:,} | {r['seconds'] * 1e3:.0f} ms | "
                     f"{r['first_s']:.1f} s | {r['solves_per_s']:,.0f} | {r['nodes_per_s']:.3g} | "
                     f"{r['speedup']:.2f}x | {r['nodes']:,} | {'yes' if r['same_as_1x2'] else 'NO'} | "
                     f"{'yes' if r['same_as_1x1'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="synthetic N=4, B = 256, one repeat")
    ap.add_argument("--plants", default="tanks:4,synthetic:4", help="plant:horizon list (tanks, synthetic)")
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per layout")
    args = ap.parse_args(argv)
    if args.quick:
        args.plants, args.batch, args.repeats = "synthetic:4", 256, 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for item in args.plants.split(","):
            plant, horizon = item.split(":")
            rows += measure(plant, int(horizon), args.batch, args.repeats, args.timeout, Path(tmp))
    print(markdown(rows))


if __name__ == "__main__":
    main()
