"""Figures in the style of paper 2: the contact transition tree (Fig. 1, 3, 4),
stick-figure sequences of a plan (Fig. 5, 6) and kinetic energy over time for
the sweep (Fig. 7). matplotlib with the Agg backend; no ROS."""
from __future__ import annotations

import dataclasses
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from humfall_ros.multicontact.model import HANDS, PlanarModel
from humfall_ros.multicontact.modes import parse_mode

_COLORS = {"root": "#e6c700", "terminal": "#1f5fd6", "connectable": "#2ca02c", "failed": "#d62728"}


def _node_color(node: dict, path: list[int]) -> str:
    if node["id"] == 0:
        return _COLORS["root"]
    if node["status"] == "terminal":
        return _COLORS["terminal"]
    if node["status"] == "expanded" or node["id"] in path:
        return _COLORS["connectable"] if node["status"] != "expanded" else _COLORS["failed"]
    return _COLORS["connectable"]


def plot_tree(tree: dict, path: str, title: str = "") -> str:
    """Contact transition tree: depth left to right, one row per node of a level.

    Yellow root, blue terminal (stabilised), green connectable (reached, not
    yet expanded), red expanded without a stabilising self-motion; the solution
    path in orange; labels give the mode, the node's kinetic energy and the duration of the edge that
    made it (two children of the same mode differ in it: a release and its short alternative).
    """
    nodes = tree["nodes"]
    sol = tree.get("path") or []
    by_depth: dict[int, list] = {}
    for n in nodes:
        by_depth.setdefault(n["depth"], []).append(n)
    pos = {}
    for d, ns in by_depth.items():
        for i, n in enumerate(ns):
            pos[n["id"]] = (d, -(i - (len(ns) - 1) / 2.0))
    width = 2.8 + 2.4 * max(by_depth) if by_depth else 4
    fig, ax = plt.subplots(figsize=(width, 1.2 + 0.9 * max(len(v) for v in by_depth.values())))
    for n in nodes:
        if n["parent"] is not None:
            (x0, y0), (x1, y1) = pos[n["parent"]], pos[n["id"]]
            on = n["id"] in sol and n["parent"] in sol
            ax.plot([x0, x1], [y0, y1], color="orange" if on else "0.6", lw=2.5 if on else 1.0, zorder=1)
    for n in nodes:
        x, y = pos[n["id"]]
        ax.scatter([x], [y], s=140, color=_node_color(n, sol), edgecolor="k", zorder=3)
        sm = n.get("self_motion")
        extra = f"\nself: {sm['final_ke']:.2g} J" if sm else ""
        edge = n.get("edge")   # the tree dict without trajectories, as every caller passes it
        after = f" ({edge['duration']:.2f} s)" if edge else ""
        ax.annotate(f"{n['mode']}{after}\n{n['ke']:.1f} J{extra}", (x, y), textcoords="offset points",
                    xytext=(9, 4), fontsize=7)
    ax.set_xlabel("tree depth")
    ax.set_yticks([])
    ax.margins(y=0.12)   # room for the top row's labels under the title
    ax.set_xlim(-0.3, max(by_depth) + 0.9 if by_depth else 1)
    ax.set_title(title or ("solution: " + " -> ".join(nodes[i]["mode"] for i in sol) if sol else "no solution"),
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_sticks(model: PlanarModel, segments: list, path: str, wall_x: float | None = None, title: str = "") -> str:
    """Stick figures at every knot of each segment of a plan (Fig. 5-6 style)."""
    k = len(segments)
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 3.6), squeeze=False)
    for ax, seg in zip(axes[0], segments):
        N = len(seg.time)
        for i in range(N):
            c = plt.cm.viridis(i / max(1, N - 1))
            for a, b in model.skeleton(seg.q[i]):
                ax.plot([a[0], b[0]], [a[1], b[1]], color=c, lw=1.4, alpha=0.35 + 0.65 * (i == N - 1))
        ax.axhline(0.0, color="k", lw=1)
        if wall_x is not None:
            ax.axvline(wall_x, color="saddlebrown", lw=3)
        lbl = seg.kind.replace("_", "-")
        tgt = f" -> {'/'.join(seg.target_mode)}" if seg.kind == "transition" else ""
        ax.set_title(f"{lbl} {'/'.join(seg.mode)}{tgt}\n{seg.time[-1]:.2f} s, KE {seg.ke[0]:.1f} -> {seg.ke[-1]:.2g} J",
                     fontsize=8)
        ax.set_aspect("equal")
        ax.set_xlim(-0.6, 1.4)
        ax.set_ylim(-0.05, 1.5)
        ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ke_profile(segments: list) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated (t, KE) over a plan's segments, with the impact drops."""
    ts, ks = [], []
    t0 = 0.0
    for s in segments:
        ts.append(t0 + s.time)
        ks.append(s.ke)
        t0 += float(s.time[-1])
    return (np.concatenate(ts), np.concatenate(ks)) if ts else (np.zeros(0), np.zeros(0))


