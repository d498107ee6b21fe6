"""Every landing policy by name: how to build it and what configures it.

    name --entry(name)--> PolicyEntry(config type, preset by timing name, build)
         --make_policy(name, config, speed limits, hand-over altitude)--> a Policy

The policies import only `base` (the contract); this module imports the policies, at the top, so
there is no cycle and no import hidden in a function. `config_file` (the `--policy-config` TOML)
reads the same entries, so a policy is declared once, here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from dovesei.controller.policies.base import Policy
from dovesei.controller.policies.clearance.closelook import CloseLookPolicy, close_look_config
from dovesei.controller.policies.clearance.config import ClearanceConfig, clearance_preset
from dovesei.controller.policies.clearance.policy import ClearancePolicy
from dovesei.controller.policies.dovesei.config import DoveseiConfig, timing_preset
from dovesei.controller.policies.dovesei.policy import DoveseiPolicy

# (horizontal, up, down) m/s: the largest velocities the vehicle flies (the MAVLink adapter's limits).
SpeedLimitsMS = tuple[float, float, float]


@dataclass(frozen=True)
class PolicyEntry:
    """One policy: its config type, the config under a timing preset, and its builder."""

    name: str
    config_type: type
    preset: Callable[[str], Any]  # timing preset name ("reference", "real") -> config
    build: Callable[[Any, SpeedLimitsMS | None, float | None], Policy]  # (config, limits, hand-over alt)


def _build_dovesei(config: Any, speed_limits_m_s: SpeedLimitsMS | None = None,
                   handover_alt_m: float | None = None) -> Policy:
    # The paper's policy stays faithful: it asks what the reference asks, the adapter clamps it.
    # It has no hand-over altitude of its own (it descends towards LANDED at 5 m): the controller's
    # watchdog stops it at the hand-over altitude, so `handover_alt_m` changes nothing inside it.
    return DoveseiPolicy(config, name="dovesei")


def _build_dovesei_nofocus(config: Any, speed_limits_m_s: SpeedLimitsMS | None = None,
                           handover_alt_m: float | None = None) -> Policy:
    return DoveseiPolicy(config, name="dovesei-nofocus", dynamic_focus=False)


def _build_clearance(config: Any, speed_limits_m_s: SpeedLimitsMS | None = None,
                     handover_alt_m: float | None = None) -> Policy:
    policy = ClearancePolicy(config)
    cfg = policy.config
    if handover_alt_m is not None and handover_alt_m != cfg.handover_alt_m:
        # The controller's hand-over altitude is the policy's: one declaring HANDOVER above the
        # controller's would be refused as a fault, one below it would never be asked to hand over.
        cfg = cfg.replace(handover_alt_m=float(handover_alt_m))
    if speed_limits_m_s is not None:
        # Ours asks only what the vehicle flies: a clamped command is a different command (a
        # descent asked at 4 m/s and flown at 1.5 m/s left its timers and odometry prior wrong).
        cfg = cfg.limited_to(*speed_limits_m_s)
    if cfg is not policy.config:
        policy.config = cfg
        policy.reset()
    return policy


POLICIES: Mapping[str, PolicyEntry] = MappingProxyType({e.name: e for e in (
    PolicyEntry("clearance", ClearanceConfig, clearance_preset, _build_clearance),
    PolicyEntry("dovesei", DoveseiConfig, timing_preset, _build_dovesei),
    PolicyEntry("dovesei-nofocus", DoveseiConfig, timing_preset, _build_dovesei_nofocus),
)})


def policy_names() -> list[str]:
    """Every name `make_policy` accepts."""
    return sorted(POLICIES)


def entry(name: str) -> PolicyEntry:
    """The registry's entry for `name`, or ValueError listing the known names."""
    try:
        return POLICIES[name]
    except KeyError:
        raise ValueError(f"unknown policy {name!r}; known: {', '.join(policy_names())}") from None


# The policies whose descent a close look gates (the paper's stays as published).
CLOSE_LOOK_POLICIES = ("clearance",)


def make_policy(name: str, config: Any = None, speed_limits_m_s: SpeedLimitsMS | None = None, *,
                handover_alt_m: float | None = None, close_look: bool = False) -> Policy:
    """Build the policy called `name`.

    `config` is policy-specific: for `dovesei*` a `DoveseiConfig`, a timing preset name
    ("reference" or "real") or None (the `real` preset); for `clearance` a `ClearanceConfig`, a
    timing preset name (it runs on true data-clock seconds under both) or None.
    `speed_limits_m_s` (horizontal, up, down), the vehicle's: `clearance` never asks for more;
    the `dovesei` policies stay faithful to the reference and are clamped by the adapter.
    `handover_alt_m`, the controller's (None: the config's own, dovesei.shared.mission's default):
    a policy with a hand-over altitude of its own (`clearance`) takes it; the paper's has none.
    `close_look`: `clearance` looks at its spot at full resolution before committing
    (`clearance/closelook.py`); the controller must then carry out its look requests.
    """
    policy = entry(name).build(config, speed_limits_m_s, handover_alt_m)
    if close_look and name in CLOSE_LOOK_POLICIES:
        policy = CloseLookPolicy(policy, close_look_config(policy.config.handover_alt_m))
    return policy
