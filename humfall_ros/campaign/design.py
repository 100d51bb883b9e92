"""Design points and trials: from a spec's grid or seeded random design to ``--set`` overrides.

Design keys are scenario keys (anything ``humfall up --set`` takes, checked by
humfall_ros.scenario.apply_override) or one of three push keys that are easier to sweep
than a force vector:

* ``push.N.magnitude_n`` — horizontal force magnitude [N],
* ``push.N.direction_deg`` — its heading, counter-clockwise from +x (forward) [deg]
  (90 = towards +y, the robot's left),
* ``push.N.height_m`` — z of the application point in the pushed link's frame [m].

They become ``push.N.force`` / ``push.N.point``; a push key the design leaves out keeps
the base scenario's value (its force's magnitude, heading and vertical part).

Two target keys put the base scenario's target box (its first ``is_target`` obstacle, same
size) on the floor along a heading, yawed to face the robot, so that a sweep over push
directions keeps a target in the way of every push (paper 1's layout, for every direction):

* ``target.distance_m`` — the box's near face from the origin (the initial feet centre) [m],
* ``target.heading_deg`` — its heading, counter-clockwise from +x [deg]; default: the
  heading of push 0 (after ``push.0.direction_deg``).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from typing import Any

import numpy as np

from humfall_ros import scenario as scenario_mod
from humfall_ros.campaign.spec import CampaignSpec, CampaignSpecError, Choice, Circle, Linspace, Normal, Uniform

PUSH_KEY = re.compile(r"^push\.(\d+)\.(magnitude_n|direction_deg|height_m)$")
TARGET_KEYS = ("target.distance_m", "target.heading_deg")


@dataclasses.dataclass(frozen=True)
class Trial:
    """One closed-loop run: a base scenario and its overrides.

    Attributes:
        index: position in the campaign's deterministic order (the table is sorted by it).
        trial_id: stable name, the key for resuming.
        settings: design key -> value of this trial.
        overrides: the ``--set`` assignments that make its scenario (spec ``set`` first).
        base_scenario: scenario name or path.
        tags: study bookkeeping stored with the row (cell, step, ...).
    """

    index: int
    trial_id: str
    settings: dict[str, Any]
    overrides: tuple[str, ...]
    base_scenario: str
    tags: dict[str, Any] = dataclasses.field(default_factory=dict)


def _yaml_value(v) -> str:
    return json.dumps(v)  # JSON is YAML: lists, numbers, strings, booleans all parse back


def overrides_for(settings: dict[str, Any], base: dict) -> list[str]:
    """``--set`` assignments for one design point on the validated base scenario ``base``."""
    out, pushes, target = [], {}, {}
    for key, value in settings.items():
        m = PUSH_KEY.match(key)
        if m:
            pushes.setdefault(int(m.group(1)), {})[m.group(2)] = value
        elif key in TARGET_KEYS:
            target[key.split(".")[1]] = float(value)
        else:
            out.append(f"{key}={_yaml_value(value)}")
    for i, p in sorted(pushes.items()):
        if i >= len(base["push"]):
            raise CampaignSpecError(f"push.{i}: the base scenario has {len(base['push'])} pushes")
        f = base["push"][i]["force"]
        if "magnitude_n" in p or "direction_deg" in p:
            mag = float(p.get("magnitude_n", math.hypot(f[0], f[1])))
            heading = math.radians(float(p.get("direction_deg", math.degrees(math.atan2(f[1], f[0])))))
            force = [round(mag * math.cos(heading), 9), round(mag * math.sin(heading), 9), f[2]]
            out.append(f"push.{i}.force={_yaml_value(force)}")
        if "height_m" in p:
            pt = base["push"][i]["point"]
            out.append(f"push.{i}.point={_yaml_value([pt[0], pt[1], float(p['height_m'])])}")
    if target:
        out.append(_target_override(target, base, pushes.get(0, {})))
    return out


def _target_override(target: dict[str, float], base: dict, push0: dict) -> str:
    """``obstacles=[...]``: the base's obstacles with its target box moved as the target keys say."""
    if "distance_m" not in target:
        raise CampaignSpecError("target.heading_deg needs target.distance_m")
    boxes = [dict(o) for o in base["obstacles"]]
    i = next((k for k, o in enumerate(boxes) if o.get("is_target")), None)
    if i is None:
        raise CampaignSpecError("target.*: the base scenario has no obstacle with is_target: true")
    if "heading_deg" in target:
        heading = math.radians(target["heading_deg"])
    elif "direction_deg" in push0:
        heading = math.radians(float(push0["direction_deg"]))
    elif base["push"]:
        f = base["push"][0]["force"]
        heading = math.atan2(f[1], f[0])
    else:
        raise CampaignSpecError("target.distance_m without target.heading_deg needs a push 0")
    box = boxes[i]
    centre = target["distance_m"] + box["size"][0] / 2  # the near face at distance_m
    box["position"] = [round(centre * math.cos(heading), 6), round(centre * math.sin(heading), 6),
                       box["position"][2]]
    box["yaw"] = round(heading, 6)
    boxes[i] = box
    return f"obstacles={_yaml_value(boxes)}"


