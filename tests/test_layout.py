"""The package layout: one concept per module, no import circle (module-level or
inside functions), the CLI and the testing helpers imported by no library module, no
private name imported across modules, no formulation named outside the registry's
package, no attribute forwarding by ``__getattr__``, no status as a number."""

import ast
import pathlib

import pytest

pytestmark = pytest.mark.timeout(60)

PKG = pathlib.Path(__file__).resolve().parents[1] / "ampc_jax"


def _module(path: pathlib.Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: pathlib.Path) -> list[tuple[str, list[str], bool]]:
    """(module imported, names, at module level) for every import of the package's own modules."""
    mod = _module(path)
    is_pkg = path.name == "__init__.py"
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("ampc_jax"):
                out.append((target, [a.name for a in node.names], id(node) in top))
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("ampc_jax"):
                    out.append((a.name, [], id(node) in top))
    return out


FILES = sorted(PKG.rglob("*.py"))
MODULES = {_module(p): p for p in FILES}


def _resolve(target: str) -> str:
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target


def _graph(module_level_only: bool) -> dict[str, set[str]]:
    """module -> the package's modules it imports (at module level only, or also
    inside functions and ``if TYPE_CHECKING:`` blocks)."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for m, p in MODULES.items():
        for target, names, top in _imports(p):
            if module_level_only and not top:
                continue
            t = _resolve(target)
            # "from pkg import name" where name is a submodule imports that submodule
            for n in names:
                if f"{t}.{n}" in MODULES:
                    graph[m].add(f"{t}.{n}")
            if t and t != m:
                graph[m].add(t)
    return graph


def _assert_no_circle(graph: dict[str, set[str]]) -> None:
    # a package's __init__ re-exporting its own submodules is not a circle
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in graph[m]:
            if m.startswith(t + ".") and MODULES[t].name == "__init__.py":
                continue  # a module importing its own package's __init__ (ancestor)
            if state.get(t) == 1:
                cycle = stack[stack.index(t) :] + [t]
                if not all(MODULES[x].name == "__init__.py" or x == t for x in cycle[:-1]):
                    raise AssertionError(f"import circle: {' -> '.join(cycle)}")
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_no_import_circle_among_module_level_imports():
    _assert_no_circle(_graph(module_level_only=True))


def test_no_import_circle_hidden_in_function_local_imports():
    """An import inside a function (or for type checking only) is a dependency
    too: with them the graph has no circle either (closed_loop/config.py once
    built the controller and simulator that import it)."""
    _assert_no_circle(_graph(module_level_only=False))


def test_the_circle_check_sees_function_local_imports():
    """The walk finds an import inside a function, so the check above can fail."""
    cfg = MODULES["ampc_jax.closed_loop.config"]
    assert ("ampc_jax.closed_loop.controller", ["Controller"], False) not in _imports(cfg)
    local = [(t, top) for t, _, top in _imports(MODULES["ampc_jax.tuning.solver"])]
    assert ("ampc_jax.sweep.engine", False) in local
    graph = _graph(module_level_only=False)
    graph["ampc_jax.closed_loop.config"].add("ampc_jax.closed_loop.loop")
    with pytest.raises(AssertionError, match="import circle: .*closed_loop"):
        _assert_no_circle(graph)


def test_library_never_imports_the_cli():
    for m, p in MODULES.items():
        if m.startswith("ampc_jax.cli"):
            continue
        for target, _, _ in _imports(p):
            assert not _resolve(target).startswith("ampc_jax.cli"), f"{m} imports {target}"


def test_no_private_name_imported_across_modules():
    """A name starting with an underscore stays in its module (tests may reach in)."""
    for m, p in MODULES.items():
        for target, names, _ in _imports(p):
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            assert not private, f"{m} imports {private} from {target}"


def test_one_concept_per_module_stays_small():
    """No module of more than about 700 lines (the flat modules were up to 1,400)."""
    big = {m: n for m, p in MODULES.items() if (n := len(p.read_text().splitlines())) > 700}
    assert not big, big


def _formulation_name_uses(tree: ast.AST, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) where a formulation's name is compared, listed (two or more
    names in one tuple, list or set) or a dict key: a branch or a list kept
    outside the registry."""

    def strings(node: ast.AST) -> list[str]:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [node.value]
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return [s for e in node.elts for s in strings(e)]
        return []

    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            found = [s for e in (node.left, *node.comparators) for s in strings(e) if s in names]
        elif isinstance(node, ast.Dict):
            found = [s for k in node.keys if k is not None for s in strings(k) if s in names]
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            listed = [s for s in strings(node) if s in names]
            found = listed if len(listed) > 1 else []
        elif isinstance(node, ast.match_case):
            found = [s for s in strings(getattr(node.pattern, "value", None)) if s in names]
        else:
            found = []
        out.extend((node.lineno if hasattr(node, "lineno") else 0, s) for s in found)
    return out


