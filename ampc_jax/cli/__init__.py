"""The ``ampc`` command line: ``solve``, ``simulate``, ``demo``, ``run``, ``plant``,
``export``, ``replay``, ``sweep``, ``sweep-merge``, ``tune``.

Errors go to stderr as ``ampc: error: --flag: message`` with exit code 2 (bad
input); library warnings as ``ampc: warning: ...`` lines. Nothing in the
library imports this package. A command refuses a non-empty ``--out`` unless
``--force``, and a failed one removes what it created and left empty
(:mod:`~ampc_jax.cli.outdir`).

Every command keeps JAX's persistent compilation cache in the user's cache
directory (:func:`cache_dir`): a command's second run loads its compiled
programs instead of compiling them (``bench/bench_compile.py`` measures both).
``--compilation-cache DIR`` or ``AMPC_COMPILATION_CACHE=DIR`` moves it,
``--no-compilation-cache`` or ``AMPC_COMPILATION_CACHE=off`` turns it off, and a
cache JAX was already given (``JAX_COMPILATION_CACHE_DIR``) is left as it is.
Whichever it is, a directory others can write is not used (one warning line;
:mod:`~ampc_jax.cli.cache`): a compiled program loaded from it may run code.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .. import __version__
from . import outdir
from .args import Parser, fail
from .runtime import add_runtime_commands
from .simulate import add_simulate_commands
from .solve import add_solve_command
from .sweep import add_sweep_command
from .tune import add_tune_command

__all__ = ["CACHE_ENV", "build_parser", "cache_dir", "main"]

CACHE_ENV = "AMPC_COMPILATION_CACHE"
"""Environment variable: the compilation cache's directory, or ``off``."""

CACHE_OFF = ("off", "0", "none", "false", "no")

CACHE_MIN_COMPILE_S = 0.0
"""Programs that compiled faster than this are not cached. Rule: cache every
program; reason: a command's programs are few and small (a cached one loads in
milliseconds), and the small ones add up (``ampc solve`` compiles 29 programs,
24 of them under 0.1 s each; ``bench/bench_compile.py``)."""


def cache_dir(flag: str | None = None, env: dict[str, str] | None = None) -> Path | None:
    """Where ``ampc`` keeps compiled programs: ``flag`` (``--compilation-cache``),
    else ``$AMPC_COMPILATION_CACHE``, else ``$XDG_CACHE_HOME/ampc-jax/xla``
    (``~/.cache/ampc-jax/xla``); None when turned off (``off``)."""
    env = os.environ if env is None else env
    value = flag if flag is not None else env.get(CACHE_ENV)
    if value is not None and value.strip().lower() in CACHE_OFF:
        return None
    if value:
        return Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME") or str(Path("~/.cache").expanduser())
    return Path(base) / "ampc-jax" / "xla"


def _use_compilation_cache(args: object) -> None:
    """Point JAX's persistent compilation cache at :func:`cache_dir` (before the first
    compilation). A directory that cannot be created turns the cache off with a
    warning line; a cache set through JAX's own ``JAX_COMPILATION_CACHE_DIR`` wins
    unless the flag names one."""
    from .cache import cache_problem

    flag = getattr(args, "compilation_cache", None)
    if getattr(args, "no_compilation_cache", False):
        flag = "off"
    import jax

    jax_dir = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if flag is None and jax_dir:
        problem = cache_problem(jax_dir) if os.path.isdir(jax_dir) else None
        if problem:  # JAX's own setting, checked by the same rule
            _cache_off(f"JAX_COMPILATION_CACHE_DIR: {problem}")
        return
    path = cache_dir(flag)
    if path is None:
        jax.config.update("jax_enable_compilation_cache", False)
        return
    try:
        path.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as exc:
        print(f"ampc: warning: compilation cache off: {path}: {exc.strerror}", file=sys.stderr)
        jax.config.update("jax_enable_compilation_cache", False)
        return
    problem = cache_problem(path)
    if problem:
        _cache_off(problem)
        return
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)


def _cache_off(problem: str) -> None:
    import jax

    print(
        f"ampc: warning: compilation cache off: {problem}; a compiled program loaded from "
        "it could run code someone else put there (chmod go-w, or another directory)",
        file=sys.stderr,
    )
    jax.config.update("jax_enable_compilation_cache", False)


def build_parser() -> Parser:
    parser = Parser(
        prog="ampc",
        description="Multi-objective agent-based MPC (consensus ADMM, Local Explicit) in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"ampc-jax {__version__}")
    cache = parser.add_mutually_exclusive_group()
    cache.add_argument(
        "--compilation-cache",
        metavar="DIR",
        help=f"keep compiled programs in DIR (default: ${CACHE_ENV}, else "
        "$XDG_CACHE_HOME/ampc-jax/xla or ~/.cache/ampc-jax/xla)",
    )
    cache.add_argument(
        "--no-compilation-cache",
        action="store_true",
        help=f"compile every program afresh, as {CACHE_ENV}=off does (default: the cache on)",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_solve_command(sub)
    add_simulate_commands(sub)
    add_runtime_commands(sub)
    add_sweep_command(sub)
    add_tune_command(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``ampc`` with ``argv`` (default: the process's); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _use_compilation_cache(args)
    outdir.begin()
    code = 1  # an exception: what the command created and left empty is removed
    try:
        code = int(args.func(args))
    except KeyboardInterrupt:
        code = fail("interrupted", 130)
    except BrokenPipeError:  # output piped into e.g. `head`: not an error of ours
        sys.stdout = None
        code = 0
    finally:
        outdir.finish(code)
    return code
