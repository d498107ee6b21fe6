"""The bench page's interval bars carry the success rate in their colour: 0/2 and 2/2 have intervals
of about the same width, and one colour for all made them read alike."""

from __future__ import annotations

import re
from pathlib import Path

from dovesei.bench.stats import wilson_interval
from dovesei.pictures.html import write_bench_page


def _summary(safe: int, n: int) -> dict:
    return {"episodes": n, "safe": safe, "success_rate": safe / n, "success_ci95": list(wilson_interval(safe, n)),
            "unsafe": n - safe, "timeout": 0, "out_of_world": 0, "error": 0, "mean_sim_time_s": None,
            "mean_path_length_m": None}


def _bar_rgb(row_html: str) -> tuple[int, int, int]:
    colour = re.search(r'<span class="ci"[^>]*><span style="[^"]*background:#([0-9a-f]{6})', row_html).group(1)
    return int(colour[0:2], 16), int(colour[2:4], 16), int(colour[4:6], 16)


def test_bars_of_zero_and_full_success_differ_in_colour(tmp_path: Path) -> None:
    doc = {"summary": {"none": _summary(0, 2), "half": _summary(1, 2), "all": _summary(2, 2)}}
    page = write_bench_page(tmp_path, doc).read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"<tr><td>(none|half|all)</td>.*?</tr>", page)}
    none, half, all_ = (_bar_rgb(rows[k]) for k in ("none", "half", "all"))
    assert none[0] > 2 * none[1]  # 0/2: red
    assert all_[1] > 2 * all_[0]  # 2/2: green
    assert half != none and half != all_
