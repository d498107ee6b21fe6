"""Test tiers share these: offline transformers, a free loopback port, paired Zenoh sessions."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

# Nothing in the tests may reach for the network (a failed hub lookup hangs ~30 s).
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


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