def build_scenario(base_scenario: str, overrides: list[str] | tuple[str, ...]) -> dict:
    """The validated scenario of a trial (ScenarioError on a bad key or value)."""
    return scenario_mod.load(base_scenario, list(overrides))


def _axis_values(axis) -> list:
    if isinstance(axis, (Linspace, Circle)):
        return axis.values()
    return list(axis)


def _draw(dist, rng: np.random.Generator, n: int) -> list:
    if isinstance(dist, Uniform):
        return [float(x) for x in rng.uniform(dist.uniform[0], dist.uniform[1], n)]
    if isinstance(dist, Normal):
        return [float(x) for x in rng.normal(dist.normal[0], dist.normal[1], n)]
    if isinstance(dist, Choice):
        return [dist.choice[int(i)] for i in rng.integers(0, len(dist.choice), n)]
    raise TypeError(dist)


def design_points(spec: CampaignSpec) -> list[dict[str, Any]]:
    """The design's points in a fixed order (grid: row-major in key order; random: draw order)."""
    d = spec.design
    if d.grid is not None:
        axes = {k: _axis_values(v) for k, v in d.grid.items()}
        return [dict(zip(axes, combo)) for combo in itertools.product(*axes.values())]
    rng = np.random.Generator(np.random.PCG64(d.random.seed))
    cols = {k: _draw(dist, rng, d.random.n) for k, dist in d.random.keys.items()}
    return [{k: cols[k][i] for k in cols} for i in range(d.random.n)]


def check_design(spec: CampaignSpec, base: dict, points: list[dict], sample: int = 16) -> dict:
    """Refuse a spec whose keys or values the scenario refuses, before anything starts.

    Applies the spec's ``set``, then each design key alone (so an unknown key is named with its
    dotted path), then the first, last and up to ``sample`` evenly spaced design points (with the
    study's bracket ends) to the base scenario. Returns the base scenario with ``set`` applied.
    """
    where = f"design.{'grid' if spec.design.grid is not None else 'random.keys'}"
    try:
        for ov in spec.set:
            base = scenario_mod.apply_override(base, ov)
    except scenario_mod.ScenarioError as e:
        raise CampaignSpecError(f"set: {e}") from None
    if not points:
        raise CampaignSpecError("design: empty design (no trials)")
    study = spec.study
    if study.type == "threshold-map" and study.key in spec.design.key_names():
        raise CampaignSpecError(f"study.key: {study.key} is bisected by the study; it cannot also be a design key")

    def apply(settings: dict) -> None:
        sc = base
        for ov in overrides_for(settings, base):
            sc = scenario_mod.apply_override(sc, ov)

    keys = {k: points[0][k] for k in points[0]}
    if study.type == "threshold-map":
        keys[study.key] = study.low
    for key, value in keys.items():
        path = "study.key" if study.type == "threshold-map" and key == study.key else f"{where}.{key}"
        try:
            apply({key: value})
        except (scenario_mod.ScenarioError, CampaignSpecError) as err:
            raise CampaignSpecError(f"{path}: {err}") from None
    picks = sorted({0, len(points) - 1, *np.linspace(0, len(points) - 1, min(sample, len(points))).astype(int)})
    extra = [{study.key: study.low}, {study.key: study.high}] if study.type == "threshold-map" else [{}]
    for i in picks:
        for e in extra:
            try:
                apply({**points[int(i)], **e})
            except (scenario_mod.ScenarioError, CampaignSpecError) as err:
                raise CampaignSpecError(f"{where}: design point {int(i)} {points[int(i)]}: {err}") from None
    return base
