"""Test tiers share these: offline transformers, a free loopback port, paired Zenoh sessions, a tiny
CLIPSeg written once per session; and every run ends with what the suite cost (see "The suite's
cost" below)."""

from __future__ import annotations

import os
import resource
from collections.abc import Iterator

import pytest

# Nothing in the tests may reach for the network (a failed hub lookup hangs ~30 s).
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# One intra-op thread for torch (and the services the tests start, which inherit it): the README's
# `-n 2` already puts a test on each core, and two OpenMP threads per process on a loaded 2-core
# machine spin at their barriers: the tiny CLIPSeg took 1.33 s a frame with two, 0.12 s with one.
os.environ.setdefault("OMP_NUM_THREADS", "1")


from dovesei.shared.zconfig import free_port  # noqa: E402  (re-exported for the test tiers)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The `sitl` tier flies a real ArduCopter SITL (DOVESEI_SITL_DIR): never part of the default
    suite, only run when a -m expression names it (`pytest -m sitl`)."""
    if "sitl" in (config.getoption("markexpr") or ""):
        return
    kept = [item for item in items if item.get_closest_marker("sitl") is None]
    if len(kept) != len(items):
        config.hook.pytest_deselected(items=[item for item in items if item.get_closest_marker("sitl") is not None])
        items[:] = kept


@pytest.fixture(scope="session")
def tiny_clipseg_dir(tmp_path_factory: pytest.TempPathFactory):
    """A random-weight tiny CLIPSeg written once per session (per xdist worker) with save_pretrained;
    the tests that load it only read it (seed 0, so every module sees the same weights)."""
    from dovesei.testing.random_model import build_random_clipseg

    return build_random_clipseg(tmp_path_factory.mktemp("clipseg") / "tiny", size="tiny", seed=0)


@pytest.fixture
def zenoh_pair() -> Iterator[tuple[object, object]]:
    """Two in-process peers on loopback (multicast off): one listens, the other connects to it."""
    import zenoh

    from dovesei.shared.lifecycle import wait_until
    from dovesei.shared.zconfig import loopback_config

    port = free_port()
    a = zenoh.open(loopback_config(listen_port=port))
    b = zenoh.open(loopback_config(connect_ports=[port]))
    try:
        # Connected when each sees the other as a peer.
        assert wait_until(lambda: any(True for _ in a.info.peers_zid()), 10.0), "peers did not connect"
        yield a, b
    finally:
        b.close()
        a.close()


# ---------------------------------------------------------------- the suite's cost, shown every run
# The README's command must fit about 15 minutes on 2 cores. Every run ends with the tests that cost
# the most: wall seconds (setup + call + teardown) and CPU seconds (this process's threads and the
# children it waited for; unlike wall time it barely moves with the machine's load, which is high on
# shared machines). Nothing fails on time: a test past SLOW_TEST_CPU_S is named so its author makes
# it cheaper (shorter simulated flights, a shared fixture) before the suite outgrows its budget.
SLOW_TEST_CPU_S = 20.0
_CPU_AT_START = pytest.StashKey[float]()
_COSTS: dict[str, list[float]] = {}  # nodeid -> [wall s, CPU s], filled where reports arrive


def _cpu_s() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    item.stash[_CPU_AT_START] = _cpu_s()
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    outcome = yield
    if call.when == "teardown" and _CPU_AT_START in item.stash:
        # On the report, so it reaches the xdist controller with the rest of it.
        outcome.get_result().user_properties.append(("cpu_s", _cpu_s() - item.stash[_CPU_AT_START]))


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    cost = _COSTS.setdefault(report.nodeid, [0.0, 0.0])
    cost[0] += report.duration
    cost[1] += sum(value for name, value in report.user_properties if name == "cpu_s")
    # DOVESEI_TEST_COSTS=<file>: every test's cost as it finishes, for a census during a long run.
    if report.when == "teardown" and os.environ.get("DOVESEI_TEST_COSTS") and "PYTEST_XDIST_WORKER" not in os.environ:
        with open(os.environ["DOVESEI_TEST_COSTS"], "a", encoding="utf-8") as out:
            out.write(f"{cost[0]:.2f}\t{cost[1]:.2f}\t{report.nodeid}\n")


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    if not _COSTS or hasattr(config, "workerinput"):
        return
    tr = terminalreporter
    tr.section("suite cost (slowest tests; budget: the whole suite in ~15 min on 2 cores)")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    tr.write_line(f"{len(_COSTS)} tests: {sum(c[0] for c in _COSTS.values()):.0f} s of test wall time, "
                  f"{sum(c[1] for c in _COSTS.values()):.0f} CPU s; load average now {load} on {os.cpu_count()} cores")
    for nodeid, (wall_s, cpu_s) in sorted(_COSTS.items(), key=lambda kv: -kv[1][0])[:15]:
        tr.write_line(f"{wall_s:7.1f} s {cpu_s:7.1f} CPU s  {nodeid}")
    over = sorted((nodeid for nodeid, (_, cpu_s) in _COSTS.items() if cpu_s > SLOW_TEST_CPU_S),
                  key=lambda n: -_COSTS[n][1])
    if over:
        tr.write_line(f"{len(over)} tests over {SLOW_TEST_CPU_S:g} CPU s each (make them cheaper): "
                      + ", ".join(f"{n} ({_COSTS[n][1]:.0f})" for n in over), yellow=True)
