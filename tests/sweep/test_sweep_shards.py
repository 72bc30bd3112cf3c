"""``ampc sweep --shard I/N`` and ``ampc sweep-merge``: shards run as parallel local
processes join into the unsharded run's table, bit for bit; a missing,
duplicated, unfinished or foreign shard is refused by name and nothing is
written; closed-loop sweeps shard the same way."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from ampc_jax.cli import main
from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(300)

# the same sweep as tests/sweep/test_sweep_run.py (its program compiled once):
# 3 chunks of 8 cases, one per shard
ARGS = ["--family", "cruise_step", "--cases", "24", "--rho", "0.3,1,3", "--chunk", "8"]
ARGS += ["--quiet", "--no-figures"]
N = 3


def _rows(path):
    return pq.read_table(path / "sweep.parquet").replace_schema_metadata(None)


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    """The unsharded sweep (in this process, which compiles and caches its
    program) and its 3 shards, run as 3 processes at once."""
    root = tmp_path_factory.mktemp("shards")
    assert main(["sweep", *ARGS, "--out", str(root / "whole")]) == 0
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "ampc_jax.cli", "sweep", *ARGS, "--shard", f"{i}/{N}"]
            + ["--out", str(root / f"s{i}")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(N)
    ]
    outs = [p.communicate(timeout=budget(240)) for p in procs]
    for i, (p, (o, e)) in enumerate(zip(procs, outs, strict=True)):
        assert p.returncode == 0, e[-3000:]
        assert f"shard {i}/{N}: 24 rows" in o and "1 chunk(s) run" in o, o
    return root


def test_shards_in_parallel_processes_merge_to_the_unsharded_table(shards, capsys):
    root = shards
    # each shard holds its own chunk and no table
    for i in range(N):
        assert sorted(p.name for p in (root / f"s{i}" / "chunks").iterdir()) == [
            f"chunk_{i:05d}.parquet"
        ]
        assert not (root / f"s{i}" / "sweep.parquet").exists()
        assert json.loads((root / f"s{i}" / "sweep.json").read_text())["shard"] == [i, N]
    out = root / "merged"
    dirs = [str(root / f"s{i}") for i in (2, 0, 1)]  # any order
    assert main(["sweep-merge", *dirs, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "72 rows (24 cases x 3 rho points) from 3 shard(s)" in text
    assert _rows(out).equals(_rows(root / "whole"))  # bit for bit, the same columns
    whole = json.loads((root / "whole" / "sweep.json").read_text())
    merged = json.loads((out / "sweep.json").read_text())
    assert merged["spec"] == whole["spec"] and merged["spec_hash"] == whole["spec_hash"]
    assert merged["shards"] == N and merged["chunks_run"] == N
    assert [r["shard"] for r in merged["shard_runs"]] == [[i, N] for i in range(N)]
    assert json.loads(pq.read_schema(out / "sweep.parquet").metadata[b"ampc"]) == merged
    for name in ("iterations_vs_rho.png", "best_rho.png"):  # the figures a sweep draws
        assert (out / name).stat().st_size > 0


def _refused(capsys, argv, *words):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err, err
    return err


def test_merge_refuses_a_missing_duplicated_unfinished_or_foreign_shard(shards, tmp_path, capsys):
    root = shards
    s0, s1, s2 = (root / f"s{i}" for i in range(N))
    out = tmp_path / "m"
    merge = ["sweep-merge", "--quiet", "--no-figures", "--out", str(out)]
    _refused(capsys, [*merge, str(s0), str(s2)], "shard 1/3 missing")
    copy = tmp_path / "copy_of_s0"
    shutil.copytree(s0, copy)
    _refused(capsys, [*merge, str(s0), str(s1), str(s2), str(copy)], "shard 0/3 given 2 times")
    _refused(capsys, [*merge, str(s0), str(s1), str(root / "whole")], "holds a whole sweep")
    _refused(capsys, [*merge, str(s0), str(s1), str(tmp_path)], "holds no sweep.json")

    def variant(name, src, edit):
        d = tmp_path / name
        shutil.copytree(src, d)
        edit(d)
        return d

    def manifest(**changes):
        def edit(d):
            doc = json.loads((d / "sweep.json").read_text())
            for k, v in changes.items():
                if k == "shard":
                    doc["shard"] = v
                else:
                    doc["spec"][k] = v
            (d / "sweep.json").write_text(json.dumps(doc))

        return edit

    # a shard of another sweep: its spec, or its chunks' spec hash
    seed = variant("seed", s1, manifest(seed=1))
    _refused(capsys, [*merge, str(s0), str(seed), str(s2)], str(seed), "another sweep", "seed")
    # another split of the same sweep
    four = variant("four", s1, manifest(shard=[1, 4]))
    _refused(capsys, [*merge, str(s0), str(four), str(s2)], "shard 1/4", "share N")
    # unfinished: its chunk missing
    gone = variant("gone", s1, lambda d: (d / "chunks" / "chunk_00001.parquet").unlink())
    _refused(capsys, [*merge, str(s0), str(gone), str(s2)], "not finished", "chunk 1 (cases 8..15)")
    # a chunk of another shard put into a shard's directory
    extra = variant(
        "extra", s1, lambda d: shutil.copy(s0 / "chunks" / "chunk_00000.parquet", d / "chunks")
    )
    _refused(capsys, [*merge, str(s0), str(extra), str(s2)], "not a chunk of shard 1/3")

    # a chunk whose rows are not the cases the spec draws, under its own record
    def forged(d):
        path = d / "chunks" / "chunk_00001.parquet"
        table = pq.read_table(path)
        mu = table.column("mu").to_numpy().copy()
        mu[3] += 1e-3
        i = table.schema.get_field_index("mu")
        pq.write_table(table.set_column(i, "mu", pa.array(mu)), path)

    bad = variant("forged", s1, forged)
    _refused(capsys, [*merge, str(s0), str(bad), str(s2)], "this sweep draws", "mu")
    # the output: not a shard, and not a non-empty directory without --force
    _refused(capsys, [*merge[:-1], str(s0), str(s0), str(s1), str(s2)], "one of the shards")
    full = tmp_path / "full"
    full.mkdir()
    (full / "notes.txt").write_text("mine")
    argv = ["sweep-merge", "--quiet", "--no-figures", str(s0), str(s1), str(s2)]
    _refused(capsys, [*argv, "--out", str(full)], "not empty", "--force")
    assert not out.exists()  # no refusal left anything behind
    assert main([*argv, "--out", str(full), "--force"]) == 0
    assert _rows(full).equals(_rows(root / "whole"))
    assert (full / "notes.txt").read_text() == "mine"


def test_shard_flag(shards, tmp_path, capsys):
    s0 = shards / "s0"
    usage = ["sweep", *ARGS]
    for bad in ("3/3", "1", "a/2", "-1/2", "0/0"):
        with pytest.raises(SystemExit) as exc:
            main([*usage, f"--shard={bad}", "--out", str(tmp_path / "x")])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith("ampc: error: --shard: expected I/N") and repr(bad) in err, err
    _refused(capsys, [*usage, "--shard", "0/4", "--out", str(tmp_path / "x")], "at most 3 shards")
    assert not (tmp_path / "x").exists()
    _refused(capsys, [*usage, "--shard", "1/3", "--out", str(s0)], "holds shard 0/3", "--out")
    _refused(capsys, [*usage, "--out", str(s0)], "holds shard 0/3", "--out")
    # a rerun of a shard resumes it: its chunk checked against the spec, not solved
    assert main([*usage, "--shard", "0/3", "--out", str(s0)]) == 0
    assert "0 chunk(s) run, 1 skipped" in capsys.readouterr().out


def test_closed_loop_sweeps_shard_the_same_way(tmp_path, capsys):
    # calls of 2 closed loops, as tests/sweep/test_sweep_run.py's: one program
    args = ["sweep", "--family", "cruise_lane_change", "--cases", "4", "--rho", "0.5,2"]
    args += ["--duration", "0.5", "--chunk", "2", "--quiet", "--no-figures"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    for i in range(2):
        assert main([*args, "--shard", f"{i}/2", "--out", str(tmp_path / f"s{i}")]) == 0
    assert "shard 1/2: 4 rows" in capsys.readouterr().out  # cases 2, 3 at 2 points
    dirs = [str(tmp_path / "s1"), str(tmp_path / "s0")]
    assert main(["sweep-merge", *dirs, "--no-figures", "--out", str(tmp_path / "m")]) == 0
    merged = _rows(tmp_path / "m")
    assert merged.equals(_rows(tmp_path / "whole"))
    assert merged.num_rows == 8 and np.all(np.isfinite(merged.column("yaw_rms").to_numpy()))
