"""Category sets of PanopticFPN and the mapping between network outputs and dataset category ids.

PanopticFPN has two classifiers (detectron2's "separated" panoptic metadata, builtin_meta.py
``_get_coco_panoptic_separated_meta``): the box head predicts a *contiguous thing class* ``k`` in
``0 .. num_things-1`` (things in the order of the category list) and the semantic head a *channel* ``c`` where
channel 0 means "some thing" and channel ``c >= 1`` is the ``c``-th stuff category in list order.
:class:`CategorySet` maps both to dataset category ids (COCO panoptic ids 1..200; PVO's VKITTI2 trainIds 1..14),
which is what :class:`~pvslam_core.types.Segment` carries.  ``movable`` lists the categories that count as
dynamic (PV-SLAM eq. 4's mask), per set; a segmenter config may override it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Sequence

import torch

from pvslam_core.types import Category

__all__ = ["CategorySet", "category_set", "BUILTIN_SETS"]

_DATA = Path(__file__).with_name("data")
BUILTIN_SETS = ("coco_panoptic", "vkitti2")


@dataclass(frozen=True)
class CategorySet:
    name: str
    categories: tuple[Category, ...]
    movable: frozenset[int] = frozenset()  # dataset ids of the categories that count as dynamic

    def __post_init__(self) -> None:
        ids = [c.id for c in self.categories]
        if len(set(ids)) != len(ids):
            raise ValueError(f"category set {self.name!r}: duplicate category ids")
        if any(i <= 0 for i in ids):
            raise ValueError(f"category set {self.name!r}: category ids must be positive (0 is void)")
        unknown = set(self.movable) - set(ids)
        if unknown:
            raise ValueError(f"category set {self.name!r}: movable ids {sorted(unknown)} are not categories")

    # ------------------------------------------------------------------------------------------ structure
    @property
    def things(self) -> tuple[Category, ...]:
        return tuple(c for c in self.categories if c.isthing)

    @property
    def stuff(self) -> tuple[Category, ...]:
        return tuple(c for c in self.categories if not c.isthing)

    @property
    def num_thing_classes(self) -> int:
        """Box-head classes (the classifier has one more logit, background)."""
        return len(self.things)

    @property
    def num_sem_classes(self) -> int:
        """Semantic-head channels: 1 ("things") + the stuff categories."""
        return len(self.stuff) + 1

    def thing_ids(self) -> torch.Tensor:
        """int64 ``[num_thing_classes]``: contiguous thing class -> dataset category id."""
        return torch.tensor([c.id for c in self.things], dtype=torch.int64)

    def semantic_ids(self) -> torch.Tensor:
        """int64 ``[num_sem_classes]``: semantic channel -> dataset category id (channel 0 is "things", id 0)."""
        return torch.tensor([0] + [c.id for c in self.stuff], dtype=torch.int64)

    def by_id(self, category_id: int) -> Category:
        for c in self.categories:
            if c.id == category_id:
                return c
        raise KeyError(f"category set {self.name!r} has no category id {category_id}")

    def ids_of(self, names: Iterable[str]) -> frozenset[int]:
        """Dataset ids of categories given by name (case-insensitive); unknown names are an error."""
        lookup = {c.name.lower(): c.id for c in self.categories}
        out, missing = set(), []
        for n in names:
            if n.lower() in lookup:
                out.add(lookup[n.lower()])
            else:
                missing.append(n)
        if missing:
            raise ValueError(f"category set {self.name!r} has no categories named {missing}; "
                             f"known: {', '.join(c.name for c in self.categories)}")
        return frozenset(out)

    def with_movable(self, names: Sequence[str]) -> "CategorySet":
        return CategorySet(self.name, self.categories, self.ids_of(names))

    def is_movable(self, category_ids: torch.Tensor) -> torch.Tensor:
        """bool, same shape: whether each dataset category id is movable (ids <= 0 / void are not)."""
        movable = torch.tensor(sorted(self.movable), dtype=torch.int64, device=category_ids.device)
        return torch.isin(category_ids, movable)

    # ------------------------------------------------------------------------------------------ (de)serialise
    def to_dict(self) -> dict:
        return {"name": self.name,
                "categories": [{"id": c.id, "name": c.name, "isthing": c.isthing, "color": list(c.color)}
                               for c in self.categories],
                "movable": sorted(self.movable)}

    @classmethod
    def from_dict(cls, d: dict) -> "CategorySet":
        cats = tuple(Category(int(c["id"]), str(c["name"]), bool(c["isthing"]),
                              tuple(int(v) for v in c["color"])) for c in d["categories"])  # type: ignore[arg-type]
        movable = d.get("movable", ())
        if movable and isinstance(next(iter(movable)), str):
            return cls(str(d["name"]), cats).with_movable(movable)
        return cls(str(d["name"]), cats, frozenset(int(m) for m in movable))

    @classmethod
    def placeholder(cls, num_thing_classes: int, num_sem_classes: int, name: str = "placeholder") -> "CategorySet":
        """Unnamed categories of the right counts (stuff ids 1.., thing ids after them), for timing/tests."""
        n_stuff = num_sem_classes - 1
        cats = [Category(i + 1, f"stuff{i}", False) for i in range(n_stuff)]
        cats += [Category(n_stuff + k + 1, f"thing{k}", True) for k in range(num_thing_classes)]
        return cls(name, tuple(cats))

    @classmethod
    def from_categories(cls, name: str, categories: Sequence[Category], movable: Sequence[str] = ()) -> "CategorySet":
        """A set built from a dataset's category list (e.g. the synthetic generator's), things/stuff in list order."""
        return cls(name, tuple(categories)).with_movable(movable)


@lru_cache(maxsize=None)
def category_set(name: str) -> CategorySet:
    """A built-in set: ``coco_panoptic`` (133 categories, detectron2 order) or ``vkitti2`` (PVO's 14)."""
    path = _DATA / f"{name}.json"
    if name not in BUILTIN_SETS or not path.is_file():
        raise ValueError(f"unknown built-in category set {name!r}; known: {', '.join(BUILTIN_SETS)}")
    return CategorySet.from_dict(json.loads(path.read_text()))
