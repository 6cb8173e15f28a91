"""The import layers of docs/ARCHITECTURE.md as folder rules, checked on the source (no module is imported).

The package's folders are stages; each may import only the units below it in LAYERS (a unit is a
top-level folder, or one of the modules RUN_LEVEL / LEAVES names). No import cycle, package
imports at module level (LAZY_IMPORTS says which are not, and why), masks/dpt/ stands alone,
capture/ and data/ never reach the NeRF side, no module but the dispatcher reaches a cli module,
experiments/ and benchmarks/ call the library, and library strings name keys (`export.box`), not
flags (`--box`): cli/flags.py maps them.
"""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxnerf_grid"
# low to high: a unit imports only units before it
LAYERS = ["util", "catenary", "schema", "nerf", "data", "capture", "masks", "config", "optim", "render", "train",
          "report", "runs", "export", "eval", "demo", "cli", "__main__"]
# modules that are their own unit, and why
LEAVES = {
    "jaxnerf_grid.config.schema": "schema",  # the frozen-dataclass machinery every stage's config uses
    "jaxnerf_grid.train.optim": "optim",  # the optimiser: training, and NeRF-W's test-time appearance fit in render/
    "jaxnerf_grid.export.catenary": "catenary",  # a span's curve: export fits it, report/html.py draws it
}
RUN_LEVEL = {  # modules that load or drive a whole run, above train/, render/ and report/
    "jaxnerf_grid.train.runs": "runs", "jaxnerf_grid.render.videos": "runs",
    "jaxnerf_grid.report.progress_page": "runs",
}
NERF_SIDE = {"nerf", "train", "optim", "render", "runs", "eval", "export", "report", "config", "demo"}
# package imports inside functions, outside cli/ (which imports the library on use so that
# `jaxnerf-grid X --help` and argument errors return before JAX loads): (file, module) -> why
LAZY_IMPORTS = {
    ("data/synthetic/generate.py", "jaxnerf_grid.util.progress"):
        "the generator's source is hashed into the experiments' scene and run keys "
        "(experiments.scenes.generator_digest); it stays as the committed results' runs had it",
    ("data/synthetic/__init__.py", "jaxnerf_grid.data.synthetic.generate"):
        "generate imports this package's tables (CLASSES, PRESETS), so a module-level import is a "
        "cycle; and it loads JAX (about 1 s), which the scene tables and synth's parser do not need",
}
# strings in library modules (docstrings and argparse calls aside) that may name a flag: (file, flag) -> why
FLAG_TEXT_ALLOWED = {
    ("data/synthetic/generate.py", "--overwrite"): "the synth marker file's text, and an error whose source is "
                                                   "hashed into the experiments' keys (generator_digest)",
    ("capture/poses.py", "--overwrite"): "the poses marker file's text, for a person who finds the folder",
    ("demo.py", "--source"): "a report note quoting the command line that made the masks",
    ("masks/write.py", "--depth-weights"): "a note `mask` prints while it runs (not an error)",
    ("eval/evaluate.py", "--full-size"): "the report's resolution line tells a reader how to score at full size",
    ("capture/poses.py", "--keep-all"): "the poses report and summary tell a person how to keep the photos "
                                        "the vetting left out",
}
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def imports_of(path: Path) -> set[str]:
    """Every jaxnerf_grid module a file imports (top level or inside functions), dotted."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("jaxnerf_grid")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxnerf_grid"):
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def top(name: str) -> str:
    """jaxnerf_grid.a.b -> a."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else ""


def package_files():
    return sorted(PACKAGE.rglob("*.py"))


