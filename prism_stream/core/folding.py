"""Results summed as they come, a few at a time, level by level: a tree reduce that needs no list of every
part up front, so what is held stays bounded however many parts there are."""

from __future__ import annotations


class Folding:
    """Handles (futures, or values) folded ``fan_in`` at a time as they are added, a counter in base
    ``fan_in``: level 0 holds parts as given, level j sums of ``fan_in ** j`` of them. A tree reduce's work
    (each part is in one fold a level, ``log_fan_in(n)`` levels), and at most ``fan_in - 1`` handles a level
    are held, where a list of every part would hold all n until the end.

    ``fold(*handles)`` returns a handle to their sum (a Dask future of a merge task, say); the sum must not
    depend on how the parts are grouped (merges that are associative and commutative: histograms, bottom sets).
    """

    def __init__(self, fold, fan_in: int):
        if fan_in < 2:
            raise ValueError(f"fan_in must be at least 2, not {fan_in}")
        self.fold, self.fan_in = fold, fan_in
        self.levels: list[list] = []

    def add(self, handle) -> None:
        level = 0
        while True:
            if len(self.levels) == level:
                self.levels.append([])
            self.levels[level].append(handle)
            if len(self.levels[level]) < self.fan_in:
                return
            handle, self.levels[level] = self.fold(*self.levels[level]), []
            level += 1

    def result(self, *more, fold_one: bool = False):
        """A handle to the sum of every part added (and of ``more``), the held ones folded ``fan_in`` at a
        time, smallest first, so that no fold takes more than ``fan_in`` parts. A lone part is returned as
        it is, unless ``fold_one`` (a fold that does more than sum, such as keeping one slot range of a
        bottom set, must see every part)."""
        handles = [*more, *reversed(self.held())]
        if not handles or (fold_one and len(handles) == 1):
            return self.fold(*handles)
        while len(handles) > 1:
            handles = [self.fold(*handles[i:i + self.fan_in]) if len(handles[i:i + self.fan_in]) > 1
                       else handles[i] for i in range(0, len(handles), self.fan_in)]
        return handles[0]

    def held(self) -> list:
        """The handles not yet folded, the largest sums first."""
        return [h for level in reversed(self.levels) for h in level]

    def __len__(self) -> int:
        return sum(len(level) for level in self.levels)
