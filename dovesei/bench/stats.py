"""Bench statistics: counts per outcome, Wilson intervals, per-world tables, success vs time limit.

Everything here is a pure function of the episode records (dicts as in `results.json`), so a
finished bench, a resumed one and a sweep are summarised by the same code.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from dovesei.shared.timing import PAPER_TIME_LIMIT_S, timing
from dovesei.sim.judge import CANOPY_NEAR_M, SEARCH_RADIUS_M

OUTCOMES = ("safe", "unsafe", "timeout", "out_of_world", "error")
SUMMARY_KEYS = ("episodes", *OUTCOMES)
# The paper's limits on its own (wall) clock; each preset maps them onto sim seconds.
PAPER_LIMITS_S = (60.0, 300.0, 600.0, PAPER_TIME_LIMIT_S)
WILSON_Z_95 = 1.959963984540054
# How far the judge looks for people and vehicles (its SEARCH_RADIUS_M): nobody that close reads as this.
SEPARATION_SEARCH_M = SEARCH_RADIUS_M


def wilson_interval(successes: int, n: int, z: float = WILSON_Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95 % by default); (0, 1) when n == 0.

    Chosen over the normal approximation because bench counts are small and often 0 or n, where
    the normal interval collapses to a point.
    """
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def _counts(eps: list[dict]) -> dict:
    s: dict = {k: 0 for k in SUMMARY_KEYS}
    s["episodes"] = len(eps)
    for e in eps:
        s[e["outcome"]] += 1
    safe = [e for e in eps if e["outcome"] == "safe"]
    # The paper's means are over SUCCESSFUL episodes (Table I).
    s["mean_sim_time_s"] = round(float(np.mean([e["sim_time_s"] for e in safe])), 1) if safe else None
    s["mean_path_length_m"] = round(float(np.mean([e["path_length_m"] for e in safe])), 1) if safe else None
    s["mean_wall_time_s"] = round(float(np.mean([e["wall_time_s"] for e in eps])), 2) if eps else None
    # How far from the ground it last confirmed each episode handed over (policies that confirm a
    # spot; a record without one says null and is not counted as 0).
    errors = [e["touchdown_error_m"] for e in eps if e.get("touchdown_error_m") is not None]
    s["touchdown_error_episodes"] = len(errors)
    s["median_touchdown_error_m"] = round(float(np.median(errors)), 2) if errors else None
    s["max_touchdown_error_m"] = round(float(np.max(errors)), 2) if errors else None
    s.update(separation_counts(eps))
    s.update(canopy_counts(eps))
    lo, hi = wilson_interval(s["safe"], len(eps))
    s["success_rate"] = round(s["safe"] / len(eps), 4) if eps else None
    s["success_ci95"] = [round(lo, 4), round(hi, 4)]
    return s


def separation_counts(eps: list[dict]) -> dict:
    """Hand-overs the judge measured separations for, how many were too close to a person or a
    vehicle, and the nearest person's / vehicle's distance (median and min; nobody within the
    judge's search radius counts as that radius, so a median never hides the far ones)."""
    judged = [e for e in eps if e.get("separation_violated") is not None]
    out: dict = {"separation_judged": len(judged),
                 "separation_violations": sum(bool(e["separation_violated"]) for e in judged)}
    for what in ("person", "vehicle"):
        d = [SEPARATION_SEARCH_M if e.get(f"nearest_{what}_m") is None else e[f"nearest_{what}_m"] for e in judged]
        out[f"median_nearest_{what}_m"] = round(float(np.median(d)), 2) if d else None
        out[f"min_nearest_{what}_m"] = round(float(np.min(d)), 2) if d else None
    return out


