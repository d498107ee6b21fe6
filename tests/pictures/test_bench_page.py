"""The bench report page: a small real bench writes report.html, which headless Chromium (Debian's
package) loads with no console errors; a screenshot is taken for a person to look at."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Callable, Mapping
from pathlib import Path

import pytest

from dovesei.bench import main as bench_main

WORLD = "synthetic:size_m=400,seed=1"


REQUIRE_BROWSER = "DOVESEI_REQUIRE_BROWSER"  # .ci/run sets it to 1: there a missing browser is a failure


def browser_verdict(which: Callable[[str], str | None], env: Mapping[str, str]) -> tuple[str, str]:
    """("run", executable), or ("skip" | "fail", why) when no Chromium is on PATH.

    The README's test command must pass on a machine without a browser, so the page test is
    skipped there; where the environment says the browser is required (.ci/run, which installs
    Chromium) its absence fails the run instead of hiding behind a skip.
    """
    exe = which("chromium") or which("chromium-browser")
    if exe is not None:
        return "run", exe
    if env.get(REQUIRE_BROWSER, "").strip() not in ("", "0"):
        return "fail", (f"chromium is not installed and {REQUIRE_BROWSER}={env[REQUIRE_BROWSER]} requires it "
                        "(Debian: apt-get install -y chromium; .ci/run does it)")
    return "skip", (f"chromium is not installed (Debian: apt-get install -y chromium); set {REQUIRE_BROWSER}=1 "
                    "to make this a failure")


def _chromium() -> str:
    verdict, text = browser_verdict(shutil.which, os.environ)
    if verdict == "fail":
        pytest.fail(text)
    if verdict == "skip":
        pytest.skip(text)
    return text


def test_a_missing_browser_skips_unless_the_environment_requires_it() -> None:
    missing: Callable[[str], str | None] = lambda name: None  # noqa: E731
    assert browser_verdict(missing, {})[0] == "skip"
    assert browser_verdict(missing, {REQUIRE_BROWSER: "0"})[0] == "skip"
    verdict, why = browser_verdict(missing, {REQUIRE_BROWSER: "1"})
    assert verdict == "fail" and REQUIRE_BROWSER in why
    found = {"chromium-browser": "/usr/bin/chromium-browser"}.get
    assert browser_verdict(found, {REQUIRE_BROWSER: "1"}) == ("run", "/usr/bin/chromium-browser")
    assert browser_verdict(found, {}) == ("run", "/usr/bin/chromium-browser")


def test_ci_requires_the_browser_for_the_readme_command() -> None:
    """.ci/run exports the requirement before it runs the README's command, and stops when the
    browser could not be installed (so the page test is never silently skipped in CI)."""
    script = (Path(__file__).resolve().parents[2] / ".ci" / "run").read_text(encoding="utf-8")
    export = script.find(f"export {REQUIRE_BROWSER}=1")
    assert export != -1, f".ci/run does not export {REQUIRE_BROWSER}=1"
    assert export < script.find('bash -c "$cmd"')
    assert "command -v chromium >/dev/null || {" in script  # a missing browser after install ends the run


def _flags(profile: Path) -> list[str]:
    return ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}"]


@pytest.fixture(scope="module")
def bench_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # The reference timing: its 4 s of sim time hold the paper's 60 s limit, so the page has
    # its success-against-the-limit table too (on the real clock that limit is 60 s of sim time).
    out = tmp_path_factory.mktemp("bench") / "b"
    assert bench_main(["--world", WORLD, "--episodes", "2", "--policy", "dovesei,clearance", "--time-limit-s", "4",
                       "--start-alt-m", "40", "--timing", "reference", "--jobs", "1", "--no-progress", "--out", str(out)]) == 0
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
