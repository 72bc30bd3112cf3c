"""Import-time XLA flags of ampc_jax (README, "Known issues" and "Speed"): the one
global effect of the import, stated in the package docstring, and the README's
Python block."""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.timeout(120)

SCRIPT = "import os, ampc_jax; print(os.environ.get('XLA_FLAGS', ''))"


def _run(script: str, **env_extra: str) -> str:
    """stdout of ``script`` in a fresh interpreter without our XLA variables (plus ``env_extra``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "AMPC_KEEP_XLA_FLAGS")}
    env.update(env_extra)
    r = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def _flags(**env_extra: str) -> str:
    return _run(SCRIPT, **env_extra)


def test_flags_appended_once_and_user_flags_kept():
    from importlib.metadata import version

    import ampc_jax

    flags = _flags(XLA_FLAGS="--xla_cpu_multi_thread_eigen=true --xla_dump_to=/tmp/x")
    assert "--xla_dump_to=/tmp/x" in flags
    # a flag the user set is not overridden or repeated
    assert flags.count("xla_cpu_multi_thread_eigen") == 1 and "eigen=true" in flags
    assert "--xla_cpu_enable_concurrency_optimized_scheduler=false" in flags
    ynn = "--xla_cpu_experimental_ynn_fusion_type="
    tested = any(version("jaxlib").startswith(p) for p in ampc_jax.XLA_PERFORMANCE_FLAGS)
    assert (ynn in flags) == tested


def test_opt_out_keeps_xla_flags_untouched():
    assert (
        _flags(AMPC_KEEP_XLA_FLAGS="1", XLA_FLAGS="--xla_dump_to=/tmp/y") == "--xla_dump_to=/tmp/y"
    )


def test_small_while_loop_threshold_flag():
    """The raised threshold is appended, a user's own backend options are kept,
    and it takes effect: a loop over a 16 kB matrix becomes one kernel
    (an ``xla_cpu_small_call``) only with it."""
    from importlib.metadata import version

    import ampc_jax

    if not any(version("jaxlib").startswith(p) for p in ampc_jax.XLA_PERFORMANCE_FLAGS):
        pytest.skip("the flag is only set for the jaxlib versions it was measured with")
    key = "--xla_backend_extra_options"
    assert f"{key}=xla_cpu_small_while_loop_byte_threshold=1000000" in _flags()
    own = f"{key}=xla_cpu_small_while_loop_byte_threshold=0"
    kept = _flags(XLA_FLAGS=own)
    assert own in kept and kept.count(key) == 1
    probe = (
        "import os, ampc_jax, jax, jax.numpy as jnp\n"
        "f = lambda M, v: jax.lax.fori_loop(0, 10, lambda i, x: jnp.tanh(M @ x), v)\n"
        "txt = jax.jit(f).lower(jnp.ones((64, 64)), jnp.ones(64)).compile().as_text()\n"
        "print('xla_cpu_small_call' in txt)\n"
    )
    assert _run(probe) == "True"
    assert _run(probe, AMPC_KEEP_XLA_FLAGS="1") == "False"


def test_the_import_changes_xla_flags_alone_as_the_docstring_states():
    """Importing ampc_jax changes no environment variable but XLA_FLAGS, and appends
    exactly the flags its docstring names (the workaround always, the performance
    flags for the jaxlib versions they were measured with)."""
    from importlib.metadata import version

    import ampc_jax

    probe = (
        "import json, os\n"
        "before = dict(os.environ)\n"
        "import ampc_jax\n"
        "after = dict(os.environ)\n"
        "print(json.dumps(sorted(k for k in set(before) | set(after) "
        "if before.get(k) != after.get(k))))\n"
        "print(after.get('XLA_FLAGS', ''))\n"
    )
    changed, flags = _run(probe).splitlines()
    assert changed == '["XLA_FLAGS"]'
    wanted = list(ampc_jax.XLA_WORKAROUND_FLAGS)
    for prefix, extra in ampc_jax.XLA_PERFORMANCE_FLAGS.items():
        if version("jaxlib").startswith(prefix):
            wanted.extend(extra)
    assert flags.split() == wanted
    doc = " ".join(ampc_jax.__doc__.split())
    every = [*ampc_jax.XLA_WORKAROUND_FLAGS]
    every += [f for extra in ampc_jax.XLA_PERFORMANCE_FLAGS.values() for f in extra]
    for flag in every:
        assert f"``{flag}``" in doc, flag
    assert "AMPC_KEEP_XLA_FLAGS=1" in doc
    assert _run(probe, AMPC_KEEP_XLA_FLAGS="1").splitlines()[0] == "[]"


def _readme_python_block() -> str:
    """The first ```python block of README.md (its Python example)."""
    from pathlib import Path

    text = (Path(__file__).parents[1] / "README.md").read_text()
    fence = "```python\n"
    assert fence in text, "README.md has no ```python block"
    start = text.index(fence) + len(fence)
    end = text.index("\n```", start - 1)
    return text[start : end + 1]


def _line(out: str, prefix: str) -> str:
    lines = [line for line in out.splitlines() if line.startswith(prefix)]
    assert len(lines) == 1, (prefix, out)
    return lines[0]


@pytest.mark.timeout(300)
def test_readme_python_example_runs_and_agrees_with_clarabel():
    """The README's Python block, run as it stands in a fresh interpreter: Local
    Explicit agrees with Clarabel, a vmap over 1000 scenarios and one over a
    grid of rho scales (a SolverParams batch) all solve, and tuning the log rho
    scales through solve_fixed lowers the loss by orders of magnitude."""
    out = _run(_readme_python_block())
    assert _line(out, "groups:") == "groups: [['drive', 'brake'], ['vector', 'brake']]"
    assert _line(out, "status ").startswith("status 0 ")
    err = float(_line(out, "max |u0 - Clarabel|").split()[-1])
    assert err < 1e-5, out
    assert _line(out, "batch u0").endswith("all solved True"), out
    assert " points, all solved True " in _line(out, "sweep "), out
    before, after = (float(v) for v in _line(out, "rho scale").split("loss")[1].split("->"))
    assert after < 1e-3 * before, out