def canopy_counts(eps: list[dict]) -> dict:
    """The unsafe landings on a class the labels lump with tree canopy (records with the judge's
    `canopy` figures, a disk at least partly on such a class) and, of them, how many had canopy the
    image shows in the disk or within CANOPY_NEAR_M, and the nearest crown's median distance (none
    within the judge's search radius counting as that radius). Empty for benches whose worlds lump
    nothing, so their summaries stay as they were."""
    judged = [e for e in eps if isinstance(e.get("canopy"), dict)]
    if not judged:
        return {}
    lumped = [e["canopy"] for e in judged if e["outcome"] == "unsafe" and e["canopy"]["lumped"] > 0]
    near = [SEARCH_RADIUS_M if f["nearest_m"] is None else f["nearest_m"] for f in lumped]
    return {"canopy_judged": len(judged), "canopy_unsafe": len(lumped),
            "canopy_unsafe_crown_in_disk": sum(f["in_disk"] > 0 for f in lumped),
            "canopy_unsafe_crown_near": sum(d < CANOPY_NEAR_M for d in near),
            "canopy_unsafe_median_crown_m": round(float(np.median(near)), 2) if near else None}


def canopy_table(summary: dict[str, dict]) -> list[str]:
    """Per policy, the `canopy_counts` of its landings (no lines when no record has them)."""
    pols = [p for p, s in summary.items() if "canopy_judged" in s]
    if not pols:
        return []
    lines = ["| policy | unsafe landings on the lumped class | canopy in the disk "
             f"| a crown within {CANOPY_NEAR_M:g} m | nearest crown median (m) |", "|---|---|---|---|---|"]
    for pol in pols:
        s = summary[pol]
        lines.append(f"| {pol} | {s['canopy_unsafe']}/{s['canopy_judged']} | {s['canopy_unsafe_crown_in_disk']} | "
                     f"{s['canopy_unsafe_crown_near']} | {_fmt(s['canopy_unsafe_median_crown_m'])} |")
    return lines


def separation_text(config: dict) -> str:
    """How the bench's judge counted separation (benches from before it did: not at all)."""
    if "separation_m" not in config:
        return "without separation from people and vehicles (a bench from before the judge counted it)"
    person_m, vehicle_m = config["separation_m"]
    rules = [f"no {what} within {m:g} m of the touchdown" for what, m in (("person", person_m), ("vehicle", vehicle_m))
             if m > 0]
    return ("and " + " and ".join(rules) if rules else "separation from people and vehicles off") + \
        " (separation violations: hand-overs that broke it; nearest person: its median / min distance at the " \
        f"judged hand-overs, nobody within {SEPARATION_SEARCH_M:g} m counting as {SEPARATION_SEARCH_M:g})"


def limits_for(timing_name: str, run_limit_s: float) -> list[tuple[float, float]]:
    """(paper seconds, sim seconds) of the paper's limit ladder that fit inside the run's limit."""
    scale = timing(timing_name).timer_scale
    return [(p, p * scale) for p in PAPER_LIMITS_S if p * scale <= run_limit_s + 1e-9]


def success_by_limit(eps: list[dict], limits: Sequence[tuple[float, float]]) -> dict[str, dict]:
    """Successes had each episode been cut at a shorter limit, from the same runs.

    Exact because nothing a policy does depends on the limit: the first L seconds of an episode
    are the same whatever the limit, so it counts as safe under L iff it landed safely by L.
    """
    out = {}
    for paper_s, sim_s in limits:
        k = sum(e["outcome"] == "safe" and e["sim_time_s"] <= sim_s + 1e-9 for e in eps)
        lo, hi = wilson_interval(k, len(eps))
        out[f"{paper_s:g}"] = {"limit_sim_s": round(sim_s, 3), "safe": k, "episodes": len(eps),
                               "success_ci95": [round(lo, 4), round(hi, 4)]}
    return out


def summarise(episodes: Iterable[dict], policies: Sequence[str], *, limits: Sequence[tuple[float, float]] = ()
              ) -> dict[str, dict]:
    """Per policy: counts per outcome, the paper's means, success rate with its Wilson interval,
    and (with `limits`) success against the time limit."""
    episodes = list(episodes)
    summary: dict[str, dict] = {}
    for pol in policies:
        eps = [e for e in episodes if e["policy"] == pol]
        s = _counts(eps)
        if limits:
            s["success_by_limit"] = success_by_limit(eps, limits)
        summary[pol] = s
    return summary


