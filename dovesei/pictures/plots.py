"""Pictures of flown episodes: the trajectory over the map and the bench's paths.

Everything here reads plain data (the report dict `dovesei up` writes, the bench's results and
track files) and writes files; nothing talks to Zenoh or runs an episode.

    report.json dict  --plot_trajectory-->  trajectory.png   world crop, path coloured by the
                                                             controller's state, start, end, the
                                                             footprint disk to scale + inset zoom
    results.json dict + tracks/*.npy --plot_bench_paths-->  paths.png   one panel per start, every
                                                             policy's path from it

matplotlib is imported inside the plotting functions (it is a dev extra and slow to import).
World coordinates: x east, y north, metres (see `dovesei.sim.world`).
"""

from __future__ import annotations

import logging
import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dovesei.pictures.common import ReportError, backend_label
from dovesei.shared.mission import HANDOVER_ALT_M, PERSON_SEPARATION_M, SAFETY_RADIUS_M, VEHICLE_SEPARATION_M

log = logging.getLogger(__name__)

# Controller states -> colour. The policy's states first, then the loop's own (INIT, HANDOVER).
STATE_COLOURS: dict[str, str] = {
    "SENSOR_ERROR": "#9e9e9e",
    "INIT": "#bdbdbd",
    "SEARCHING": "#1f77b4",
    "AIMING": "#ff7f0e",
    "LANDING": "#2ca02c",
    "WAITING": "#d62728",
    "RESTARTING": "#9467bd",
    "CLIMBING": "#8c564b",
    "LANDED": "#17becf",
    "HANDOVER": "#17becf",
    # The `clearance` policy's phases (the same hue for the same role as the paper's states).
    "WARMUP": "#c7c7c7",
    "SEARCH": "#1f77b4",
    "PROBE": "#aec7e8",
    "APPROACH": "#ff7f0e",
    "DESCEND": "#2ca02c",
    "ABORT": "#8c564b",
    "GAP_HOLD": "#d62728",
    "NO_SPOT": "#9467bd",
    "watchdog hold": "#000000",
    "watchdog climb": "#e6550d",
    "watchdog state_stale": "#636363",
}
OTHER_STATE_COLOUR = "#e377c2"
# The controller's watchdog overriding the policy (blind: hold, then climb): drawn instead of the state.
WATCHDOG_COLOURS = {"hold": "#000000", "climb": "#e6550d", "state_stale": "#636363"}
OUTCOME_COLOURS = {"safe": "#2ca02c", "unsafe": "#d62728", "timeout": "#ff7f0e", "out_of_world": "#7f7f7f",
                   "error": "#000000"}
POLICY_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b")


# ---------------------------------------------------------------- shared helpers


def _crop_box_m(xs: np.ndarray, ys: np.ndarray, world: Any, margin_frac: float = 0.25,
                min_half_m: float = 25.0) -> tuple[float, float, float, float]:
    """A square (x0, x1, y0, y1) around the points with a margin, clipped to the world."""
    cx, cy = (float(xs.min()) + float(xs.max())) / 2.0, (float(ys.min()) + float(ys.max())) / 2.0
    half_m = max(float(np.ptp(xs)), float(np.ptp(ys))) / 2.0
    half_m = max(min_half_m, half_m * (1.0 + 2.0 * margin_frac))
    x0, x1 = max(0.0, cx - half_m), min(world.width_m, cx + half_m)
    y0, y1 = max(0.0, cy - half_m), min(world.height_m, cy + half_m)
    return x0, x1, y0, y1


def _world_crop(world: Any, box_m: tuple[float, float, float, float],
                max_side_px: int = 1600) -> tuple[np.ndarray, list[float]]:
    """The orthoimage inside a box, with the imshow extent in metres that it really covers.

    Crops larger than `max_side_px` are shrunk first (area averaging): a figure is ~1000 px
    wide, and handing matplotlib a whole 6400 px world costs seconds for nothing.
    """
    x0, x1, y0, y1 = box_m
    g, h = world.gsd_m, world.height_px
    # Image rows count from the north edge; world y counts from the south edge.
    c0, c1 = max(0, int(math.floor(x0 / g))), min(world.width_px, int(math.ceil(x1 / g)))
    r0, r1 = max(0, int(math.floor(h - y1 / g))), min(h, int(math.ceil(h - y0 / g)))
    if c1 <= c0 or r1 <= r0:
        raise ReportError(f"crop box {box_m} lies outside the world")
    extent = [c0 * g, c1 * g, (h - r1) * g, (h - r0) * g]
    crop = world.image_rgb[r0:r1, c0:c1]
    scale = max_side_px / max(crop.shape[:2])
    if scale < 1.0:
        size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
    return crop, extent


