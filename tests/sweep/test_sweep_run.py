"""``ampc sweep`` end to end: the table, resume, refusal of a different sweep, and the
same table from one device, four forced CPU devices and two processes joined by
``jax.distributed`` (JAX's CPU collectives, gloo)."""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pyarrow.parquet as pq
import pytest

from ampc_jax.cli import main
from ampc_jax.testing.budget import budget

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


SMALL = ["--family", "cruise_step", "--cases", "8", "--chunk", "4", "--quiet", "--no-figures"]


class _Bar:
    """A stand-in for tqdm that records its updates and postfixes."""

    made: list = []

    def __init__(self, *args, **kwargs):
        self.updates, self.postfix = [], []
        _Bar.made.append(self)

    def update(self, n):
        self.updates.append(n)

    def set_postfix(self, **kw):
        self.postfix.append(kw)

    def close(self):
        pass


def test_a_sweep_never_joins_rows_of_another_spec(tmp_path, capsys, monkeypatch):
    """With sweep.json deleted, a rerun with another grid must not join the old
    grid's chunks under the new spec, nor a foreign valid chunk, and a corrupt
    chunk is named. Every chunk carries
    its spec's hash and cases; anything else is refused naming the file.
    The bar moves after every call of the program, not per chunk."""
    import tqdm

    import ampc_jax.sweep.run as run

    monkeypatch.setattr(run, "SUB_PAIRS", 4, raising=False)  # calls of 2 cases x 2 points
    monkeypatch.setattr(tqdm, "tqdm", _Bar)
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)]) == 0
    bar = _Bar.made[-1]
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--seed", "1", "--out", str(b)]) == 0
    capsys.readouterr()
    first = _table(a)

    def refused(*argv, name):
        code = main(["sweep", *SMALL, *argv, "--out", str(a)])
        err = capsys.readouterr().err
        assert code == 2, err
        assert err.startswith("ampc: error: --out: ") and name in err, err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        return err

    # sweep.json gone, another grid: the chunks of the old grid are refused
    (a / "sweep.json").unlink()
    err = refused("--rho", "0.5,3", name="chunk_00000.parquet")
    assert "another sweep" in err
    assert not (a / "sweep.json").exists()  # refused before anything was written
    # the same spec resumes: both chunks carry its hash
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)]) == 0
    assert "0 chunk(s) run, 2 skipped" in capsys.readouterr().out
    _same_rows(first, _table(a), exact=True)
    keep = tmp_path / "keep.parquet"
    shutil.copy(a / "chunks" / "chunk_00001.parquet", keep)
    # a valid chunk of another sweep (seed 1) in place of chunk 1
    shutil.copy(b / "chunks" / "chunk_00001.parquet", a / "chunks" / "chunk_00001.parquet")
    assert "another sweep" in refused("--rho", "0.5,2", name="chunk_00001.parquet")
    shutil.copy(keep, a / "chunks" / "chunk_00001.parquet")
    # a stray chunk beyond this sweep's two
    shutil.copy(keep, a / "chunks" / "chunk_00007.parquet")
    assert "not a chunk of this sweep" in refused("--rho", "0.5,2", name="chunk_00007")
    (a / "chunks" / "chunk_00007.parquet").unlink()
    # chunk 1 moved to chunk 0's place: its cases are not chunk 0's
    shutil.copy(a / "chunks" / "chunk_00000.parquet", keep.with_suffix(".0"))
    shutil.copy(keep, a / "chunks" / "chunk_00000.parquet")
    assert "holds cases 4..7" in refused("--rho", "0.5,2", name="chunk_00000")
    # a corrupt chunk and a corrupt sweep.json: one clear line each
    (a / "chunks" / "chunk_00000.parquet").write_bytes(b"PAR1 not a parquet file")
    err = refused("--rho", "0.5,2", name="chunk_00000.parquet")
    assert "not a readable sweep chunk" in err and "--Could" not in err
    shutil.copy(keep.with_suffix(".0"), a / "chunks" / "chunk_00000.parquet")
    (a / "sweep.json").write_text("{not json")
    err = refused("--rho", "0.5,2", name="sweep.json")
    assert "not a sweep manifest" in err and "--Expecting" not in err
    (a / "sweep.json").write_text(json.dumps({"spec": [1]}))
    refused("--rho", "0.5,2", name="sweep.json")
    (a / "sweep.json").unlink()
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)]) == 0
    _same_rows(first, _table(a), exact=True)
    # the first run's bar moved after every call of 2 cases, not per chunk of 4
    assert bar.updates == [2, 2, 2, 2]
    assert len(bar.postfix) == 4 and all("waste" in p for p in bar.postfix)


