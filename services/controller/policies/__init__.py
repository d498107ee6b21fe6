"""Landing policies: pure objects, heatmap and altitude in, command and status out."""

from dovesei.controller.policies.base import Decision, Observation, Policy, make_policy, policy_names

__all__ = ["Decision", "Observation", "Policy", "make_policy", "policy_names"]
