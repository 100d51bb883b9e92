"""Studies: which trials to run, given the results so far.

A study hands out trials (``start``) and, fed each finished trial's row, the trials
that became ready (``feed``). ``Sweep`` runs every design point once. ``ThresholdMap``
bisects one key (the push magnitude) per design point (a *cell*: a push direction and
height, say) until the bracket [largest value with outcome False, smallest with outcome
True] is no wider than the tolerance: ceil(log2((high - low) / tolerance)) trials per
cell, the cells in parallel. Both are deterministic, so a resumed campaign asks for the
same trials and finds the finished ones in the store.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from humfall_ros.campaign.design import Trial, overrides_for
from humfall_ros.campaign.spec import CampaignSpec, ThresholdMapStudy


class Sweep:
    def __init__(self, spec: CampaignSpec, base: dict, points: list[dict[str, Any]]):
        width = max(6, len(str(len(points))))
        self.trials = [Trial(i, f"t{i:0{width}d}", p, (*spec.set, *overrides_for(p, base)), spec.base_scenario)
                       for i, p in enumerate(points)]

    @property
    def total(self) -> int:
        return len(self.trials)

    def start(self) -> list[Trial]:
        return list(self.trials)

    def feed(self, trial: Trial, row: dict) -> list[Trial]:
        return []


@dataclasses.dataclass
class Cell:
    """One bisection: ``low`` has not shown the outcome, ``high`` has (or the range ends)."""

    index: int
    point: dict[str, Any]
    low: float
    high: float
    step: int = 0
    low_seen: bool = False       # a trial at `low` gave outcome False
    high_seen: bool = False      # a trial at `high` gave outcome True
    failed: bool = False
    done: bool = False


class ThresholdMap:
    def __init__(self, spec: CampaignSpec, base: dict, points: list[dict[str, Any]]):
        study = spec.study
        assert isinstance(study, ThresholdMapStudy)
        self.spec, self.base, self.study = spec, base, study
        self.steps = study.max_steps()
        self.cells = [Cell(i, p, study.low, study.high) for i, p in enumerate(points)]

    @property
    def total(self) -> int:
        """Trials if no cell fails (each cell takes exactly ``steps`` trials)."""
        return len(self.cells) * self.steps

    def _trial(self, cell: Cell) -> Trial:
        value = round(0.5 * (cell.low + cell.high), 6)
        settings = {**cell.point, self.study.key: value}
        return Trial(cell.index * (self.steps + 1) + cell.step, f"c{cell.index:04d}-s{cell.step:02d}", settings,
                     (*self.spec.set, *overrides_for(settings, self.base)), self.spec.base_scenario,
                     {"cell": cell.index, "step": cell.step, "bracket_low": cell.low, "bracket_high": cell.high})

    def start(self) -> list[Trial]:
        return [self._trial(c) for c in self.cells if self.steps > 0]

    def feed(self, trial: Trial, row: dict) -> list[Trial]:
        cell = self.cells[trial.tags["cell"]]
        if cell.done:
            return []
        outcome = row.get(f"m.{self.study.outcome}")
        if row.get("status") != "ok" or outcome is None:
            cell.failed = cell.done = True      # no outcome: the bisection cannot go on
            return []
        value = trial.settings[self.study.key]
        if outcome:
            cell.high, cell.high_seen = value, True
        else:
            cell.low, cell.low_seen = value, True
        cell.step += 1
        if cell.step >= self.steps:
            cell.done = True
            return []
        return [self._trial(cell)]
