"""``ampc sweep`` end to end: the table, resume, refusal of a different sweep, and the
same table from one device, four forced CPU devices and two processes joined by
``jax.distributed`` (JAX's CPU collectives, gloo)."""

import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pyarrow.parquet as pq
import pytest

from ampc_jax.cli import main

pytestmark = pytest.mark.timeout(300)

ARGS = ["--family", "cruise_step", "--cases", "24", "--rho", "0.3,1,3", "--chunk", "8"]
ARGS += ["--quiet", "--no-figures"]


def _env(devices=None):
    env = dict(os.environ)
    if devices:
        env["XLA_FLAGS"] = (
            env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}"
        ).strip()
    return env


def _table(path):
    return pq.read_table(path / "sweep.parquet")


def _same_rows(a, b, exact):
    assert a.column_names == b.column_names
    assert a.num_rows == b.num_rows
    for c in a.column_names:
        x, y = a.column(c).to_numpy(), b.column(c).to_numpy()
        if x.dtype.kind == "f" and not exact:
            np.testing.assert_allclose(x, y, rtol=1e-8, atol=1e-10, err_msg=c)
        elif x.dtype.kind == "f":
            np.testing.assert_array_equal(x, y, err_msg=c)
        else:
            assert np.array_equal(x, y), c


def test_table_resume_and_refusal(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["sweep", *ARGS, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "72 rows (24 cases x 3 rho points)" in text and "3 chunk(s) run" in text
    tab = _table(out)
    assert tab.num_rows == 72
    for col in ("case", "rho_scale", "iterations", "converged", "status", "e_sub", "violation"):
        assert col in tab.column_names
    assert set(tab.column("case").to_pylist()) == set(range(24))
    assert b"ampc" in tab.schema.metadata
    # every pair converged at the vehicle tolerance; e_sub is finite and in Nm
    assert all(tab.column("converged").to_pylist())
    assert np.all(np.isfinite(tab.column("e_sub").to_numpy()))
    # one chunk lost: the rerun computes only that one, and the table is the same
    (out / "chunks" / "chunk_00001.parquet").unlink()
    assert main(["sweep", *ARGS, "--out", str(out)]) == 0
    assert "1 chunk(s) run, 2 skipped" in capsys.readouterr().out
    _same_rows(tab, _table(out), exact=True)
    # another grid into the same directory is refused, naming what differs
    assert main(["sweep", *ARGS[:5], "0.3,1", *ARGS[6:], "--out", str(out)]) == 2
    assert "--out" in capsys.readouterr().err


def test_bad_flags(capsys, tmp_path):
    assert main(["sweep", "--family", "nope", "--out", str(tmp_path)]) == 2
    assert "--family" in capsys.readouterr().err
    assert main(["sweep", "--family", "generated", "--rho", "1:0:3", "--out", str(tmp_path)]) == 2
    assert "--rho" in capsys.readouterr().err
    args = ["sweep", "--family", "generated", "--duration", "1", "--out", str(tmp_path)]
    assert main(args) == 2
    assert "--duration" in capsys.readouterr().err


PARTITION = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from ampc_jax.formulations import formulation
    from ampc_jax.sweep import family, pair_data, pair_params, sweep_solve
    assert len(jax.devices()) == 4
    c = family("generated").sample(8, seed=1)
    s = formulation("local_explicit", c.topology, max_iter=200)
    g = s.params(rho=[[1.0, 1.0], [2.0, 2.0]])
    res, work = sweep_solve(s, pair_data(c.data, 2), pair_params(g, 8))
    shards = res.iterations.addressable_shards
    assert len({sh.device for sh in shards}) == 4
    assert all(sh.data.shape == (4,) for sh in shards)
    assert work.computed.shape == (4,)
    print("partitioned", len(shards))
    """
)


@pytest.mark.both_cores
def test_four_devices_and_two_processes_give_the_same_table(tmp_path, capsys):
    r = subprocess.run(
        [sys.executable, "-c", PARTITION], env=_env(4), capture_output=True, text=True, timeout=200
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "partitioned 4" in r.stdout
    one, four, two = tmp_path / "one", tmp_path / "four", tmp_path / "two"
    assert main(["sweep", *ARGS, "--out", str(one)]) == 0
    r = subprocess.run(
        ["ampc", "sweep", *ARGS, "--cpu-devices", "4", "--out", str(four)],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=200,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [
        subprocess.Popen(
            ["ampc", "sweep", *ARGS, "--cpu-devices", "2", "--num-processes", "2"]
            + ["--process-id", str(k), "--coordinator", f"127.0.0.1:{port}", "--out", str(two)],
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for k in range(2)
    ]
    outs = [p.communicate(timeout=240) for p in procs]
    for p, (_, e) in zip(procs, outs, strict=True):
        assert p.returncode == 0, e[-3000:]
    assert "on 4 device(s), 2 process(es)" in outs[0][0]
    # each process wrote the rows its own devices hold: complementary halves
    for k in range(3):
        parts = [pq.read_table(two / "chunks" / f"chunk_{k:05d}.p{p}of2.parquet") for p in (0, 1)]
        cases = [set(t.column("case").to_pylist()) for t in parts]
        assert cases[0] and cases[1] and not cases[0] & cases[1]
    # four devices in one process and two processes of two: the same per-device
    # programs, bit for bit; against one device (another batch size, so other
    # vectorised code) the same integers and floats to round-off
    _same_rows(_table(four), _table(two), exact=True)
    _same_rows(_table(one), _table(four), exact=False)


def test_closed_loop_family(tmp_path, capsys):
    out = tmp_path / "loops"
    args = ["sweep", "--family", "cruise_lane_change", "--cases", "2", "--rho", "0.5,2"]
    assert main([*args, "--duration", "0.5", "--quiet", "--no-figures", "--out", str(out)]) == 0
    assert "4 closed loops" in capsys.readouterr().out
    tab = _table(out)
    assert tab.num_rows == 4
    assert set(tab.column("n_steps").to_pylist()) == {10}
    for col in ("iterations", "iterations_max", "e_sub", "yaw_rms", "slip_max", "torque_max"):
        assert np.all(np.isfinite(tab.column(col).to_numpy())), col
    # the drawn friction of each case is in its rows
    mu = tab.column("mu").to_numpy()
    assert mu[0] == mu[1] and mu[2] == mu[3] and mu[0] != mu[2]


def test_full_groups_reach_the_integrated_optimum(tmp_path, capsys):
    # the reference is Clarabel on the condensed QP: with every agent in every
    # group the decomposition is exact, and e_sub shrinks with the tolerance
    # (the paper's cruise groups drop a weak coupling: several Nm by design)
    out = tmp_path / "full"
    args = ["sweep", "--family", "cruise_step", "--cases", "12", "--rho", "1", "--groups"]
    args += ["full", "--tol", "1e-8", "--max-iter", "2000", "--quiet", "--no-figures"]
    assert main([*args, "--out", str(out)]) == 0
    tab = _table(out)
    assert all(tab.column("converged").to_pylist())
    assert float(np.max(tab.column("e_sub").to_numpy())) < 1e-2
