"""The ``ampc`` command line: ``solve``, ``simulate``, ``demo``, ``run``, ``plant``,
``export``, ``replay``, ``sweep``, ``tune``.

Errors go to stderr as ``ampc: error: --flag: message`` with exit code 2 (bad
input); library warnings as ``ampc: warning: ...`` lines. Nothing in the
library imports this package.
"""

from __future__ import annotations

import sys

from .. import __version__
from .args import Parser, fail
from .runtime import add_runtime_commands
from .simulate import add_simulate_commands
from .solve import add_solve_command
from .sweep import add_sweep_command
from .tune import add_tune_command

__all__ = ["build_parser", "main"]


def build_parser() -> Parser:
    parser = Parser(
        prog="ampc",
        description="Multi-objective agent-based MPC (consensus ADMM, Local Explicit) in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"ampc-jax {__version__}")
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
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return fail("interrupted", 130)
    except BrokenPipeError:  # output piped into e.g. `head`: not an error of ours
        sys.stdout = None
        return 0
