"""The import layers of docs/ARCHITECTURE.md, checked on the source (no module is imported).

cli -> runs / evaluate / demo / masking / recipes -> train / views -> models -> fields / sampling / render /
coords -> jax; data/ and dpt/ never import the NeRF side; config.py imports nothing of it; no
module but the dispatcher reaches a cli module, and experiments/ and benchmarks/ call the library.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxnerf_grid"
NERF_SIDE = {"models", "fields", "sampling", "render", "coords", "losses", "optim", "checkpoint", "train",
             "views", "runs", "evaluate", "demo", "export", "report", "recipes"}
LIBRARY_TOP = {"runs", "evaluate", "demo", "masking", "recipes"}


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


def test_data_and_dpt_never_import_the_nerf_side():
    for sub in ("data", "dpt"):
        for path in sorted((PACKAGE / sub).rglob("*.py")):
            bad = {m for m in imports_of(path) if top(m) in NERF_SIDE}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_config_and_the_model_layers_stay_below_the_library():
    assert not {top(m) for m in imports_of(PACKAGE / "config.py")} & NERF_SIDE
    for name in ("models", "train", "views", "sampling", "render", "coords"):
        bad = {m for m in imports_of(PACKAGE / f"{name}.py") if top(m) in LIBRARY_TOP | {"cli"}}
        assert not bad, f"{name}.py imports {bad}"


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
