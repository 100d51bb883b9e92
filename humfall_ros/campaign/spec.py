"""The campaign spec (config/campaigns/*.yaml): what to run, over which scenario keys, how.

A spec names a base scenario (config/scenarios), fixed ``--set`` overrides, a design
(a grid, or a seeded random sample, over scenario keys), a study (``sweep``: run
every design point; ``threshold-map``: bisect one key per design point until the
outcome flips within ``tolerance``), the per-trial time limit and the output folder.

Every model refuses unknown keys; errors carry the dotted path of the offending key
(``design.grid.push.0.direction_deg: ...``), and an empty design is refused, all before
anything starts. :func:`spec_hash` identifies a spec for resuming.
"""
from __future__ import annotations

import hashlib
import json
import pathlib
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class CampaignSpecError(ValueError):
    """A spec that cannot run; the message starts with the dotted path of the bad key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Linspace(_Strict):
    """``{linspace: [start, stop, count]}``: ``count`` evenly spaced values, both ends included."""

    linspace: tuple[float, float, int]

    @field_validator("linspace")
    @classmethod
    def _count(cls, v):
        if v[2] < 1:
            raise ValueError("count must be >= 1 (an empty axis makes an empty design)")
        return v

    def values(self) -> list[float]:
        a, b, n = self.linspace
        return [a] if n == 1 else [a + (b - a) * i / (n - 1) for i in range(n)]


class Circle(_Strict):
    """``{circle: count}``: ``count`` directions 0, 360/count, ... [deg] (360 itself left out)."""

    circle: int = Field(ge=1)

    def values(self) -> list[float]:
        return [360.0 * i / self.circle for i in range(self.circle)]


GridAxis = Annotated[list[Any], Field(min_length=1)] | Linspace | Circle


class Uniform(_Strict):
    uniform: tuple[float, float]


class Normal(_Strict):
    """``{normal: [mean, std]}``."""

    normal: tuple[float, float]


class Choice(_Strict):
    choice: Annotated[list[Any], Field(min_length=1)]


Distribution = Uniform | Normal | Choice


class RandomDesign(_Strict):
    """``n`` trials, each key drawn independently from its distribution with numpy's PCG64(seed)."""

    n: int = Field(ge=1)
    seed: int = 0
    keys: Annotated[dict[str, Distribution], Field(min_length=1)]


class Design(_Strict):
    """Exactly one of ``grid`` (the cartesian product of its axes, in key order) or ``random``."""

    grid: dict[str, GridAxis] | None = None
    random: RandomDesign | None = None

    @model_validator(mode="after")
    def _one(self):
        if (self.grid is None) == (self.random is None):
            raise ValueError("give exactly one of grid or random")
        if self.grid is not None and not self.grid:
            raise ValueError("grid: empty design (no keys)")
        return self

    def key_names(self) -> list[str]:
        return list(self.grid) if self.grid is not None else list(self.random.keys)


class SweepStudy(_Strict):
    """Run every design point once."""

    type: Literal["sweep"] = "sweep"


class ThresholdMapStudy(_Strict):
    """Per design point (a cell), bisect ``key`` on [low, high] until the bracket is <= tolerance.

    The outcome (a boolean result metric, ``fell`` by default) is assumed False at ``low``
    and True at ``high`` and monotone in between; a cell whose trials all give True
    (False) reports its threshold as below (above) the range.
    """

    type: Literal["threshold-map"]
    key: str = "push.0.magnitude_n"
    low: float
    high: float
    tolerance: float = Field(5.0, gt=0)
    outcome: str = "fell"

    @model_validator(mode="after")
    def _range(self):
        if not self.high > self.low:
            raise ValueError(f"high ({self.high}) must be above low ({self.low})")
        return self

    def max_steps(self) -> int:
        """Bisection steps that shrink the bracket to ``tolerance``."""
        steps, width = 0, self.high - self.low
        while width > self.tolerance:
            width /= 2.0
            steps += 1
        return steps


Study = Annotated[SweepStudy | ThresholdMapStudy, Field(discriminator="type")]


class TrialSpec(_Strict):
    time_limit_s: float = Field(120.0, gt=0, description="wall time after which a trial is killed [s]")
    mode: Literal["inprocess", "graph"] = "inprocess"
    stop_when_fallen: bool = Field(False, description=(
        "in-process only: end a trial STOP_AFTER_LANDING_S after the trunk lands (or 1 s after the fall if it "
        "does not land); the metrics that decide a fall and its direction are final by then"))


class OutputSpec(_Strict):
    dir: str = ""            # default runs/campaigns/<name>
    bags: bool = False       # per-trial recordings (graph: the MCAP bag; in-process: joint trajectories .npz)


class CampaignSpec(_Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    base_scenario: str
    set: list[str] = []
    design: Design
    study: Study = SweepStudy()
    trial: TrialSpec = TrialSpec()
    output: OutputSpec = OutputSpec()

    def output_dir(self) -> pathlib.Path:
        return pathlib.Path(self.output.dir or f"runs/campaigns/{self.name}")


def _dotted(loc: tuple) -> str:
    """pydantic's error location as a dotted key path, without the union-member tags it inserts."""
    parts = []
    for p in loc:
        s = str(p)
        if s in ("list[any]", "Linspace", "Circle", "Uniform", "Normal", "Choice", "sweep", "threshold-map") or \
                s.startswith(("function-", "tagged-union")) or "[" in s:
            continue
        parts.append(s)
    return ".".join(parts)


def from_dict(data: Any, source: str = "spec") -> CampaignSpec:
    """A validated spec, or CampaignSpecError naming the dotted path of the first problem."""
    if not isinstance(data, dict):
        raise CampaignSpecError(f"{source}: expected a mapping, got {type(data).__name__}")
    try:
        return CampaignSpec.model_validate(data)
    except ValidationError as e:
        errs = e.errors()
        # an unknown key is the most useful thing to say first
        errs.sort(key=lambda x: x["type"] != "extra_forbidden")
        first = errs[0]
        path = _dotted(first["loc"]) or "spec"
        msg = "unknown key" if first["type"] == "extra_forbidden" else first["msg"]
        more = f" (and {len(errs) - 1} more problems)" if len(errs) > 1 else ""
        raise CampaignSpecError(f"{path}: {msg}{more}") from None


def load(path: str | pathlib.Path) -> CampaignSpec:
    p = pathlib.Path(path)
    if not p.is_file():
        builtin = pathlib.Path(__file__).resolve().parents[2] / "config" / "campaigns" / f"{path}.yaml"
        if builtin.is_file():
            p = builtin
        else:
            raise CampaignSpecError(f"no campaign spec {str(path)!r}")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise CampaignSpecError(f"{p}: not valid YAML: {e}") from e
    return from_dict(data, str(p))


def spec_hash(spec: CampaignSpec, base_scenario: dict) -> str:
    """sha256 over what decides the trials' results: the spec (less its output folder) and the base scenario.

    The resolved base scenario is part of it, so an edited scenario file is not resumed
    into results of the old one. Execution options (workers, Ray address) are not.
    """
    d = spec.model_dump(mode="json")
    d["output"] = {k: v for k, v in d["output"].items() if k != "dir"}
    blob = json.dumps({"spec": d, "base_scenario": base_scenario}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()
