"""The bench report page: one self-contained HTML file (report.html) beside results.json.

    results.json's dict --write_bench_page--> report.html
        the settings line, the policy table with Wilson 95 % intervals (and a bar per interval),
        success against the time limit, per-world and per-variant rows, the paths pictures
        embedded as data: URIs, and a link to each episode's recording when the folder has one

Self-contained: no script, no external style or font, images inline, so the file can be mailed
or attached to an issue and opens the same anywhere. Only the standard library.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from dovesei.shared.mission import HANDOVER_ALT_M

_STYLE = """
body{font:14px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px auto;max-width:1100px;color:#222}
h1{font-size:22px;margin-bottom:4px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:8px 0}th,td{padding:4px 10px;border-bottom:1px solid #eee;text-align:right}
th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.ci{display:inline-block;width:120px;height:10px;background:#eee;position:relative;vertical-align:middle}
.ci span{position:absolute;top:0;height:10px}
.ci i{position:absolute;top:-2px;width:2px;height:14px;background:#111}
.note{color:#555;font-size:13px}img{max-width:100%;border:1px solid #ddd}
"""


def _e(value: Any) -> str:
    return html.escape(str(value))


def _pct(lo_hi: Sequence[float]) -> str:
    return f"{100 * lo_hi[0]:.0f}&ndash;{100 * lo_hi[1]:.0f} %"


def rate_colour(rate: float | None) -> str:
    """The bar's colour for a success rate: red (0 %) through yellow to green (100 %), grey for none.

    One colour for every bar made 0/2 read like 2/2: the wide intervals of small benches look alike,
    so the colour carries the point estimate.
    """
    if rate is None or not 0.0 <= rate <= 1.0:
        return "#9e9e9e"
    red, green = min(1.0, 2.0 - 2.0 * rate), min(1.0, 2.0 * rate)  # the video's P(safe) ramp
    return f"#{round(200 * red):02x}{round(170 * green):02x}30"


def _ci_bar(rate: float | None, lo_hi: Sequence[float]) -> str:
    """The interval as a bar on 0..100 % coloured by the point estimate, which is a tick."""
    lo, hi = 100 * lo_hi[0], 100 * lo_hi[1]
    tick = "" if rate is None else f'<i style="left:{100 * rate:.1f}%"></i>'
    return (f'<span class="ci" title="Wilson 95 % interval {lo:.0f}-{hi:.0f} %">'
            f'<span style="left:{lo:.1f}%;width:{max(hi - lo, 0.5):.1f}%;background:{rate_colour(rate)}"></span>'
            f'{tick}</span>')


def _fmt(v: float | None) -> str:
    return "&ndash;" if v is None else f"{v:.1f}"


def _policy_table(summary: Mapping[str, Mapping[str, Any]]) -> str:
    from dovesei.bench.stats import nearest_cell, separation_cell  # lazy: dovesei.bench imports this module
    rows = []
    for pol, s in summary.items():
        n = s["episodes"]
        rows.append(f"<tr><td>{_e(pol)}</td><td>{s['safe']}/{n}</td><td>{_pct(s['success_ci95'])}</td>"
                    f"<td>{_ci_bar(s.get('success_rate'), s['success_ci95'])}</td><td>{s['unsafe']}</td>"
                    f"<td>{s['timeout']}</td><td>{s['out_of_world']}</td><td>{s['error']}</td>"
                    f"<td>{_fmt(s['mean_sim_time_s'])}</td><td>{_fmt(s['mean_path_length_m'])}</td>"
                    f"<td>{_e(separation_cell(s))}</td><td>{_e(nearest_cell(s))}</td>"
                    f"<td>{_e(nearest_cell(s, 'vehicle'))}</td></tr>")
    return ("<table><tr><th>policy</th><th>success</th><th>95 % CI</th><th>interval</th><th>unsafe</th>"
            "<th>timeout</th><th>out of world</th><th>error</th><th>avg. time (sim s)</th><th>avg. distance (m)</th>"
            "<th>separation violations</th><th>nearest person median / min (m)</th>"
            "<th>nearest vehicle median / min (m)</th></tr>" + "".join(rows) + "</table>")


def _limit_table(summary: Mapping[str, Mapping[str, Any]]) -> str:
    pols = [p for p, s in summary.items() if s.get("success_by_limit")]
    if not pols:
        return ""
    limits = list(summary[pols[0]]["success_by_limit"].items())
    head = "".join(f"<th>{_e(paper)} s<br><span class='note'>({v['limit_sim_s']:g} sim s)</span></th>"
                   for paper, v in limits)
    rows = []
    for pol in pols:
        cells = "".join(f"<td>{v['safe']}/{v['episodes']} <span class='note'>({_pct(v['success_ci95'])})</span></td>"
                        for v in summary[pol]["success_by_limit"].values())
        rows.append(f"<tr><td>{_e(pol)}</td>{cells}</tr>")
    return (
        "<h2>Success against the time limit</h2><p class='note'>The same runs, cut at each limit: the paper's "
        "limits on its own clock and, below, on this preset's sim clock.</p>"
        f"<table><tr><th>policy</th>{head}</tr>{''.join(rows)}</table>")


def _rows_table(title: str, rows: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> str:
    if not rows:
        return ""
    from dovesei.bench.stats import nearest_cell, separation_cell  # lazy: dovesei.bench imports this module
    head = "".join(f"<th>{_e(k)}</th>" for k in keys)
    body = []
    for r in rows:
        n = r["episodes"]
        body.append("<tr>" + "".join(f"<td>{_e(r.get(k))}</td>" for k in keys)
                    + f"<td>{r['safe']}/{n}</td><td>{_pct(r['success_ci95'])}</td>"
                    f"<td>{_ci_bar(r.get('success_rate'), r['success_ci95'])}</td><td>{r['unsafe']}</td>"
                    f"<td>{r['timeout']}</td><td>{r['out_of_world']}</td><td>{_e(separation_cell(r))}</td>"
                    f"<td>{_e(nearest_cell(r))}</td></tr>")
    return (f"<h2>{_e(title)}</h2><table><tr>{head}<th>success</th><th>95 % CI</th><th>interval</th><th>unsafe</th>"
            f"<th>timeout</th><th>out of world</th><th>separation violations</th>"
            f"<th>nearest person median / min (m)</th></tr>{''.join(body)}</table>")


def _images(folder: Path) -> str:
    out = []
    for png in sorted(folder.glob("paths*.png")):
        data = base64.b64encode(png.read_bytes()).decode()
        out.append(f"<figure><img alt='{_e(png.name)}' src='data:image/png;base64,{data}'>"
                   f"<figcaption class='note'>{_e(png.name)}</figcaption></figure>")
    return "<h2>Paths</h2>" + "".join(out) if out else ""


def _episodes(folder: Path, episodes: Sequence[Mapping[str, Any]]) -> str:
    rows = []
    for e in episodes:
        rec = e.get("recording")
        link = (f"<a href='{_e(rec)}'>{_e(Path(rec).name)}</a>" if rec and (folder / rec).is_file() else "&ndash;")
        rows.append(f"<tr><td>{_e(e.get('policy'))}</td><td>{_e(e.get('index'))}</td><td>{_e(e.get('outcome'))}</td>"
                    f"<td>{_fmt(e.get('sim_time_s'))}</td><td>{_fmt(e.get('path_length_m'))}</td>"
                    f"<td>{_e(e.get('world', ''))}</td><td>{link}</td></tr>")
    return ("<h2>Episodes</h2><details><summary>every episode (" + str(len(episodes)) + ")</summary>"
            "<table><tr><th>policy</th><th>start</th><th>outcome</th><th>sim time (s)</th><th>path (m)</th>"
            "<th>world</th><th>recording</th></tr>" + "".join(rows) + "</table></details>")


def write_bench_page(folder: Path | str, doc: Mapping[str, Any], *, title: str = "dovesei bench") -> Path:
    """Write <folder>/report.html from a bench's results.json dict; returns its path."""
    from dovesei.bench.stats import separation_text  # lazy: dovesei.bench imports this module
    folder = Path(folder)
    config = doc.get("config", {})
    settings = ", ".join(f"{k} {_e(config[k])}" for k in ("world", "episodes", "seed", "start_alt_m", "time_limit_s",
                                                          "timing", "perception") if k in config)
    handover_m = float(config.get("handover_alt_m", HANDOVER_ALT_M))
    body = [
        f"<h1>{_e(title)}</h1><p class='note'>{settings}. Success = reaching the hand-over altitude "
        f"({handover_m:g} m) with the "
        f"footprint disk on safe classes, judged on the label map, {_e(separation_text(config))}. Intervals are "
        "Wilson 95 %; averages are over "
        "successful episodes, as in the paper's Table I.</p>",
        "<h2>Policies</h2>", _policy_table(doc.get("summary", {})),
        _limit_table(doc.get("summary", {})),
        _rows_table("Per world", doc.get("per_world") or [], ("world", "policy")),
        _rows_table("Per perception profile and prompt set", doc.get("per_variant") or [],
                    ("policy", "perception", "prompts")),
        _images(folder),
        _episodes(folder, doc.get("episodes", [])),
    ]
    page = ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>" + _e(title) + "</title>"
            "<meta name='viewport' content='width=device-width,initial-scale=1'>"
            f"<style>{_STYLE}</style></head><body>" + "".join(body) + "</body></html>\n")
    path = folder / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
