"""Room-seed ranges of the train / val / test splits of the procedural rooms (one place).

The rich rooms of :mod:`cegc_ros.data.rooms` are numbered by an integer *room seed*. A split
owns a half-open range of seeds; room ``k`` of a split has seed ``start + k``. The ranges never
overlap, so a validation or test room is never a training room, whichever tool made the data
(the pair cache, the different-view bags, ad-hoc scripts).

These seeds are a different namespace from the scene seeds of :mod:`cegc_ros.data.protocols`
(the older rooms of :mod:`cegc_ros.data.scenes`): the rich-room generator salts its random
streams differently, so room seed 5 and scene seed 5 are unrelated rooms.
"""

from __future__ import annotations

# split -> (first seed, one past the last seed)
ROOM_SPLITS: dict[str, tuple[int, int]] = {
    "train": (0, 10_000_000),
    "val": (10_000_000, 10_100_000),
    "test": (20_000_000, 20_100_000),
}
SPLITS = tuple(ROOM_SPLITS)


def check_split(split: str) -> None:
    """Raise ValueError naming the valid splits when ``split`` is not one of them."""
    if split not in ROOM_SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")


def num_rooms(split: str) -> int:
    """How many rooms the split's seed range holds."""
    check_split(split)
    lo, hi = ROOM_SPLITS[split]
    return hi - lo


def room_seed(split: str, k: int) -> int:
    """Seed of room ``k`` (0-based) of a split."""
    check_split(split)
    lo, hi = ROOM_SPLITS[split]
    if not 0 <= k < hi - lo:
        raise ValueError(f"room index {k} outside 0..{hi - lo - 1} of split {split!r}")
    return lo + int(k)


def split_of(seed: int) -> str:
    """The split a room seed belongs to; ValueError for a seed outside every range."""
    for name, (lo, hi) in ROOM_SPLITS.items():
        if lo <= seed < hi:
            return name
    raise ValueError(f"room seed {seed} belongs to no split {ROOM_SPLITS}")
