"""The fast tier (`pytest -m "not slow"`, the inner loop) as conftest.py defines it, checked on the
source (nothing is collected or run): every file, fixture and test the slow lists name exists, and
every package module is imported by a test file that keeps at least one fast test, directly or
through the modules it imports (an import inside a slow test's body does not count)."""

import ast
from pathlib import Path

from jaxnerf_grid import cli
from tests import conftest
from tests.test_layers import MODULES, ROOT, import_graph, import_nodes, imported_modules

TESTS = ROOT / "tests"
# modules no fast test imports in-process, and why
NOT_IMPORTED = {
    "jaxnerf_grid.__main__": "`python -m jaxnerf_grid` in a child process (the CLI tests run `cli.main` in-process)",
}


def suite_files(tree: Path = TESTS) -> list[Path]:
    """Every test file under tests/."""
    return sorted(tree.rglob("test_*.py"))


def functions(path: Path) -> dict[str, ast.FunctionDef]:
    """{name: node} of the module-level functions of a file."""
    return {n.name: n for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}


def is_slow(rel: str, fn: ast.FunctionDef) -> bool:
    """conftest's rule on a test function, from the fixtures its signature names."""
    return conftest.slow_reason(rel, fn.name, [a.arg for a in fn.args.args]) is not None


def test_every_name_in_the_slow_lists_exists():
    for rel in conftest.SLOW_FILES | set(conftest.SLOW_FIXTURES):
        assert (TESTS / rel).is_file(), f"conftest names tests/{rel}, which does not exist"
    for rel, fixtures in conftest.SLOW_FIXTURES.items():
        missing = fixtures - set(functions(TESTS / rel))
        assert not missing, f"tests/{rel} has no fixture {sorted(missing)}"
    for name in conftest.SLOW:
        rel, function = name.split("::")
        assert (TESTS / rel).is_file() and function in functions(TESTS / rel), f"conftest names {name}, not a test"
    for rel in conftest.LONGEST_FIRST:
        assert (TESTS / rel).is_file(), f"conftest's LONGEST_FIRST names tests/{rel}, which does not exist"


def source_module(name: str) -> Path | None:
    """The file of a package, experiments or benchmarks module (None for any other)."""
    if name in MODULES:
        return MODULES[name]
    path = ROOT.joinpath(*name.split("."))
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if name.split(".")[0] in ("experiments", "benchmarks") and candidate.is_file():
            return candidate
    return None


def subcommands_run(tree: ast.AST, skipped: set[int]) -> set[str]:
    """The cli modules that `cli.main(["NAME", ...])` calls import (the dispatcher imports a
    subcommand's module by name when it runs)."""
    out = set()
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and id(node) not in skipped and isinstance(node.func, ast.Attribute)
                and node.func.attr == "main" and isinstance(node.func.value, ast.Name) and node.func.value.id == "cli"
                and node.args and isinstance(node.args[0], ast.List) and node.args[0].elts
                and isinstance(node.args[0].elts[0], ast.Constant) and node.args[0].elts[0].value in cli.SUBCOMMANDS):
            out.add(cli.SUBCOMMANDS[node.args[0].elts[0].value][0])
    return out


def imports_in(tree: ast.AST, module: str, skip=()) -> set[str]:
    """The package, experiments and benchmarks modules a parsed file imports, anywhere but inside
    the nodes of `skip`, with the subcommands it runs through `cli.main`."""
    skipped = {id(n) for s in skip for n in ast.walk(s)}
    out = subcommands_run(tree, skipped)
    for node in [*import_nodes(tree, True), *import_nodes(tree, False)]:
        if id(node) in skipped:
            continue
        out |= imported_modules(node, module, False)
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else [
            f"{node.module}.{a.name}" for a in node.names] + [node.module or ""]
        out |= {n for n in names if n.split(".")[0] in ("experiments", "benchmarks") and source_module(n)}
    return out


def reached_by_fast_tests() -> dict[str, str]:
    """{package module: a fast test file that imports it, directly or not}."""
    graph = {m: a | b for (m, a), b in zip(import_graph(True).items(), import_graph(False).values())}
    reached: dict[str, str] = {}
    for path in suite_files():
        rel = path.relative_to(TESTS).as_posix()
        tree = ast.parse(path.read_text())
        tests = [f for f in tree.body if isinstance(f, ast.FunctionDef) and f.name.startswith("test_")]
        slow = [f for f in tests if is_slow(rel, f)]
        if len(slow) == len(tests):
            continue
        todo = list(imports_in(tree, "tests", slow))
        while todo:
            name = todo.pop()
            parts = name.split(".")
            for k in range(1, len(parts) + 1):  # a module's packages are initialised first
                parent = ".".join(parts[:k])
                if parent not in reached and (parent in MODULES or source_module(parent)):
                    reached[parent] = rel
                    file = source_module(parent)
                    todo += graph.get(parent, set()) if parent in MODULES else imports_in(
                        ast.parse(file.read_text()), parent) if file else []
    return {m: f for m, f in reached.items() if m in MODULES}


def test_every_package_module_is_imported_by_a_fast_test():
    reached = reached_by_fast_tests()
    missing = sorted(set(MODULES) - set(reached) - set(NOT_IMPORTED))
    assert not missing, f"package modules no fast test imports: {missing}"


def test_compile_fast_flags_are_added_once_and_a_given_flag_is_kept():
    from tests.conftest import with_compile_fast_flags

    count = "--xla_force_host_platform_device_count=2"
    assert with_compile_fast_flags(count) == (
        f"{count} --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true")
    assert with_compile_fast_flags("") == "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
    given = "--xla_backend_optimization_level=2"
    assert with_compile_fast_flags(given) == f"{given} --xla_llvm_disable_expensive_passes=true"
    once = with_compile_fast_flags(count)
    assert with_compile_fast_flags(once) == once
