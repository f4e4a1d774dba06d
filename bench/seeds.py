"""The seed ledger (``bench/seeds.toml``): the named seed sets of the synthetic benchmark and the spent seeds.

    python bench/seeds.py             # the sets, the spent ranges and the next fresh seeds
    python bench/seeds.py --fresh 3   # the next 3 fresh seeds (for a new decision)
    python bench/seeds.py --which 4   # which set a seed belongs to
"""
from __future__ import annotations

import argparse
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

LEDGER = Path(__file__).resolve().with_name("seeds.toml")


@dataclass(frozen=True)
class Spent:
    first: int
    last: int
    use: str

    @property
    def seeds(self) -> range:
        return range(self.first, self.last + 1)


@dataclass(frozen=True)
class Ledger:
    sets: dict[str, tuple[int, ...]]  # name -> seeds (default, tune, report, heldout)
    spent: tuple[Spent, ...]          # sorted, non-overlapping ranges

    @property
    def spent_seeds(self) -> tuple[int, ...]:
        return tuple(s for r in self.spent for s in r.seeds)

    def set_of(self, seed: int) -> str:
        """The set ``seed`` belongs to: a named set, ``used`` (spent) or ``fresh``."""
        for name, seeds in self.sets.items():
            if seed in seeds:
                return name
        return "used" if any(seed in r.seeds for r in self.spent) else "fresh"

    def fresh(self, n: int) -> list[int]:
        """The ``n`` lowest seeds that no set and no spent range names (every lower seed has been seen)."""
        known = set(self.spent_seeds) | {s for v in self.sets.values() for s in v}
        out, s = [], 0
        while len(out) < n:
            if s not in known:
                out.append(s)
            s += 1
        return out


class LedgerError(ValueError):
    pass


def load(path: Path = LEDGER) -> Ledger:
    """Read and check the ledger: sets disjoint, spent ranges sorted, disjoint from each other and from the sets."""
    raw = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    sets = {str(k): tuple(int(s) for s in v) for k, v in raw.get("sets", {}).items()}
    spent = tuple(Spent(int(e["seeds"][0]), int(e["seeds"][1]), str(e.get("use", ""))) for e in raw.get("spent", []))
    for name in ("default", "tune", "report"):
        if not sets.get(name):
            raise LedgerError(f"{path}: [sets] {name} is missing or empty")
    names = list(sets)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if set(sets[a]) & set(sets[b]):
                raise LedgerError(f"{path}: sets {a} and {b} share seeds {sorted(set(sets[a]) & set(sets[b]))}")
    named = {s for v in sets.values() for s in v}
    for k, r in enumerate(spent):
        if r.first > r.last or not r.use:
            raise LedgerError(f"{path}: spent range {r.first}-{r.last} is empty or says no use")
        if k and r.first <= spent[k - 1].last:
            raise LedgerError(f"{path}: spent range {r.first}-{r.last} overlaps or precedes the one before")
        if named & set(r.seeds):
            raise LedgerError(f"{path}: spent range {r.first}-{r.last} holds seeds of a named set "
                              f"{sorted(named & set(r.seeds))}")
    return Ledger(sets, spent)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fresh", type=int, metavar="N", help="print the next N fresh seeds")
    ap.add_argument("--which", type=int, nargs="+", metavar="SEED", help="print the set of each seed")
    args = ap.parse_args(argv)
    led = load()
    if args.fresh:
        print(" ".join(map(str, led.fresh(args.fresh))))
        return 0
    if args.which:
        for s in args.which:
            print(f"{s}: {led.set_of(s)}")
        return 0
    width = max(len("spent"), *map(len, led.sets)) + 1
    for name, seeds in led.sets.items():
        print(f"{name:<{width}}{', '.join(map(str, seeds))}")
    for r in led.spent:
        print(f"{'spent':<{width}}{r.first}-{r.last}: {r.use}")
    print(f"next fresh: {', '.join(map(str, led.fresh(3)))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
