"""Every Zenoh key expression of the project, built in one place.

Per vehicle, under `dovesei/<vehicle>/`:

    camera    CameraFrame        sim or onboard camera -> segmenter
    state     VehicleState       sim or MAVLink adapter -> controller
    heatmap   SafetyHeatmap      segmenter -> controller
    cmd       VelocityCommand    controller -> sim or MAVLink adapter
    status    ControllerStatus   controller -> operators, reports
    prompts   PromptSetMsg       operator -> segmenter
    episode   EpisodeResult      sim judge -> `dovesei up`, bench
    odometry  VisualOdometry     onboard camera -> controller (visual velocity for the autopilot)
    segment   queryable: CameraFrame in, SafetyHeatmap out (request-reply segmentation);
              CropFrame in, CropHeatmap out (a close look, scored with the "never" set too)
    crop      queryable: CropRequest in, CropFrame out (answered onboard by the camera, or the sim)
    look      CropFrame + CropHeatmap  controller -> operators, reports (each close look it took)
    alive/<service>              liveliness tokens

A ground-station segmenter serving several vehicles subscribes to `dovesei/*/camera` and declares
its queryable on `dovesei/*/segment`; the vehicle id in the key tells whose frame it is.
"""

from __future__ import annotations

import re

from dovesei.shared.errors import ConfigError

ROOT = "dovesei"
ANY_VEHICLE = "*"
SERVICES = ("sim", "segmenter", "controller", "camera", "mavlink")
TOPICS = ("camera", "state", "heatmap", "cmd", "status", "prompts", "episode", "segment", "odometry", "crop", "look")
_VEHICLE_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_vehicle_id(vehicle: str) -> str:
    """A vehicle id is one key chunk: letters, digits, '_' or '-' (no '/', '*', '$', '?', '#')."""
    if not isinstance(vehicle, str) or not _VEHICLE_RE.match(vehicle):
        raise ConfigError(f"vehicle id {vehicle!r}: use 1-64 letters, digits, '_' or '-'")
    return vehicle


def _key(vehicle: str, topic: str) -> str:
    if vehicle != ANY_VEHICLE:
        check_vehicle_id(vehicle)
    return f"{ROOT}/{vehicle}/{topic}"


def camera(vehicle: str) -> str:
    return _key(vehicle, "camera")


def state(vehicle: str) -> str:
    return _key(vehicle, "state")


def heatmap(vehicle: str) -> str:
    return _key(vehicle, "heatmap")


def cmd(vehicle: str) -> str:
    return _key(vehicle, "cmd")


def status(vehicle: str) -> str:
    return _key(vehicle, "status")


def prompts(vehicle: str) -> str:
    return _key(vehicle, "prompts")


def episode(vehicle: str) -> str:
    return _key(vehicle, "episode")


def odometry(vehicle: str) -> str:
    return _key(vehicle, "odometry")


def segment(vehicle: str) -> str:
    return _key(vehicle, "segment")


def crop(vehicle: str) -> str:
    return _key(vehicle, "crop")


def look(vehicle: str) -> str:
    return _key(vehicle, "look")


def alive(vehicle: str, service: str) -> str:
    if service not in SERVICES and service != ANY_VEHICLE:
        raise ConfigError(f"service {service!r} is not one of {SERVICES}")
    return f"{_key(vehicle, 'alive')}/{service}"


def vehicle_of(key: str) -> str:
    """The vehicle id in a concrete key such as `dovesei/uav1/camera`."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise ConfigError(f"key {key!r} is not a dovesei key")
    return check_vehicle_id(parts[1])