def plot_ke_sweep(results: list[dict], path: str) -> str:
    """Kinetic energy over time for every case of the sweep (Fig. 7 style)."""
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for r in results:
        t, ke = ke_profile(r.get("segments", []))
        if len(t):
            lbl = f"{r['initial_ke']:.0f} J: " + " -> ".join(r["contact_sequence"])
            ax.plot(t, ke, marker=".", lw=1.2, label=lbl)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("kinetic energy (J)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_library(model: PlanarModel, library, path: str, limits=None) -> str:
    """What a plan library holds: per stored push, the pre-impact kinetic energy of each landing against
    the push's (top; the dashed line is issue 14's "no more than the push"), and its touchdown speed
    (bottom; ``limits``' hand bound dotted). Feet triangles, hands circles; a colour per group (forward,
    backward, each wall distance); a push with no landing (inertial shaping only) sits at zero."""
    fig, (ax_ke, ax_v) = plt.subplots(2, 1, figsize=(7.0, 6.2), sharex=True)
    groups: dict[tuple, list] = {}
    for entry, reps in library.landings(model, limits):
        groups.setdefault((entry.direction, entry.wall_distance), []).append((entry, reps))
    cmap = plt.get_cmap("tab10")
    top = 0.0
    for i, ((d, w), items) in enumerate(sorted(groups.items(), key=lambda kv: (kv[0][1], -kv[0][0]))):
        color = cmap(i % 10)
        label = f"wall {w:g} m" if w > 0 else ("forward" if d > 0 else "backward")
        for j, (e, reps) in enumerate(items):
            if not reps:
                ax_ke.scatter([e.kinetic_energy], [0.0], marker="s", color=color, s=22,
                              label=label if j == 0 else None)
            for k, r in enumerate(reps):
                hand = r.limb in HANDS
                kw = dict(marker="o" if hand else "^", color=color, s=26, alpha=0.85,
                          label=label if j == 0 and k == 0 else None)
                ax_ke.scatter([e.kinetic_energy], [r.pre_impact_ke], **kw)
                ax_v.scatter([e.kinetic_energy], [r.normal_speed], **{**kw, "label": None})
                top = max(top, r.pre_impact_ke, e.kinetic_energy)
    ax_ke.plot([0, top], [0, top], "k--", lw=0.8)
    hand_max = getattr(limits, "hand_normal_speed_max", float("inf"))
    if np.isfinite(hand_max):
        ax_v.axhline(hand_max, color="k", ls=":", lw=0.8)
    ax_ke.set_ylabel("pre-impact KE (J)")
    ax_v.set_ylabel("touchdown normal speed (m/s)")
    ax_v.set_xlabel("push kinetic energy (J)")
    for ax in (ax_ke, ax_v):
        ax.grid(alpha=0.3)
    ax_ke.legend(fontsize=7, ncol=2, title="triangles feet, circles hands, squares no landing", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_all(model: PlanarModel, results: list[dict], wall_result: dict | None, outdir: str) -> list[str]:
    """All figures for a sweep (and the wall case) into ``outdir``: the sweep's
    kinetic energies, then ``write_plan`` for every case."""
    os.makedirs(outdir, exist_ok=True)
    files = [plot_ke_sweep(results, os.path.join(outdir, "multicontact_ke_sweep.png"))]
    for r in list(results) + ([wall_result] if wall_result else []):
        tag = f"multicontact_{r['initial_ke']:.0f}J" + ("_wall" if r.get("wall_x") else "")
        files += write_plan(model, r, outdir, tag)
    return files


@dataclasses.dataclass
class PlottedSegment:
    """What the plots need of a plan segment; built from a ``plan_fall``
    response (``PlanSegment`` messages: row-major arrays) by ``segments_from_msgs``."""

    kind: str
    mode: tuple
    target_mode: tuple
    time: np.ndarray
    q: np.ndarray
    ke: np.ndarray


def segments_from_msgs(msgs) -> list[PlottedSegment]:
    out = []
    for s in msgs:
        n = len(s.coordinate_names)
        out.append(PlottedSegment(kind=s.kind, mode=parse_mode(s.mode),
                                  target_mode=parse_mode(s.target_mode), time=np.asarray(s.time, float),
                                  q=np.asarray(s.q, float).reshape(len(s.time), n),
                                  ke=np.asarray(s.kinetic_energy, float)))
    return out


def write_plan(model: PlanarModel, result: dict, outdir: str, tag: str = "plan") -> list[str]:
    """The figures of one plan: its tree (Fig. 1), stick figures (Fig. 5-6) and
    kinetic energy over time (Fig. 7). ``result`` holds ``tree`` (dict or None),
    ``segments``, ``contact_sequence``, ``success``, ``initial_ke`` and
    ``wall_x`` (None without a wall)."""
    os.makedirs(outdir, exist_ok=True)
    files = []
    title = f"{result['initial_ke']:.0f} J" + (f", wall at {result['wall_x']:.2f} m" if result.get("wall_x") else "")
    if result.get("tree"):
        seq = ": " + " -> ".join(result["contact_sequence"]) if result["success"] else ": no solution"
        files.append(plot_tree(result["tree"], os.path.join(outdir, f"{tag}_tree.png"), title=title + seq))
    if result.get("segments"):
        files.append(plot_sticks(model, result["segments"], os.path.join(outdir, f"{tag}_sticks.png"),
                                 wall_x=result.get("wall_x"), title=title))
        files.append(plot_ke_sweep([result], os.path.join(outdir, f"{tag}_ke.png")))
    return files