def _marker_xy(x: float, y: float, extent: Sequence[float], margin_frac: float = 0.035) -> tuple[float, float]:
    """Where to draw a point's marker: the point, or for one at or past the panel's edge (a track that
    left the map) the nearest place a whole marker fits inside the axes. Matplotlib draws a marker
    whose centre is inside the axes unclipped, so one on the top edge sat on the panel's title."""
    mx = margin_frac * (extent[1] - extent[0])
    my = margin_frac * (extent[3] - extent[2])
    return (min(max(x, extent[0] + mx), extent[1] - mx), min(max(y, extent[2] + my), extent[3] - my))


def _labels_crop(world: Any, box_m: tuple[float, float, float, float]) -> np.ndarray | None:
    if world.labels is None:
        return None
    x0, x1, y0, y1 = box_m
    g, h = world.gsd_m, world.height_px
    c0, c1 = max(0, int(math.floor(x0 / g))), min(world.width_px, int(math.ceil(x1 / g)))
    r0, r1 = max(0, int(math.floor(h - y1 / g))), min(h, int(math.ceil(h - y0 / g)))
    return world.labels[r0:r1, c0:c1]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only: no display on servers and CI
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------- one episode: trajectory.png


# A close look's verdict (issue 24) where the vehicle took it: cleared, something of the never set
# inside the margin, or no answer.
LOOK_MARKERS = {"clear": ("o", "#2ca02c", "close look: clear"),
                "never": ("X", "#d62728", "close look: never set inside the margin"),
                "look failed": ("s", "#ff7f0e", "close look: no answer")}


def _close_looks(ax: Any, xs: np.ndarray, ys: np.ndarray, looks: list[str]) -> list[Any]:
    """Mark each new close-look verdict at the position it arrived; the legend handles of those shown."""
    from matplotlib.lines import Line2D

    if len(looks) != xs.size:
        return []
    shown = {}
    for i, verdict in enumerate(looks):
        if not verdict or (i and verdict == looks[i - 1]):
            continue
        kind = next((k for k in LOOK_MARKERS if verdict.startswith(k)), None)
        if kind is None:
            continue
        marker, colour, label = LOOK_MARKERS[kind]
        ax.plot(xs[i], ys[i], marker=marker, ls="", color=colour, markeredgecolor="white", ms=7, zorder=7)
        shown[kind] = Line2D([], [], marker=marker, ls="", color=colour, markeredgecolor="white", ms=8, label=label)
    return list(shown.values())


