"""The user documentation, checked on its text (nothing is run): every repo path it cites exists,
no absolute path of a machine is committed, and the README's commands are the ones CI runs.

The docs are README.md, experiments/README.md and docs/*.md. A repo path is a markdown link's
target, or a word in backticks that contains "/" and starts at a tracked top-level entry
(`docs/GRID.md`), at a folder beside the doc (`results/...` in experiments/README.md) or, for a
module (`.py` or a trailing "/"), at a package folder (`dpt/reassemble.py`). Words with
placeholders (`<setting>`, `{json,md}`, `*`, `...`) and git-ignored caches are not paths.
"""

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOP_LEVEL = ("jaxnerf_grid", "docs", "experiments", "benchmarks", "tests", "scripts", ".ci",
             "README.md", "pyproject.toml")
PLACEHOLDER = re.compile(r"[<>{}*$|]|\.\.\.")
IGNORED_PARTS = {".cache", ".venv", "__pycache__"}


def doc_files() -> list[Path]:
    """The user documentation: README.md, experiments/README.md, docs/*.md."""
    return [ROOT / "README.md", ROOT / "experiments" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def link_targets(text: str) -> list[str]:
    """Markdown link targets `[..](target)` that point into the repo (no URL, no bare anchor),
    anchors stripped."""
    out = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        out.append(target.split("#")[0])
    return out


def backtick_words(text: str) -> list[str]:
    """The whitespace-separated words inside `...` spans (code fences excluded), outer
    punctuation stripped."""
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)
    words = []
    for span in re.findall(r"`([^`\n]+)`", text):
        words += [w.strip("()[],;:'\"") for w in span.split()]
    return [w for w in words if w]


def repo_path_base(word: str, doc_dir: Path) -> Path | None:
    """The folder `word` is relative to if it looks like a repo path, else None."""
    if "/" not in word or word.startswith("/") or "://" in word or PLACEHOLDER.search(word):
        return None
    parts = word.rstrip("/").split("/")
    if IGNORED_PARTS & set(parts):
        return None
    first = parts[0]
    if first in TOP_LEVEL:
        return ROOT
    if doc_dir != ROOT and (doc_dir / first).exists():
        return doc_dir
    if word.endswith((".py", "/")) and (ROOT / "jaxnerf_grid" / first).exists():
        return ROOT / "jaxnerf_grid"
    return None


def missing_paths(doc: Path) -> list[str]:
    """The repo paths `doc` cites that do not exist, as 'doc: path' strings."""
    text = doc.read_text()
    missing = [t for t in link_targets(text) if t and not (doc.parent / t).exists()]
    for word in backtick_words(text):
        word = word.split("::")[0]  # a pytest node id: its file
        base = repo_path_base(word, doc.parent)
        if base is not None and not (base / word).exists():
            missing.append(word)
    return [f"{doc.relative_to(ROOT)}: {m}" for m in missing]


def test_every_cited_repo_path_exists():
    missing = [m for doc in doc_files() for m in missing_paths(doc)]
    assert not missing, "cited paths that do not exist:\n" + "\n".join(missing)


def test_the_checker_sees_paths_of_each_kind():
    """The rules above on a made-up doc: each kind of path is found, placeholders are not."""
    doc = ROOT / "docs" / "x.md"
    text = ("[a](../README.md) [b](GRID.md#grid) [c](https://x.org/y) `docs/GRID.md` "
            "`masks/dpt/reassemble.py` `docs/NOPE.md` `experiments/results/<setting>/t.md` "
            "`runs/demo/run/report.md` `experiments/.cache/x/y` [d](nope/x.md)")
    assert link_targets(text) == ["../README.md", "GRID.md", "nope/x.md"]
    bases = {w: repo_path_base(w, doc.parent) for w in backtick_words(text)}
    assert bases == {"docs/GRID.md": ROOT, "masks/dpt/reassemble.py": ROOT / "jaxnerf_grid",
                     "docs/NOPE.md": ROOT, "experiments/results/<setting>/t.md": None,
                     "runs/demo/run/report.md": None, "experiments/.cache/x/y": None}


def test_no_absolute_path_of_a_machine():
    """No home, root or work folder of the machine that wrote a doc."""
    hits = [f"{doc.relative_to(ROOT)}: {m.group()}" for doc in doc_files()
            for m in re.finditer(r"(?<![\w.])/(?:home|root|work|Users)/\S*", doc.read_text())]
    assert not hits, hits


def test_readme_test_command_is_what_ci_runs():
    """README command 2 is .ci/run's setup, environment and pytest line, joined as one line."""
    ci = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()]
    setup = next(ln for ln in ci if ln.startswith("bash scripts/setup.sh"))
    env = " ".join(ln.removeprefix("export ") for ln in ci if ln.startswith("export "))
    pytest = next(ln for ln in ci if " -m pytest " in ln)
    readme = (ROOT / "README.md").read_text().split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert readme[0] == "bash scripts/setup.sh && .venv/bin/jaxnerf-grid demo"
    assert readme[1] == f"{setup} && {env} {pytest}"


def cited_rows(doc: Path) -> list[tuple[list[str], Path]]:
    """The table rows of `doc` whose last cell cites a results file in backticks: (cells, file),
    the file resolved as test_every_cited_repo_path_exists does."""
    rows = []
    for line in doc.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        last = re.fullmatch(r"`([\w./-]+\.(?:md|json))`", cells[-1]) if line.startswith("|") else None
        if last:
            rows.append((cells, repo_path_base(last.group(1), doc.parent) / last.group(1)))
    return rows


def test_readme_results_are_copied_from_the_files_they_cite():
    """Every 'mean ± std' effect in the README's and experiments/README.md's results tables is
    printed in the results file the row cites (the generated tables write '+a ± b' or '+a +- b')."""
    rows = cited_rows(ROOT / "README.md") + cited_rows(ROOT / "experiments" / "README.md")
    assert len(rows) >= 12
    for cells, path in rows:
        text = path.read_text()
        for figure in re.findall(r"[-+]\d+\.\d+ ± \d+\.\d+", " | ".join(cells[1:-1])):
            assert figure in text or figure.replace("±", "+-") in text, (figure, path.name)


def demo_row_figures(row: dict) -> list[str]:
    """The demo's figures as the README's results table prints them, from a demo_recipe.json row."""
    f, regions = row["fscore"], row["regions"]
    return [f"test PSNR {row['psnr']:.2f} dB", f"SSIM {row['ssim']:.3f}", f"tower {regions['tower']:.2f} dB",
            f"near ground {regions['near_ground']:.2f} dB", f"far background {regions['far_background']:.2f} dB",
            f"tower F-score {f['0.01']:.3f} / {f['0.02']:.3f} / {f['0.05']:.3f} at 0.01 / 0.02 / 0.05 units",
            f"Chamfer {row['chamfer']:.4f} units"]


def test_readme_demo_row_is_the_demo_results_file():
    """The README's demo row, rounded as printed, from experiments/results/demo/demo_recipe.json:
    the one results-table row that cites that file holds every figure."""
    row = json.loads((ROOT / "experiments/results/demo/demo_recipe.json").read_text())["rows"][0]
    demo_rows = [" | ".join(cells) for cells, path in cited_rows(ROOT / "README.md")
                 if path == ROOT / "experiments/results/demo/demo_recipe.json"]
    assert len(demo_rows) == 1
    missing = [fig for fig in demo_row_figures(row) if fig not in demo_rows[0]]
    assert not missing, missing