def _relabel(src, dst):
    """``src``'s rows under ``dst``'s record (its Parquet metadata: spec hash, chunk
    number, cases), written in ``dst``'s place: a chunk whose label was copied."""
    from ampc_jax.sweep.store import META_KEY

    label = pq.read_metadata(dst).metadata[META_KEY]
    table = pq.read_table(src).replace_schema_metadata({META_KEY: label})
    pq.write_table(table, dst)


def _edit_column(path, name, value):
    """A column of a chunk set to ``value`` in every row, its record kept."""
    import pyarrow as pa

    table = pq.read_table(path)
    col = pa.array([value] * table.num_rows, table.schema.field(name).type)
    table = table.set_column(table.schema.get_field_index(name), name, col)
    pq.write_table(table, path)


def test_a_chunk_is_known_by_its_content_not_its_label(tmp_path, capsys):
    """A chunk of another sweep under this sweep's record (its Parquet metadata
    copied) was joined: another seed's chunk gave "0 chunk(s) run, 2 skipped" and
    a table of two seeds' operating points. Its rows are checked against the spec
    (cases, points, rho, family, formulation, seed) and its drawn operating points
    against the cases this spec draws: another seed, other rho points, another
    family, another case count are refused naming the file; the chunk restored,
    the sweep resumes."""
    a, b, c, d = (tmp_path / x for x in "abcd")
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)]) == 0
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--seed", "1", "--out", str(b)]) == 0
    assert main(["sweep", *SMALL, "--rho", "0.5,3", "--out", str(c)]) == 0
    assert main(["sweep", *SMALL[:3], "6", *SMALL[4:], "--rho", "0.5,2", "--out", str(d)]) == 0
    capsys.readouterr()
    first = _table(a)
    mine = a / "chunks" / "chunk_00001.parquet"
    keep = tmp_path / "keep.parquet"
    shutil.copy(mine, keep)

    def refused(words):
        code = main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)])
        err = capsys.readouterr().err
        assert code == 2, err
        assert err.startswith("ampc: error: --out: ") and str(mine) in err, err
        assert len(err.strip().splitlines()) == 1 and words in err, err
        shutil.copy(keep, mine)

    _relabel(b / "chunks" / "chunk_00001.parquet", mine)  # the reported case
    refused("seed 1, this sweep's is 0")
    _relabel(c / "chunks" / "chunk_00001.parquet", mine)
    refused("rho_scale 3.0 at point 1, this sweep's is 2.0")
    _relabel(d / "chunks" / "chunk_00001.parquet", mine)  # cases 4..5 of 6
    refused("has 4 rows, not 8")
    _edit_column(mine, "family", "stability_step")
    refused("family 'stability_step'")
    # a forger who also writes this sweep's seed into the rows: the operating
    # points are still another seed's
    _relabel(b / "chunks" / "chunk_00001.parquet", mine)
    _edit_column(mine, "seed", 0)
    refused("this sweep draws")
    assert main(["sweep", *SMALL, "--rho", "0.5,2", "--out", str(a)]) == 0
    assert "0 chunk(s) run, 2 skipped" in capsys.readouterr().out
    _same_rows(first, _table(a), exact=True)


