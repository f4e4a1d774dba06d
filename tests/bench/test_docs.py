"""The README and docs say what is true of the tree: the two fresh-machine commands (and CI runs the second), links
and named files that exist, config keys the default config has, and a Status table that is figures.py's."""
from __future__ import annotations

import re
import sys
from itertools import product
from pathlib import Path

import pytest
from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import figures  # noqa: E402

README = ROOT / "README.md"
DOCS = [README, ROOT / "bench" / "README.md", ROOT / "bench" / "RESULTS.md", *sorted((ROOT / "docs").glob("*.md"))]
INSTALL_RUN = 'pip install torch==2.13.0 -e . && pvslam run'
INSTALL_TEST = 'pip install torch==2.13.0 -e ".[test]" -e examples/pvslam-npz && python -m pytest -q -n 2'


def _expand(pattern: str) -> list[str]:
    """``a/{b,c}_*.toml`` -> ``["a/b_*.toml", "a/c_*.toml"]`` (shell brace expansion, one level)."""
    parts = re.split(r"\{([^{}]*)\}", pattern)
    choices = [[p] if k % 2 == 0 else p.split(",") for k, p in enumerate(parts)]
    return ["".join(c) for c in product(*choices)]


def test_the_two_fresh_machine_commands_and_ci():
    text = README.read_text()
    assert f"\n    {INSTALL_RUN}\n" in text and f"\n    {INSTALL_TEST}\n" in text
    ci = (ROOT / ".ci" / "run").read_text()
    assert INSTALL_TEST in ci


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(doc):
    if not doc.is_file():
        pytest.skip(f"{doc.name} not written yet")
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
        if re.match(r"[a-z]+://", target) or target.startswith("#"):
            continue
        if not (doc.parent / target.split("#")[0]).exists():
            bad.append(target)
    assert not bad, f"{doc.name} links to missing files: {bad}"


# the changelog names things that are gone on purpose
@pytest.mark.parametrize("doc", [d for d in DOCS if d.name != "changelog.md"],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_named_files_exist(doc):
    """Every repository path a doc names in backticks (`configs/x.toml`, `bench/y.py`, ...) exists (globs match)."""
    if not doc.is_file():
        pytest.skip(f"{doc.name} not written yet")
    missing = []
    roots = ("configs/", "bench/", "docs/", "tests/", "examples/", "pvslam_core/", "plugins/", ".ci/")
    for token in re.findall(r"`([^`\s]+)`", doc.read_text()):
        path = token.split("#")[0].rstrip(".,;:")
        if not path.startswith(roots) or "<" in path or path.startswith("bench/results_"):
            continue
        if not any(list(ROOT.glob(p)) for p in _expand(path)):
            missing.append(path)
    assert not missing, f"{doc.name} names files that do not exist: {missing}"


def _keys(text: str) -> set[str]:
    """Dotted config keys the text names in backticks, with or without a value (`frontend.road.enabled=false`)."""
    sections = "graph|frontend|optimizer|loop_closure|outputs|run|dataset|segmenter|vps|evaluation"
    found = re.finditer(rf"`(?:--set )?((?:{sections})\.[a-z_.]*[a-z_])(?:\s*=[^`]*)?`", text)
    return {m.group(1) for m in found if not m.group(1).endswith(".py")}  # `frontend.py` is a file


def _plugin_keys(interface: str) -> set[str]:
    """Dotted keys (below the component's table) of every registered plugin of ``interface``."""
    from pvslam_core.registry import get_registry

    reg, out = get_registry(), set()
    for name in reg.names(interface):
        stack = [("", reg.get(interface, name).config_model)]  # fields, not values: some have no defaults
        while stack:
            prefix, model = stack.pop()
            for k, field in model.model_fields.items():
                out.add(prefix + k)
                if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
                    stack.append((prefix + k + ".", field.annotation))
    return out


def test_config_keys_in_the_readme_exist():
    """Every config key the README names exists: in the default config, or (a component's key) in one of the
    registered plugins of that component, e.g. the image-folder reader's ``dataset.follow``."""
    from pvslam_core.config import COMPONENTS, load_config

    cfg = load_config(None).to_dict()
    missing = []
    for key in sorted(_keys(README.read_text())):
        table, _, rest = key.partition(".")
        if table in COMPONENTS and rest and rest in _plugin_keys(table):
            continue
        node = cfg
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                missing.append(key)
                break
            node = node[part]
    assert not missing, f"README.md names config keys no config has: {missing}"


def test_the_readme_status_is_the_figures_table():
    text = README.read_text()
    assert text.count(figures.BEGIN) == 1 and text.count(figures.END) == 1
    table = text.split(figures.BEGIN)[1].split(figures.END)[0].strip().splitlines()
    assert len(table) == 2 + len(figures.FIGURES) <= 2 + 15
    assert table[0] == figures.status_table([])[0]
    for line, fig in zip(table[2:], figures.FIGURES):
        assert line.startswith(f"| {fig.what} | {fig.data} |")
        assert f"`{figures.BENCHES[fig.bench].shown()}`" in line


def test_the_readme_keeps_no_lab_notes():
    text = README.read_text()
    for pattern in (r"\bsessions?\s+\d", r"\b12-0\d\b", r"\bissue\s+\d", r"RESULTS\.md, session", r"car_road"):
        assert not re.search(pattern, text), pattern
