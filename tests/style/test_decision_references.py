"""Every ``(docs/decisions.md: NAME)`` pointer in the library, its config descriptions, the shipped configs and
``pyproject.toml`` names a record that exists, and the records are numbered 1, 2, 3, ... without gaps."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DECISIONS = ROOT / "docs" / "decisions.md"
POINTER = re.compile(r"docs/decisions\.md: ([^)\"]+?)\s*[)\"]")


def _records() -> dict[str, int]:
    return {m.group(2).strip(): int(m.group(1))
            for m in re.finditer(r"^### (\d+)\. (.+)$", DECISIONS.read_text(encoding="utf-8"), re.M)}


def _pointers():
    files = [*ROOT.joinpath("pvslam_core").rglob("*.py"), *ROOT.joinpath("plugins").rglob("*.py"),
             *ROOT.joinpath("configs").glob("*.toml"), ROOT / "pyproject.toml"]
    for path in files:
        # comments and strings wrap: join the continuation lines before reading a pointer
        text = re.sub(r"\n\s*#\s*|\"\s*\n\s*\"|\n\s*", " ", path.read_text(encoding="utf-8"))
        for m in POINTER.finditer(text):
            yield path.relative_to(ROOT).as_posix(), " ".join(m.group(1).split())


def test_records_are_numbered_in_order():
    numbers = sorted(_records().values())
    assert numbers == list(range(1, len(numbers) + 1))


def test_every_pointer_names_a_record():
    records = {" ".join(k.split()) for k in _records()}
    pointers = list(_pointers())
    assert len(pointers) > 50  # the pointers are found at all
    missing = sorted({f"{where}: {name}" for where, name in pointers if name not in records})
    assert not missing, "\n".join(missing)
