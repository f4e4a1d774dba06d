"""The product is not a lab notebook: config field descriptions are short (what, unit, one line of why) and quote no
results, seeds or experiment dates; library code and docstrings do not cite benchmark logs or quote run results.
The measured why of a default lives in ``docs/decisions.md``.

    python tests/style/test_no_lab_notebook.py      # list every offender
"""
from __future__ import annotations

import importlib
import pkgutil
import re
import sys
import tokenize
from pathlib import Path

import pytest
from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[2]
LIBRARY = [ROOT / "pvslam_core", ROOT / "plugins" / "pvslam_plugins"]
MAX_DESCRIPTION = 200
# a run's result, a seed, an experiment's date or session, a benchmark log
RESULT = re.compile(
    r"(?<![.:\d])\d+(\.\d+)?\s*%(?![}\w])|\bseeds?\s+\d|(?-i:RESULTS\.md)|\bbench/|\bsessions?\s+(20\d\d|\d\d-\d\d)|"
    r"\b20\d\d-\d\d-\d\d\b|\bissue\s+\d|\d\s*->\s*\d|\btune (seeds|set)\b|\bfresh seeds\b", re.IGNORECASE)
SEED = re.compile(r"\bseeds?\s+\d", re.IGNORECASE)
# where a seed is the subject (the synthetic generator's sequences), naming one is not a lab note
SEED_IS_A_PARAMETER = ("plugins/pvslam_plugins/datasets/synthetic/",)


def _modules():
    for pkg in ("pvslam_core", "pvslam_plugins"):
        root = importlib.import_module(pkg)
        for info in pkgutil.walk_packages(root.__path__, pkg + "."):
            if ".tests" in info.name or info.name.endswith(("_test", ".conftest")) or ".viz" in info.name:
                continue
            try:
                yield importlib.import_module(info.name)
            except ImportError:  # an optional extra that is not installed
                continue


def config_models() -> list[type[BaseModel]]:
    """Every pydantic model defined in the library (core sections, plugin and trainer configs)."""
    seen: dict[str, type[BaseModel]] = {}
    for mod in _modules():
        for obj in vars(mod).values():
            if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == mod.__name__:
                seen[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return [seen[k] for k in sorted(seen)]


def description_problems() -> list[str]:
    out = []
    for model in config_models():
        for name, field in model.model_fields.items():
            where = f"{model.__module__}.{model.__qualname__}.{name}"
            d = field.description or ""
            if not d.strip():
                out.append(f"{where}: no description")
            if len(d) > MAX_DESCRIPTION:
                out.append(f"{where}: description of {len(d)} characters (at most {MAX_DESCRIPTION})")
            m = RESULT.search(d)
            if m:
                out.append(f"{where}: description quotes a result, seed or date ({m.group(0)!r})")
    return out


def _text_lines(path: Path):
    """``(line number, text)`` of the comments and string literals (docstrings included) of a source file."""
    with path.open("rb") as fh:
        for tok in tokenize.tokenize(fh.readline):
            if tok.type in (tokenize.COMMENT, tokenize.STRING) or tok.type == getattr(tokenize, "FSTRING_MIDDLE", -1):
                for k, text in enumerate(tok.string.splitlines()):
                    yield tok.start[0] + k, text


def source_problems() -> list[str]:
    """Library comments and strings that read as a lab log."""
    out = []
    for base in LIBRARY:
        for path in sorted(base.rglob("*.py")):
            if "tests" in path.relative_to(base).parts:
                continue
            rel = path.relative_to(ROOT).as_posix()
            for n, line in _text_lines(path):
                for m in RESULT.finditer(line):
                    if SEED.fullmatch(m.group(0)) and rel.startswith(SEED_IS_A_PARAMETER):
                        continue
                    out.append(f"{rel}:{n}: {m.group(0)!r}: {line.strip()[:100]}")
                    break
    return out


ISSUE = re.compile(r"\bissues?\s+#?\d", re.IGNORECASE)


def issue_citations() -> list[str]:
    """Comments and strings anywhere in the tree (tests and bench tools too) that cite an issue by number: the why
    is said in words, the history lives in the issues and the changelog."""
    out = []
    for base in (ROOT / "pvslam_core", ROOT / "plugins", ROOT / "tests", ROOT / "bench", ROOT / "examples"):
        for path in sorted(base.rglob("*.py")):
            for n, line in _text_lines(path):
                m = ISSUE.search(line)
                if m:
                    out.append(f"{path.relative_to(ROOT).as_posix()}:{n}: {line.strip()[:100]}")
    return out


def test_no_code_cites_an_issue_number():
    problems = issue_citations()
    assert not problems, "\n".join(problems)


def test_config_descriptions_are_short_and_quote_no_results():
    problems = description_problems()
    assert not problems, "\n".join(problems)


def test_library_code_is_not_a_lab_log():
    problems = source_problems()
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("text, bad", [
    ("robust kernel of the BA ('none': least squares)", False),
    ("Huber(1 px) gave 5.7 % ATE", True),
    ("chosen on seeds 3-5", True),
    ("see bench/RESULTS.md", True),
    ("driving_block lost them all: 0.17 -> 1.03", True),
    ("a keyframe every ~2 frames at 12 frames/s", False),
    ("f'{fail:.0%} of pixels fail'", False),
    ("sweep writes results.md", False),
])
def test_the_checker_itself(text, bad):
    assert bool(RESULT.search(text)) is bad


if __name__ == "__main__":
    rows = description_problems() + source_problems() + issue_citations()
    print("\n".join(rows))
    print(f"{len(rows)} problems", file=sys.stderr)
