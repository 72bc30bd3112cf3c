"""A compilation cache others can write is not used (``ampc_jax.cli.cache``): the
directory owned by this user and writable by no one else, every directory
above it (as given and as resolved) owned by this user or root and writable by
no one else unless sticky. Refused: world- and group-writable, another user's,
a symlink to such a directory, a parent others can write; ``ampc`` then says
one warning line and compiles afresh, writing nothing there (end to end in a
fresh process, ``JAX_COMPILATION_CACHE_DIR`` included)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ampc_jax.cli.cache import cache_problem
from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]


def _dir(base: Path, name: str, mode: int = 0o700) -> Path:
    d = base / name
    d.mkdir()
    d.chmod(mode)
    return d


def test_a_private_directory_is_trusted(tmp_path: Path) -> None:
    # tmp_path lies under /tmp: world-writable and sticky, owned by root
    assert cache_problem(_dir(tmp_path, "cache")) is None
    assert cache_problem(_dir(tmp_path, "readable", 0o755)) is None


@pytest.mark.parametrize(("mode", "words"), [(0o777, "writable by others"),
                                             (0o770, "writable by others"),
                                             (0o722, "writable by others"),
                                             (0o1777, "writable by others")])  # fmt: skip
def test_a_directory_others_can_write_is_refused(tmp_path: Path, mode: int, words: str) -> None:
    d = _dir(tmp_path, "cache", mode)
    problem = cache_problem(d)
    assert problem is not None and words in problem and str(d) in problem, problem
    assert f"{mode & 0o7777:04o}" in problem


def _other_owner(path: Path, monkeypatch) -> None:
    """``path`` owned by uid 4242: chown under root, else its stat result faked."""
    if os.geteuid() == 0:
        os.chown(path, 4242, 4242)
        return
    import ampc_jax.cli.cache as cache

    real_stat = os.stat

    def fake(p, *a, **k):
        st = real_stat(p, *a, **k)
        if Path(p) == path:
            return os.stat_result((st.st_mode, st.st_ino, st.st_dev, st.st_nlink, 4242, 4242,
                                   st.st_size, st.st_atime, st.st_mtime, st.st_ctime))  # fmt: skip
        return st

    monkeypatch.setattr(cache.os, "stat", fake)


def test_a_directory_of_another_user_is_refused(tmp_path: Path, monkeypatch) -> None:
    d = _dir(tmp_path, "cache")
    _other_owner(d, monkeypatch)
    problem = cache_problem(d)
    assert problem is not None and "owned by another user" in problem and "4242" in problem


def test_a_parent_of_another_user_is_refused(tmp_path: Path, monkeypatch) -> None:
    parent = _dir(tmp_path, "theirs", 0o755)
    d = _dir(parent, "cache")
    _other_owner(parent, monkeypatch)
    problem = cache_problem(d)
    assert problem is not None and str(parent) in problem and "another user" in problem


def test_a_symlink_to_a_directory_others_can_write_is_refused(tmp_path: Path) -> None:
    target = _dir(tmp_path, "open", 0o777)
    link = tmp_path / "cache"
    link.symlink_to(target)
    problem = cache_problem(link)
    assert problem is not None and str(target) in problem and "writable by others" in problem


def test_a_symlink_inside_a_directory_others_can_write_is_refused(tmp_path: Path) -> None:
    """The link's own directory: whoever writes it can swap the link."""
    mine = _dir(tmp_path, "mine")
    shared = _dir(tmp_path, "shared", 0o777)
    (shared / "cache").symlink_to(mine)
    problem = cache_problem(shared / "cache")
    assert problem is not None and str(shared) in problem, problem


@pytest.mark.parametrize("mode", [0o777, 0o775])
def test_a_parent_others_can_write_is_refused(tmp_path: Path, mode: int) -> None:
    parent = _dir(tmp_path, "open", mode)
    d = _dir(parent, "cache")
    problem = cache_problem(d)
    assert problem is not None and str(parent) in problem and "above the cache" in problem


# -- end to end: a fresh process, as `ampc` starts ---------------------------------

_SCRIPT = """
import sys
from ampc_jax.cli import _use_compilation_cache, build_parser
args = build_parser().parse_args(sys.argv[1:] + ["solve", "cruise_control"])
_use_compilation_cache(args)
import jax
print(float(jax.jit(lambda x: 2.0 * x + 1.0)(3.0)))
"""


def _ampc_cache(flags: list[str], env: dict[str, str] | None = None):
    e = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    e.pop("AMPC_COMPILATION_CACHE", None)
    if env is None:
        e.pop("JAX_COMPILATION_CACHE_DIR", None)
    return subprocess.run([sys.executable, "-c", _SCRIPT, *flags], capture_output=True,
                          text=True, timeout=budget(100), env=e, cwd=ROOT)  # fmt: skip


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("ampc: warning: ")]


def test_ampc_writes_a_private_cache(tmp_path: Path) -> None:
    d = _dir(tmp_path, "cache")
    p = _ampc_cache(["--compilation-cache", str(d)])
    assert p.returncode == 0 and p.stdout.strip() == "7.0", p.stderr
    assert not _warnings(p.stderr) and any(d.iterdir())  # the program was cached


@pytest.mark.parametrize("how", ["flag", "JAX_COMPILATION_CACHE_DIR"])
def test_ampc_neither_writes_nor_loads_a_cache_others_can_write(tmp_path: Path, how: str) -> None:
    d = _dir(tmp_path, "cache", 0o777)
    if how == "flag":
        p = _ampc_cache(["--compilation-cache", str(d)])
    else:
        p = _ampc_cache([], env={"JAX_COMPILATION_CACHE_DIR": str(d)})
    assert p.returncode == 0 and p.stdout.strip() == "7.0", p.stderr
    lines = _warnings(p.stderr)
    assert len(lines) == 1, p.stderr
    assert "compilation cache off" in lines[0] and str(d) in lines[0], lines[0]
    assert "writable by others" in lines[0]
    assert not any(d.iterdir())  # nothing written there
