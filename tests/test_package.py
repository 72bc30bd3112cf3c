"""Import-time XLA flags of ampc_jax (README, "Known issues" and "Speed")."""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.timeout(120)

SCRIPT = "import os, ampc_jax; print(os.environ.get('XLA_FLAGS', ''))"


def _flags(**env_extra: str) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "AMPC_KEEP_XLA_FLAGS")}
    env.update(env_extra)
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


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