def plot_trajectory(world: Any, report: Mapping[str, Any], out_png: Path | str) -> Path:
    """Draw one episode of `dovesei up` over the world image; returns the PNG's path.

    `report` is the report.json dict: it needs `trajectory` (columns x_m, y_m, state), `start`,
    `final`, `outcome`, `policy`, `backend`, `simulated` and optionally `safety_radius_m`.
    """
    from matplotlib import patheffects
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle

    plt = _pyplot()
    traj = report.get("trajectory") or {}
    xs = np.asarray(traj.get("x_m", []), dtype=np.float64)
    ys = np.asarray(traj.get("y_m", []), dtype=np.float64)
    states = list(traj.get("state", []))
    if xs.size == 0 or xs.shape != ys.shape:
        raise ReportError("the report holds no trajectory to plot (no vehicle state was recorded)")
    if len(states) != xs.size:
        states = (states + ["INIT"] * xs.size)[:xs.size]
    watchdog = list(traj.get("watchdog", []))
    if len(watchdog) == xs.size:
        # A watchdog override (blind hold, climb) matters more than the policy state it overrides.
        states = [f"watchdog {w}" if w in WATCHDOG_COLOURS and s not in ("INIT", "HANDOVER") else s
                  for s, w in zip(states, watchdog)]
    radius_m = float(report.get("safety_radius_m", SAFETY_RADIUS_M))
    final = report.get("final") or {"x_m": float(xs[-1]), "y_m": float(ys[-1])}
    end_x, end_y = float(final["x_m"]), float(final["y_m"])
    outcome = str(report.get("outcome") or "no outcome")

    box = _crop_box_m(xs, ys, world)
    crop, extent = _world_crop(world, box)
    crop, _ = with_people(world, crop, None, extent, report.get("sim_time_s"), px_per_m=2.0)
    # The map above, the altitude profile below: seen from above a descent shrinks to a dot.
    fig, (ax, ax_alt) = plt.subplots(2, 1, figsize=(8.5, 10.4), dpi=110, gridspec_kw={"height_ratios": [4.0, 1.25]})
    ax.imshow(crop, extent=extent, interpolation="bilinear")

    # One polyline per run of ticks in the same state (thousands of ticks, far fewer runs),
    # each step coloured by the state the controller was in at its start.
    pts = np.column_stack([xs, ys])
    segs, colours = [], []
    run_start = 0
    for i in range(1, len(pts)):
        if i == len(pts) - 1 or states[i] != states[run_start]:
            segs.append(pts[run_start:i + 1])
            colours.append(STATE_COLOURS.get(states[run_start], OTHER_STATE_COLOUR))
            run_start = i
    # A white casing under the path keeps it readable over a busy city image.
    casing = [patheffects.Stroke(linewidth=4.2, foreground="white", alpha=0.8), patheffects.Normal()]
    ax.add_collection(LineCollection(segs, colors=colours, linewidths=2.2, zorder=3, path_effects=casing))
    seen = list(dict.fromkeys(states))
    handles = [Line2D([], [], color=STATE_COLOURS.get(s, OTHER_STATE_COLOUR), lw=3, label=s) for s in seen]
    handles.append(Line2D([], [], marker="^", ls="", color="white", markeredgecolor="black", ms=11,
                          label=f"start ({report.get('start', {}).get('alt_m', float('nan')):.0f} m)"))
    handles.append(Line2D([], [], marker="X", ls="", color=OUTCOME_COLOURS.get(outcome, "black"),
                          markeredgecolor="white", ms=12, label=f"end: {outcome}"))
    ax.plot(xs[0], ys[0], marker="^", color="white", markeredgecolor="black", ms=13, zorder=5)
    ax.plot(*_marker_xy(end_x, end_y, extent), marker="X", color=OUTCOME_COLOURS.get(outcome, "black"), markeredgecolor="white",
            ms=14, zorder=5)
    # The footprint disk to scale: at this zoom it is a few pixels, hence the inset below.
    ax.add_patch(Circle((end_x, end_y), radius_m, fill=False, ec="yellow", lw=1.2, zorder=6))
    confirmed = report.get("confirmed")
    if confirmed is not None:
        # The ground the policy last confirmed, joined to the touchdown: how far from it it handed over.
        error = report.get("touchdown_error_m")
        ax.plot([confirmed["x_m"], end_x], [confirmed["y_m"], end_y], color="white", lw=1.2, ls=":", zorder=6)
        ax.plot(confirmed["x_m"], confirmed["y_m"], marker="o", ms=10, markerfacecolor="none", markeredgecolor="magenta",
                markeredgewidth=2.0, zorder=6)
        handles.append(Line2D([], [], marker="o", ls="", markerfacecolor="none", markeredgecolor="magenta", ms=10,
                              label="ground last confirmed" + (f" ({error:.1f} m away)" if error is not None else "")))
    handles += _close_looks(ax, xs, ys, list(traj.get("look", [])))
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    # Inset and legend go to the corners the path crosses least, so neither hides the flight.
    corners = _free_corners(xs, ys, (end_x, end_y), extent)
    if outcome in ("safe", "unsafe"):
        # Only a judged landing has a footprint worth zooming on.
        _footprint_inset(ax, world, end_x, end_y, radius_m, outcome, corners[0], t_s=report.get("sim_time_s"))
    ax.legend(handles=handles, loc=corners[1], fontsize=8, framealpha=0.85)

    perception = backend_label(str(report.get("backend", "")), bool(report.get("simulated", False)),
                               report.get("noise") if report.get("simulated") else None,
                               report.get("perception") if report.get("simulated") else None)
    final_alt = final.get("alt_m")
    subtitle = (f"policy {report.get('policy', '?')}, {perception}, {report.get('timing', '?')} timing; "
                f"{report.get('sim_time_s', 0.0):.1f} s sim, path {report.get('path_length_m', 0.0):.0f} m"
                + (f", final alt {final_alt:.1f} m" if isinstance(final_alt, (int, float)) else ""))
    subtitle = "\n".join(textwrap.wrap(subtitle, 100))  # a long policy or backend name is never cut off
    detail = str(report.get("detail", ""))
    detail = detail if len(detail) <= 90 else detail[:87] + "..."  # the full text is in report.json
    ax.set_title(f"{outcome.upper()}: {detail}\n{subtitle}", fontsize=10)
    _altitude_profile(ax_alt, traj, states, report)
    out_png = Path(out_png)
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)
    return out_png