def test_no_module_outside_formulations_branches_on_a_formulation_name():
    """What a formulation is comes from its declared info, through the registry
    (``formulation_info``, ``formulation_names``): no module outside
    ``formulations/`` compares a formulation's name or keeps a list of them."""
    from ampc_jax.formulations import FORMULATIONS

    names = set(FORMULATIONS)
    bad = [
        f"{m}:{line} {name!r}"
        for m, p in MODULES.items()
        if not m.startswith("ampc_jax.formulations")
        for line, name in _formulation_name_uses(ast.parse(p.read_text()), names)
    ]
    assert not bad, bad


def test_the_formulation_name_check_finds_branches_and_lists():
    src = (
        "if args.formulation == 'integrated': pass\n"
        "BATCH = {'local_explicit': 'riccati'}\n"
        "CONSENSUS = ('fully_distributed', 'virtual_center')\n"
        "ok = formulation('local_explicit', T)\n"
    )
    found = _formulation_name_uses(
        ast.parse(src), {"integrated", "local_explicit", "fully_distributed", "virtual_center"}
    )
    assert sorted(found) == [
        (1, "integrated"),
        (2, "local_explicit"),
        (3, "fully_distributed"),
        (3, "virtual_center"),
    ]


def test_no_class_forwards_attributes_with_getattr():
    """A wrapper (a solver around a formulation, ``LearnedStart``) declares what it
    offers: no class defines ``__getattr__`` or ``__getattribute__`` to forward
    any attribute to what it wraps (what the wrapper needs goes into the core
    protocol, ``ADMMSolver``)."""
    bad = [
        f"{m}:{node.lineno} {node.name}.{f.name}"
        for m, p in MODULES.items()
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.ClassDef)
        for f in node.body
        if isinstance(f, ast.FunctionDef) and f.name in ("__getattr__", "__getattribute__")
    ]
    assert not bad, bad


def test_no_library_module_imports_the_testing_helpers():
    """``ampc_jax.testing`` (the peers the tests and benchmarks share) is imported
    by tests and benchmarks only."""
    for m, p in MODULES.items():
        if m.startswith("ampc_jax.testing"):
            continue
        for target, _, _ in _imports(p):
            assert not _resolve(target).startswith("ampc_jax.testing"), f"{m} imports {target}"


ROOT = PKG.parent


def _mentions_status(node: ast.AST) -> bool:
    """``status``, ``x.status``, ``x["status"]``, ``int(x.status)``, ``np.asarray(x.status)``."""
    if isinstance(node, ast.Name):
        return "status" in node.id.lower() and node.id != "Status"
    if isinstance(node, ast.Attribute):
        return "status" in node.attr.lower() or _mentions_status(node.value)
    if isinstance(node, ast.Subscript):
        key = node.slice
        named = (
            isinstance(key, ast.Constant) and isinstance(key.value, str) and "status" in key.value
        )
        return named or _mentions_status(node.value)
    if isinstance(node, ast.Call):
        return any(_mentions_status(a) for a in node.args)
    return False


def _int_literal(node: ast.AST) -> bool:
    """An integer literal, bare or wrapped (``np.int32(4)``)."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, int) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _int_literal(node.operand)
    if isinstance(node, ast.Call) and len(node.args) == 1 and not node.keywords:
        return _int_literal(node.args[0])
    return False


def _literal_status_codes(tree: ast.AST) -> list[int]:
    """Lines where a status is compared with, or set to, a number instead of a
    ``Status`` member."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(_mentions_status(s) for s in sides) and any(_int_literal(s) for s in sides):
                out.append(node.lineno)
        elif isinstance(node, ast.keyword) and node.arg and "status" in node.arg:
            if _int_literal(node.value):
                out.append(node.value.lineno)
    return sorted(out)


# the runtime's own numbers (a failed tick's status, the tick journal's "no step"
# mark) become Status members and a named constant with the runtime's next change
_STATUS_PENDING: set[str] = set()


def test_no_literal_status_codes():
    """A status is a ``results.Status`` member everywhere, in the package, its tests
    and its benchmarks: never ``status == 0`` or ``status=np.int32(4)``."""
    files = sorted(PKG.rglob("*.py")) + sorted((ROOT / "tests").rglob("*.py"))
    files += sorted((ROOT / "bench").rglob("*.py"))
    bad = [
        f"{rel}:{line}"
        for f in files
        if (rel := str(f.relative_to(ROOT))) not in _STATUS_PENDING
        for line in _literal_status_codes(ast.parse(f.read_text()))
    ]
    assert not bad, bad


def test_the_status_check_finds_literals():
    src = (
        "assert int(res.status) == 2\n"
        "ok = np.all(np.asarray(out.status) == 0)\n"
        "conv = out['status'] == 0\n"
        "r = report._replace(status=np.int32(4))\n"
        "fine = res.status == Status.SOLVED\n"
        "also = res.iterations == 3\n"
    )
    assert _literal_status_codes(ast.parse(src)) == [1, 2, 3, 4]
