"""The bench report page: a small real bench writes report.html, which headless Chromium (Debian's
package) loads with no console errors; a screenshot is taken for a person to look at."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from dovesei.bench import main as bench_main

WORLD = "synthetic:size_m=400,seed=1"


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium is not installed (Debian: apt-get install -y chromium; .ci/run does it)")
    return exe


def _flags(profile: Path) -> list[str]:
    return ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}"]


@pytest.fixture(scope="module")
def bench_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bench") / "b"
    assert bench_main(["--world", WORLD, "--episodes", "2", "--policy", "dovesei,clearance", "--time-limit-s", "20",
                       "--start-alt-m", "40", "--jobs", "1", "--no-progress", "--out", str(out)]) == 0
    return out


def test_page_is_self_contained_with_the_table_and_the_paths(bench_folder: Path) -> None:
    page = (bench_folder / "report.html").read_text()
    doc = json.loads((bench_folder / "results.json").read_text())
    for pol, s in doc["summary"].items():
        assert f"<td>{pol}</td><td>{s['safe']}/{s['episodes']}</td>" in page
    assert "95 % CI" in page and "Success against the time limit" in page
    if (bench_folder / "paths.png").exists():
        assert "data:image/png;base64," in page
    assert "<script" not in page and "http://" not in page and "https://" not in page  # nothing external


def test_chromium_loads_the_page_without_console_errors(bench_folder: Path, tmp_path: Path) -> None:
    exe = _chromium()
    url = (bench_folder / "report.html").as_uri()
    env = {**os.environ, "HOME": str(tmp_path)}
    dom = subprocess.run([exe, *_flags(tmp_path / "p1"), "--enable-logging=stderr", "--v=0", "--dump-dom", url],
                         capture_output=True, text=True, timeout=120, env=env)
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert "<h1>" in dom.stdout and "Policies" in dom.stdout  # the browser parsed and rendered the body
    console = [line for line in dom.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    assert not console, console
    shot = tmp_path / "report.png"
    run = subprocess.run([exe, *_flags(tmp_path / "p2"), "--window-size=1200,1400", f"--screenshot={shot}", url],
                         capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0 and shot.stat().st_size > 10_000, run.stderr[-2000:]
    keep = os.environ.get("DOVESEI_KEEP_SCREENSHOT")
    if keep:
        shutil.copy(shot, keep)