def test_memory_is_estimated_before_a_sweep_starts(tmp_path, capsys, monkeypatch):
    """10^7 rho points would run into XLA's RESOURCE_EXHAUSTED (184 GB) and
    --chunk 10**9 would pad every chunk to 10^9 cases. The grid, a call, a
    chunk's rows and the joined table are estimated up front: refused naming
    the flag and the estimate, or (a chunk beyond the cases) one chunk of them."""
    import ampc_jax.sweep.run as run

    base = ["sweep", "--family", "cruise_step", "--quiet", "--no-figures"]
    code = main([*base, "--cases", "1", "--rho", "0.1:10:10000000", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ampc: error: --rho: 10,000,000 points"), err
    assert re.search(r"[\d.]+ [GTP]B", err) and "available" in err, err
    assert not (tmp_path / "r" / "sweep.json").exists()
    # a chunk beyond the cases is one chunk of the cases: nothing padded to 10^9
    out = tmp_path / "c"
    assert (
        main([*base, "--cases", "4", "--rho", "1", "--chunk", str(10**9), "--out", str(out)]) == 0
    )
    assert "4 rows (4 cases x 1 rho points)" in capsys.readouterr().out
    assert json.loads((out / "sweep.json").read_text())["chunk_cases"] == 4
    # a chunk's rows and the joined table against the memory the machine has
    code = main([*base, "--cases", str(10**12), "--chunk", str(10**12), "--out", str(out / "x")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ampc: error: --chunk: ") and "--chunk " in err, err
    code = main([*base, "--cases", str(10**12), "--out", str(out / "x")])
    err = capsys.readouterr().err
    assert (
        code == 2 and err.startswith("ampc: error: --cases: ") and re.search(r"[\d.]+ [TP]B", err)
    ), err
    # on a device: a call against the device's free memory
    spec = run.SweepSpec(family="cruise_step", cases=8, rho=(1.0,) * 4000)

    class Gpu:
        platform = "gpu"

        def __init__(self, limit):
            self.limit = limit

        def memory_stats(self):
            return {"bytes_limit": self.limit, "bytes_in_use": 0}

    with pytest.raises(ValueError, match=r"^rho: .* 128 MB per device, more than the 100 MB free"):
        run.check_memory(spec, "step", 1000, [Gpu(10**8)], available=10**12)
    est = run.check_memory(spec, "step", 1000, [Gpu(10**9)] * 64, available=10**12)
    assert est["cases_per_call"] == 64 and est["call"] == 64 * 4000 * 32_000
    # a horizon whose condensed forms do not fit, named before any case of it is built
    code = main([*base, "--cases", "1", "--horizon", str(10**6), "--out", str(out / "h")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ampc: error: --horizon: N_p = 1000000"), err


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


@pytest.mark.slow  # four XLA processes; sharding over two devices is tests/batch/test_batch.py's test_sharded_over_two_cpu_devices, the parallel shards tests/sweep/test_sweep_shards.py's
@pytest.mark.both_cores
def test_four_devices_and_two_processes_give_the_same_table(tmp_path, capsys):
    r = subprocess.run(
        [sys.executable, "-c", PARTITION],
        env=_env(4),
        capture_output=True,
        text=True,
        timeout=budget(200),
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
        timeout=budget(200),
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
    outs = [p.communicate(timeout=budget(240)) for p in procs]
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


def test_closed_loop_family(tmp_path, capsys, monkeypatch):
    import tqdm

    monkeypatch.setattr(tqdm, "tqdm", _Bar)
    out = tmp_path / "loops"
    args = ["sweep", "--family", "cruise_lane_change", "--cases", "2", "--rho", "0.5,2"]
    assert main([*args, "--duration", "0.5", "--quiet", "--no-figures", "--out", str(out)]) == 0
    assert "4 closed loops" in capsys.readouterr().out
    assert _Bar.made[-1].postfix == []  # no waste=nan: a closed loop's work is not counted
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