def test_no_library_module_imports_a_cli():
    for path in package_files():
        if PACKAGE / "cli" in path.parents or path.name == "__main__.py":  # the dispatcher and its entry
            continue
        bad = {m for m in imports_of(path) if top(m) == "cli"}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_capture_data_and_masks_never_import_the_nerf_side():
    """The stages before training stand on their own (the synthetic cameras make rays with nerf/rays.py)."""
    for sub in ("capture", "data", "masks"):
        for path in sorted((PACKAGE / sub).rglob("*.py")):
            bad = {m for m in modules_imported(path) if unit(m) in NERF_SIDE and m != "jaxnerf_grid.nerf.rays"
                   and not (sub == "masks" and unit(m) == "config")}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_the_dpt_imports_only_itself_util_and_the_config_schema():
    for path in sorted((PACKAGE / "masks" / "dpt").rglob("*.py")):
        bad = {m for m in modules_imported(path)
               if not m.startswith(("jaxnerf_grid.masks.dpt", "jaxnerf_grid.util", "jaxnerf_grid.config.schema"))}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_util_imports_nothing_of_the_package():
    for path in sorted((PACKAGE / "util").rglob("*.py")):
        bad = {m for m in modules_imported(path) if not m.startswith("jaxnerf_grid.util")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_each_unit_imports_only_the_layers_below_it():
    """LAYERS is the order of the stages: an import that points up the list is a layer broken."""
    graph = unit_graph([import_graph(True), import_graph(False)])
    rank = {name: i for i, name in enumerate(LAYERS)}
    assert set(graph) - {""} <= set(rank), f"units missing from LAYERS: {sorted(set(graph) - set(rank) - {''})}"
    upward = sorted(f"{a} -> {b}" for a, targets in graph.items() if a for b in targets if rank[b] >= rank[a])
    assert not upward, f"imports up the layers: {upward}"


def test_the_package_root_holds_the_entry_points_only():
    """Stage folders, not loose modules: the root keeps the package's init, the dispatcher and the demo."""
    loose = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert loose == ["__init__.py", "__main__.py", "demo.py"], loose


def test_experiments_and_benchmarks_call_the_library_not_a_cli():
    for folder in ("experiments", "benchmarks"):
        for path in sorted((ROOT / folder).glob("*.py")):
            bad = {m for m in imports_of(path) if top(m) == "cli"}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_experiments_and_benchmarks_are_packages_without_path_hacks():
    """Run as `python -m experiments.X` / `python -m benchmarks.X` from the repository root
    (docs/ARCHITECTURE.md): no script edits sys.path to find its neighbours."""
    for folder in ("experiments", "benchmarks"):
        assert (ROOT / folder / "__init__.py").is_file(), f"{folder}/ is not a package"
        for path in sorted((ROOT / folder).glob("*.py")):
            assert "sys.path.insert" not in path.read_text(), f"{path.relative_to(ROOT)} edits sys.path"


# --------------------------------------------------------------------------- the import graph


def module_name(path: Path) -> str:
    """jaxnerf_grid/a/b.py -> jaxnerf_grid.a.b; jaxnerf_grid/a/__init__.py -> jaxnerf_grid.a."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in package_files()}


def imported_modules(node, module: str, is_package: bool) -> set[str]:
    """The package modules one import statement reads: `import a.b` -> a.b; `from a import x`
    -> a.x when x is a submodule, else a (x is one of a's names). A package above an imported
    module is not counted: Python initialises it first, but reading a submodule from inside its
    package's __init__ (which is under way) is no cycle."""
    if isinstance(node, ast.Import):
        names = {a.name for a in node.names}
    else:
        base = node.module or ""
        if node.level:  # relative: from . import x
            here = module.split(".") if is_package else module.split(".")[:-1]
            base = ".".join(here[:len(here) - node.level + 1] + ([base] if base else []))
        names = {f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names}
    return {m for m in names if m in MODULES and m != module}


def import_nodes(tree: ast.AST, module_level: bool):
    """Import statements of a module: those run when it is imported (module_level, i.e. not
    inside a function), or those inside functions (not module_level)."""
    def walk(node, in_function):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, (ast.Import, ast.ImportFrom)) and inside != module_level:
                yield child
            yield from walk(child, inside)
    yield from walk(tree, False)


def import_graph(module_level: bool) -> dict[str, set[str]]:
    """{module: the package modules it imports} over module-level (or function-level) imports."""
    graph = {}
    for name, path in MODULES.items():
        graph[name] = set()
        for node in import_nodes(ast.parse(path.read_text()), module_level):
            graph[name] |= imported_modules(node, name, path.name == "__init__.py")
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph as [a, b, ..., a], or None (depth-first search)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def modules_imported(path: Path) -> set[str]:
    """The package modules a file imports, at any level (a package named only as the source of
    `from package import module` is not counted)."""
    tree = ast.parse(path.read_text())
    return {m for level in (True, False) for node in import_nodes(tree, level)
            for m in imported_modules(node, module_name(path), path.name == "__init__.py")}


def unit(name: str) -> str:
    """The layer unit of a module: its top-level folder, or its own name in LEAVES / RUN_LEVEL."""
    return LEAVES.get(name) or RUN_LEVEL.get(name) or top(name)


def unit_graph(graphs) -> dict[str, set[str]]:
    """The graphs merged onto the layer units, without self-edges."""
    units = {}
    for graph in graphs:
        for a, targets in graph.items():
            units.setdefault(unit(a), set()).update(unit(b) for b in targets if unit(b) != unit(a))
    return units


def test_find_cycle_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycle_among_modules():
    """Module-level imports (what runs at import time) form no cycle."""
    cycle = find_cycle(import_graph(module_level=True))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_import_cycle_among_the_package_units():
    """Counting function-level imports too, no two top-level units (evaluate, export/, data/, ...)
    import each other, even through others."""
    cycle = find_cycle(unit_graph([import_graph(True), import_graph(False)]))
    assert cycle is None, "import cycle between units: " + " -> ".join(cycle)


def test_package_imports_sit_at_module_level():
    """Outside cli/, a package module imported inside a function is in LAZY_IMPORTS with its reason."""
    lazy = set()
    for name, path in MODULES.items():
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("cli/"):
            continue
        for node in import_nodes(ast.parse(path.read_text()), module_level=False):
            for target in imported_modules(node, name, path.name == "__init__.py"):
                lazy.add((rel, target, node.lineno))
    unlisted = sorted(f"{rel}:{line} imports {target}" for rel, target, line in lazy
                      if (rel, target) not in LAZY_IMPORTS)
    assert not unlisted, "package imports inside functions (move them up or list them in LAZY_IMPORTS): " \
        + "; ".join(unlisted)
    stale = set(LAZY_IMPORTS) - {(rel, target) for rel, target, _ in lazy}
    assert not stale, f"LAZY_IMPORTS lists imports that are gone: {sorted(stale)}"


def flag_strings(path: Path) -> list[tuple[int, str]]:
    """(line, flag) of each --flag in a module's string literals, docstrings and argparse's
    add_argument calls left out."""
    tree = ast.parse(path.read_text())
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                skip.add(id(first.value))
        if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
            skip |= {id(n) for n in ast.walk(node)}
    return [(node.lineno, flag) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip
            for flag in FLAG.findall(node.value)]


def test_flag_strings_finds_flags_in_messages_only(tmp_path):
    path = tmp_path / "m.py"
    path.write_text('"""Doc --doc."""\ndef f(p):\n    """--also-doc"""\n    p.add_argument("--arg")\n'
                    '    raise ValueError(f"{p}: pass --overwrite or a-b--c, not --x-y")\n')
    assert flag_strings(path) == [(5, "--overwrite"), (5, "--x-y")]


def test_library_strings_name_keys_not_flags():
    """Library errors name config keys and `<command>.<argument>` keys; the CLI turns them into
    its flags (cli/flags.py). Only FLAG_TEXT_ALLOWED may name a flag."""
    found = set()
    for path in package_files():
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("cli/") or rel == "data/preprocess.py":  # command lines (preprocess: its own)
            continue
        found |= {(rel, flag, line) for line, flag in flag_strings(path)}
    bad = sorted(f"{rel}:{line} {flag}" for rel, flag, line in found if (rel, flag) not in FLAG_TEXT_ALLOWED)
    assert not bad, f"library strings naming flags (name the key instead): {bad}"
    stale = set(FLAG_TEXT_ALLOWED) - {(rel, flag) for rel, flag, _ in found}
    assert not stale, f"FLAG_TEXT_ALLOWED lists strings that are gone: {sorted(stale)}"
