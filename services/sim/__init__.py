"""Simulator service: worlds, downward camera, vehicle dynamics, judge."""