def summarise_by(episodes: Iterable[dict], keys: Sequence[str]) -> list[dict]:
    """One row per distinct combination of `keys` (in first-seen order) with its counts."""
    episodes = list(episodes)
    groups: dict[tuple, list[dict]] = {}
    for e in episodes:
        groups.setdefault(tuple(e.get(k) for k in keys), []).append(e)
    return [{**dict(zip(keys, g)), **_counts(eps)} for g, eps in groups.items()]


def _pct(lo_hi: Sequence[float]) -> str:
    return f"{100 * lo_hi[0]:.0f}-{100 * lo_hi[1]:.0f} %"


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def policy_table(summary: dict[str, dict]) -> list[str]:
    lines = ["| policy | success | 95 % CI | unsafe | timeout | out of world | error | avg. time (s) | avg. distance (m) "
             "| touchdown error median / max (m) | separation violations | nearest person median / min (m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for pol, s in summary.items():
        n = s["episodes"]
        lines.append(f"| {pol} | {s['safe']}/{n} | {_pct(s['success_ci95'])} | {s['unsafe']}/{n} | {s['timeout']}/{n} | "
                     f"{s['out_of_world']}/{n} | {s['error']}/{n} | {_fmt(s['mean_sim_time_s'])} | "
                     f"{_fmt(s['mean_path_length_m'])} | {_touchdown(s)} | {separation_cell(s)} | {nearest_cell(s)} |")
    return lines


def separation_cell(s: dict) -> str:
    """'violations/judged hand-overs' ('-' when none was judged)."""
    return f"{s['separation_violations']}/{s['separation_judged']}" if s.get("separation_judged") else "-"


def nearest_cell(s: dict, what: str = "person") -> str:
    """Median / min distance of the nearest person (or vehicle) at the judged hand-overs."""
    if not s.get("separation_judged"):
        return "-"
    fmt = (lambda v: f">= {v:.0f}" if v >= SEPARATION_SEARCH_M else f"{v:.1f}")
    return f"{fmt(s[f'median_nearest_{what}_m'])} / {fmt(s[f'min_nearest_{what}_m'])}"


def _touchdown(s: dict) -> str:
    """Median / max touchdown error and over how many hand-overs, or why there is none."""
    if not s.get("touchdown_error_episodes"):
        return "- (no confirmed spot)"
    return (f"{s['median_touchdown_error_m']:.1f} / {s['max_touchdown_error_m']:.1f} "
            f"({s['touchdown_error_episodes']} hand-overs)")


def rows_table(rows: list[dict], keys: Sequence[str]) -> list[str]:
    """A markdown table of `summarise_by` rows: the key columns, then success with its interval."""
    lines = ["| " + " | ".join(keys) + " | success | 95 % CI | unsafe | timeout | out of world | error "
             "| separation violations | nearest person median / min (m) |",
             "|" + "---|" * (len(keys) + 8)]
    for r in rows:
        n = r["episodes"]
        lines.append("| " + " | ".join(f"`{r[k]}`" if k == "world" else str(r[k]) for k in keys)
                     + f" | {r['safe']}/{n} | {_pct(r['success_ci95'])} | {r['unsafe']}/{n} | {r['timeout']}/{n} | "
                     f"{r['out_of_world']}/{n} | {r['error']}/{n} | {separation_cell(r)} | {nearest_cell(r)} |")
    return lines


def limit_table(summary: dict[str, dict]) -> list[str]:
    pols = [p for p, s in summary.items() if s.get("success_by_limit")]
    if not pols:
        return []
    limits = list(summary[pols[0]]["success_by_limit"].items())
    head = " | ".join(f"{paper} s ({v['limit_sim_s']:g} sim s)" for paper, v in limits)
    lines = ["| policy | " + head + " |", "|---|" + "---|" * len(limits)]
    for pol in pols:
        cells = [f"{v['safe']}/{v['episodes']} ({_pct(v['success_ci95'])})" for v in summary[pol]["success_by_limit"].values()]
        lines.append(f"| {pol} | " + " | ".join(cells) + " |")
    return lines
