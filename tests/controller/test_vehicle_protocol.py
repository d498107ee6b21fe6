"""The `Vehicle` protocol: both vehicles declare every member, and the loop never probes for one."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from dovesei.controller.mavlink.takeoff import TakeoffLink
from dovesei.controller.mavlink.vehicle import MavlinkVehicle
from dovesei.controller.service import ZenohVehicle
from dovesei.controller.vehicle import Vehicle

CONTROLLER = Path(__file__).resolve().parents[2] / "services" / "controller"


def _members(protocol: type) -> set[str]:
    declared = set(getattr(protocol, "__annotations__", {}))
    declared |= {n for n, v in vars(protocol).items() if not n.startswith("_") and (callable(v) or isinstance(v, property))}
    return declared


@pytest.mark.parametrize("cls", [ZenohVehicle, MavlinkVehicle], ids=lambda c: c.__name__)
def test_every_vehicle_declares_every_member_of_the_protocol(cls: type) -> None:
    members = _members(Vehicle)
    assert {"wakeup", "is_link_owner", "commands_during_handover", "rejected", "set_landing_target", "counters",
            "poll_state", "send", "hold", "handover", "close"} <= members
    # class attributes, properties and methods; `wakeup` of the sim is set per instance in __init__
    missing = {m for m in members if not hasattr(cls, m) and not (m == "wakeup" and "self.wakeup" in inspect.getsource(cls))}
    assert not missing, f"{cls.__name__} lacks {sorted(missing)}"


def test_mavlink_vehicle_offers_what_takeoff_uses() -> None:
    missing = {m for m in _members(TakeoffLink) if not hasattr(MavlinkVehicle, m)
               and f"self.{m}" not in inspect.getsource(MavlinkVehicle.__init__)}
    assert not missing, sorted(missing)


def _private_reach_ins(path: Path, names: tuple[str, ...]) -> list[str]:
    """`x._private` where x is one of `names` (the vehicle, under whatever the module calls it)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [f"{path.name}:{n.lineno} {n.value.id}.{n.attr}" for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and n.attr.startswith("_") and not n.attr.startswith("__")
            and isinstance(n.value, ast.Name) and n.value.id in names]


def _probes(path: Path) -> list[str]:
    """getattr/hasattr on a vehicle."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [f"{path.name}:{n.lineno}" for n in ast.walk(tree)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in ("getattr", "hasattr")
            and n.args and "vehicle" in ast.unparse(n.args[0])]


def test_no_private_reach_ins_and_no_probing(tmp_path: Path) -> None:
    assert _private_reach_ins(CONTROLLER / "mavlink" / "takeoff.py", ("v", "vehicle")) == []
    assert _private_reach_ins(CONTROLLER / "service.py", ("vehicle",)) == []
    assert _probes(CONTROLLER / "service.py") == []
    # the checkers themselves see what they look for
    sample = tmp_path / "_probe_sample.py"
    sample.write_text("def f(v, vehicle):\n    v._lock\n    getattr(vehicle, 'x', None)\n", encoding="utf-8")
    assert _private_reach_ins(sample, ("v",)) == ["_probe_sample.py:2 v._lock"]
    assert _probes(sample) == ["_probe_sample.py:3"]