def _altitude_profile(ax: Any, traj: Mapping[str, Any], states: Sequence[str], report: Mapping[str, Any]) -> None:
    """Altitude over sim time, coloured by the controller's state as the path is, with the hand-over line."""
    from matplotlib.collections import LineCollection

    ts = np.asarray(traj.get("t_s", []), dtype=np.float64)
    alts = np.asarray(traj.get("alt_m", []), dtype=np.float64)
    if ts.size < 2 or ts.shape != alts.shape:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no altitude profile recorded", ha="center", va="center", transform=ax.transAxes)
        return
    pts = np.column_stack([ts, alts])
    segs = [pts[i:i + 2] for i in range(len(pts) - 1)]
    colours = [STATE_COLOURS.get(s, OTHER_STATE_COLOUR) for s in list(states)[:len(segs)]]
    ax.add_collection(LineCollection(segs, colors=colours, linewidths=2.0))
    handover_m = float(report.get("handover_alt_m", HANDOVER_ALT_M))
    ax.axhline(handover_m, color="black", ls="--", lw=1.0)
    ax.text(ts[0], handover_m, f" hand-over {handover_m:g} m", va="bottom", fontsize=8)
    ax.set_xlim(ts[0], ts[-1] if ts[-1] > ts[0] else ts[0] + 1.0)
    ax.set_ylim(0.0, max(float(alts.max()), handover_m) * 1.1)
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel("altitude AGL (m)")
    ax.grid(alpha=0.3)


# Corner name -> the inset's [left, bottom] in axes fractions (the inset is 0.34 wide and high).
_CORNERS = {"lower right": (0.64, 0.02), "lower left": (0.02, 0.02), "upper right": (0.64, 0.64),
            "upper left": (0.02, 0.64)}


def _free_corners(xs: np.ndarray, ys: np.ndarray, end_xy: tuple[float, float], extent: Sequence[float]) -> list[str]:
    """Corners sorted by how much of the path (and the end point, weighted) they would cover."""
    fx = (xs - extent[0]) / max(extent[1] - extent[0], 1e-9)
    fy = (ys - extent[2]) / max(extent[3] - extent[2], 1e-9)
    ex = (end_xy[0] - extent[0]) / max(extent[1] - extent[0], 1e-9)
    ey = (end_xy[1] - extent[2]) / max(extent[3] - extent[2], 1e-9)
    cost = {}
    for name, (left, bottom) in _CORNERS.items():
        inside = (fx >= left) & (fx <= left + 0.34) & (fy >= bottom) & (fy <= bottom + 0.34)
        end_inside = left <= ex <= left + 0.34 and bottom <= ey <= bottom + 0.34
        cost[name] = int(inside.sum()) + (10 * len(xs) if end_inside else 0)
    return sorted(_CORNERS, key=lambda c: cost[c])  # stable: ties keep the order above


