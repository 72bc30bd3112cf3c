"""Where ``ampc`` keeps its compilation cache (``ampc_jax.cli.cache_dir``); that the
cache is used by default is shown end to end by ``tests/test_bench.py::test_bench_compile``
(two fresh processes, every program of the second loaded from the cache)."""

from pathlib import Path

import pytest

from ampc_jax.cli import CACHE_ENV, build_parser, cache_dir

pytestmark = pytest.mark.timeout(60)


def test_default_is_the_users_cache_directory():
    assert cache_dir(env={"XDG_CACHE_HOME": "/x/cache"}) == Path("/x/cache/ampc-jax/xla")
    home = cache_dir(env={})
    assert home == Path("~/.cache/ampc-jax/xla").expanduser()


def test_environment_and_flag_override_it_and_off_disables_it():
    env = {CACHE_ENV: "/tmp/somewhere", "XDG_CACHE_HOME": "/x/cache"}
    assert cache_dir(env=env) == Path("/tmp/somewhere")
    assert cache_dir("/flag/dir", env=env) == Path("/flag/dir")  # the flag wins
    for off in ("off", "OFF", "0", "none"):
        assert cache_dir(env={CACHE_ENV: off}) is None
        assert cache_dir(off, env={}) is None
    assert cache_dir(env={CACHE_ENV: ""}) == Path("~/.cache/ampc-jax/xla").expanduser()


def test_flags_parse_before_the_command():
    args = build_parser().parse_args(["--no-compilation-cache", "solve", "cruise_control"])
    assert args.no_compilation_cache and args.compilation_cache is None
    args = build_parser().parse_args(["--compilation-cache", "d", "solve", "cruise_control"])
    assert args.compilation_cache == "d" and not args.no_compilation_cache
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--compilation-cache", "d", "--no-compilation-cache", "solve"])
