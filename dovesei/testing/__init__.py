"""Test doubles that users and tests share: a fake MAVLink autopilot and random-weight CLIPSeg models.

Nothing under ``services/`` or ``shared/`` imports this package (a test walks the imports): the
product never depends on its own doubles.
"""