def with_people(world: Any, crop: np.ndarray, labels: np.ndarray | None, extent: Sequence[float],
                t_s: float | None, px_per_m: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """A map crop (and its labels) with the world's people and cars drawn where they were at t_s,
    upsampled first to at least px_per_m so a person is more than a speck; unchanged without them."""
    if getattr(world, "population", None) is None or t_s is None:
        return crop, labels
    h_px, w_px = crop.shape[:2]
    k_x, k_y = w_px / (extent[1] - extent[0]), h_px / (extent[3] - extent[2])
    scale = max(1, int(np.ceil(px_per_m / max(k_x, 1e-9))))
    # Integers at pixel centres of the upsampled crop (extent: left, right, bottom, top).
    to_px = np.array([[scale * k_x, 0.0, -0.5 - scale * k_x * extent[0]],
                      [0.0, -scale * k_y, scale * k_y * extent[3] - 0.5], [0.0, 0.0, 1.0]])
    crop = np.ascontiguousarray(np.repeat(np.repeat(crop, scale, 0), scale, 1))
    if labels is not None:
        labels = np.ascontiguousarray(np.repeat(np.repeat(labels, scale, 0), scale, 1))
    world.population.draw(crop, labels, to_px, float(t_s), baked_labels=False)  # the crop's labels hold those
    return crop, labels


def _footprint_inset(ax: Any, world: Any, x_m: float, y_m: float, radius_m: float, outcome: str,
                     corner: str = "lower right", t_s: float | None = None) -> None:
    """A zoom on the end point: the ground with its people and cars where they were at the hand-over
    (t_s, drawn at the zoom's resolution), unsafe classes tinted red, the footprint disk and the
    separation rings (no person within 3 m, no vehicle within 5 m)."""
    from matplotlib.patches import Circle

    half_m = max(4.0 * radius_m, 6.0, VEHICLE_SEPARATION_M + 1.0)
    box = (x_m - half_m, x_m + half_m, y_m - half_m, y_m + half_m)
    try:
        crop, extent = _world_crop(world, box)
    except ReportError:
        return  # ended outside the world: nothing to zoom on
    crop, labels = with_people(world, crop, _labels_crop(world, box), extent, t_s, px_per_m=8.0)
    ins = ax.inset_axes([*_CORNERS[corner], 0.34, 0.34])
    ins.imshow(crop, extent=extent, interpolation="nearest")
    if labels is not None and labels.shape == crop.shape[:2]:
        unsafe = ~world.safe_lut[labels]
        overlay = np.zeros(unsafe.shape + (4,), dtype=np.float32)
        overlay[unsafe] = (1.0, 0.0, 0.0, 0.35)
        ins.imshow(overlay, extent=extent, interpolation="nearest")
    ins.add_patch(Circle((x_m, y_m), radius_m, fill=False, ec=OUTCOME_COLOURS.get(outcome, "yellow"), lw=2.0))
    for sep_m in (PERSON_SEPARATION_M, VEHICLE_SEPARATION_M):
        ins.add_patch(Circle((x_m, y_m), sep_m, fill=False, ec="white", lw=0.8, ls="--"))
    ins.plot(x_m, y_m, marker="+", color="white", ms=8)
    # The requested box, not the crop: near the world's edge the zoom stays square and to scale.
    ins.set_xlim(box[0], box[1])
    ins.set_ylim(box[2], box[3])
    ins.set_xticks([])
    ins.set_yticks([])
    ins.set_title(f"zoom {2 * half_m:.0f} m: {2 * radius_m:g} m disk (red: unsafe),\nrings {PERSON_SEPARATION_M:g} / "
                  f"{VEHICLE_SEPARATION_M:g} m: people / vehicles", fontsize=7,
                  color="white", backgroundcolor="#000000a0")
    for spine in ins.spines.values():
        spine.set_edgecolor("yellow")
    # The zoomed box drawn on the map, with connectors: the inset reads as a zoom, not as a second map.
    ax.indicate_inset_zoom(ins, edgecolor="yellow", alpha=0.9)


# ---------------------------------------------------------------- the bench: paths.png


def _noise_text(noise: Any) -> str:
    return "1 (as calibrated)" if noise is None else f"x{noise:g}" if isinstance(noise, (int, float)) else str(noise)


def plot_bench_paths(world: Any, doc: Mapping[str, Any], tracks_dir: Path | str, out_png: Path | str,
                     max_starts: int = 4) -> Path | None:
    """Every policy's path from the same starts, one panel per start (the paper's figure of paths).

    `doc` is results.json; each episode's track is `tracks_dir/<policy>-<index:04d>.npy` with
    rows (t_s, x_m, y_m, alt_agl_m). Starts whose tracks are all missing are skipped. Returns
    None (and writes nothing) when no track exists at all.
    """
    from matplotlib.lines import Line2D

    plt = _pyplot()
    tracks_dir = Path(tracks_dir)
    episodes = list(doc.get("episodes", []))
    policies = list(dict.fromkeys(e["policy"] for e in episodes))
    by_start: dict[int, dict[str, tuple[dict, np.ndarray]]] = {}
    for e in sorted(episodes, key=lambda e: e.get("index", 0)):
        path = tracks_dir / f"{e['policy']}-{int(e.get('index', 0)):04d}.npy"
        if not path.exists():
            continue
        track = np.load(path).astype(np.float64)
        if track.ndim != 2 or track.shape[1] < 3 or len(track) == 0:
            log.warning("track %s has shape %s, skipped", path, track.shape)
            continue
        by_start.setdefault(int(e.get("index", 0)), {})[e["policy"]] = (e, track)
    chosen = sorted(by_start)[:max_starts]
    if not chosen:
        log.warning("no tracks in %s: no paths plot", tracks_dir)
        return None

    cols = 2 if len(chosen) > 1 else 1
    rows = math.ceil(len(chosen) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 6.0 * rows), dpi=100, squeeze=False)
    colour = {p: POLICY_COLOURS[i % len(POLICY_COLOURS)] for i, p in enumerate(policies)}
    for ax, index in zip(axes.flat, chosen):
        runs = by_start[index]
        xs = np.concatenate([t[:, 1] for _, t in runs.values()])
        ys = np.concatenate([t[:, 2] for _, t in runs.values()])
        crop, extent = _world_crop(world, _crop_box_m(xs, ys, world, margin_frac=0.15, min_half_m=20.0))
        ax.imshow(crop, extent=extent, interpolation="bilinear")
        handles = []
        for rank, pol in enumerate(policies):
            if pol not in runs:
                continue
            ep, track = runs[pol]
            # The first policy (the one under study) on top: a long wandering path of the
            # ablation must not bury it.
            top = 3 + len(policies) - rank
            ax.plot(track[:, 1], track[:, 2], color=colour[pol], lw=1.8, alpha=0.85, zorder=top)
            # The end: a disc in the policy's colour under an X in the outcome's, white-edged, so it
            # stands out on any ground and says both whose end it is and how it ended.
            end = _marker_xy(track[-1, 1], track[-1, 2], extent)  # off the map: at the panel's edge
            ax.plot(*end, marker="o", ms=17, color=colour[pol], markeredgecolor="white",
                    markeredgewidth=1.5, zorder=10 + top)
            ax.plot(*end, marker="X", ms=11, color=OUTCOME_COLOURS.get(ep["outcome"], "black"),
                    markeredgecolor="white", markeredgewidth=1.2, zorder=11 + top)
            # The ground the policy last confirmed (a ring in its colour) joined to the touchdown:
            # how far from the checked ground it handed over.
            confirmed = ep.get("confirmed")
            error = ep.get("touchdown_error_m")
            if confirmed is not None:
                ax.plot([confirmed["x_m"], track[-1, 1]], [confirmed["y_m"], track[-1, 2]], color="white", lw=1.2,
                        ls=":", zorder=12 + top)
                ax.plot(confirmed["x_m"], confirmed["y_m"], marker="o", ms=9, markerfacecolor="none",
                        markeredgecolor=colour[pol], markeredgewidth=2.0, zorder=12 + top)
            checked = f", {error:.1f} m from the confirmed spot" if error is not None else ""
            handles.append(Line2D([], [], color=colour[pol], lw=2, marker="o", ms=8, markeredgecolor="white",
                                  label=f"{pol}: {ep['outcome']}, {ep.get('sim_time_s', 0):.0f} s, "
                                        f"{ep.get('path_length_m', 0):.0f} m{checked}"))
        first = next(iter(runs.values()))[1]
        ax.plot(first[0, 1], first[0, 2], marker="^", ms=12, color="white", markeredgecolor="black", zorder=6)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_title(f"start {index} ({first[0, 1]:.0f}, {first[0, 2]:.0f}) m", fontsize=10)
        ax.set_xlabel("x east (m)", fontsize=8)
        ax.set_ylabel("y north (m)", fontsize=8)
        ax.legend(handles=handles, loc="upper left", fontsize=8, framealpha=0.85)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(chosen):]:
        ax.axis("off")
    config = doc.get("config", {})
    fig.suptitle(f"Paths from the same starts: {config.get('world', 'world')}, {config.get('timing', '?')} timing, "
                 f"simulated perception noise {_noise_text(config.get('noise', '?'))}\n"
                 "triangle = start; end = disc in the policy's colour with an X coloured by outcome (green safe, "
                 "red unsafe, orange timeout, grey out of world)", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.94))  # room for the two-line title above the panels
    out_png = Path(out_png)
    fig.savefig(out_png, bbox_inches="tight")  # axis labels are never cut off
    plt.close(fig)
    return out_png
