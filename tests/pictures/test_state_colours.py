"""Every policy's states are told apart in the plots: each has its own colour, none the fallback."""

from __future__ import annotations

import pytest

from dovesei.controller.policies.clearance.machine import Phase
from dovesei.controller.policies.dovesei.policy import DoveseiState
from dovesei.pictures.plots import OTHER_STATE_COLOUR, STATE_COLOURS


@pytest.mark.parametrize("states", [[s.value for s in Phase], [s.value for s in DoveseiState]],
                         ids=["clearance", "dovesei"])
def test_each_state_of_a_policy_has_a_colour_of_its_own(states: list[str]) -> None:
    colours = [STATE_COLOURS.get(s, OTHER_STATE_COLOUR) for s in ["INIT", *states]]
    assert OTHER_STATE_COLOUR not in colours
    # HANDOVER and LANDED share one colour on purpose (the end of the chain); nothing else does.
    ends = {"HANDOVER", "LANDED"}
    rest = [c for s, c in zip(["INIT", *states], colours) if s not in ends]
    assert len(set(rest)) == len(rest)
