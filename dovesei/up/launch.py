"""How `dovesei up` starts the services: each one's command line, environment and Zenoh wiring.

    UpOptions + start --child_configs--> each service's own typed config (SimServiceConfig, ...)
        + ports --child_commands--> {"sim": argv, ...} from each service's `to_argv` (one source of
                                    truth: the flags are the service's table, proved to parse back)
        --check_link_owners--> refuses two processes binding one MAVLink endpoint

A flag renamed in a service renames it here too; a value a service refuses fails in `preflight`,
before any process starts. The services talk only over Zenoh: peers on 127.0.0.1 with multicast
scouting off, each listening on its own free port and connecting to the others, or all clients of
a router given with --connect.
"""

from __future__ import annotations

import socket
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any
from pathlib import Path

from dovesei.controller import service as controller_service
from dovesei.controller.core import DEFAULT_VEHICLE_GEOFENCE_M, ControllerConfig
from dovesei.episode import fusion_for
from dovesei.segmenter import service as segmenter_service
from dovesei.segmenter.core import SegmenterConfig
from dovesei.segmenter.service import ServiceConfig as SegmenterServiceConfig
from dovesei.shared.cliconfig import PROCESS, ProcessOptions
from dovesei.shared.errors import ConfigError
from dovesei.sim import service as sim_service
from dovesei.sim.core import SimConfig
from dovesei.sim.service import SimServiceConfig
from dovesei.shared.mavurl import SCHEMES as MAVLINK_SCHEMES
from dovesei.shared.mavurl import MavlinkEndpoint, parse_mavlink_url
from dovesei.up.options import UpOptions

SERVICES = ("sim", "segmenter", "controller")  # start order: the sim waits for the other two
MODULES = {"sim": "dovesei.sim.service", "segmenter": "dovesei.segmenter.service",
           "controller": "dovesei.controller.service"}


def zenoh_flags(name: str, ports: Mapping[str, int], connect: Sequence[str]) -> list[str]:
    """Peer-to-peer on loopback (each listens, connects to every other), or clients of a router."""
    if connect:
        return ["--mode", "client", *[a for ep in connect for a in ("--connect", ep)]]
    flags = ["--mode", "peer", "--no-multicast-scouting", "--listen", f"tcp/127.0.0.1:{ports[name]}"]
    for other, port in ports.items():
        if other != name:
            flags += ["--connect", f"tcp/127.0.0.1:{port}"]
    return flags


@dataclass(frozen=True)
class ChildConfigs:
    """The typed config of each service, as the service itself will parse it from its argv."""

    sim: SimServiceConfig
    segmenter: SegmenterServiceConfig
    controller: ControllerConfig

    @property
    def noise(self) -> float:
        """The simulated perception's noise scale the segmenter runs with (its calibrated default if unset)."""
        return self.segmenter.segmenter.sim_noise


# With --gnss-denied the sim is also the camera's visual odometry, at the camera service's rate
# (external-nav streams each view to the EKF; ArduPilot's VISO wants >= 10 Hz). Without
# --sitl-truth it renders only states with a position, so after a loss it goes quiet and the
# controller holds: the truth the views need after a loss comes from SITL.
GNSS_DENIED_ODOMETRY_HZ = 10.0
# Waiting for an autopilot's landing after the hand-over (watch.wait_for_landing): the hand-over
# altitude at this slowest descent (ArduCopter's LAND_SPEED is 0.5 m/s below LAND_ALT_LOW; a precision
# landing also moves over the spot first), plus a margin.
LANDING_MIN_DESCENT_M_S = 0.25
LANDING_MARGIN_S = 30.0


def landing_timeout_s(handover_alt_m: float) -> float:
    return LANDING_MARGIN_S + handover_alt_m / LANDING_MIN_DESCENT_M_S


# With --gnss-denied external-nav the autopilot's EKF flies on that odometry: after the judged
# hand-over the sim keeps it going while `up` waits for the landing (watch.wait_for_landing, which
# stops it); its own bound is that wait's plus this margin, so a sim left behind still ends.
ODOMETRY_TAIL_MARGIN_S = 30.0


def odometry_after_result_s(options: UpOptions) -> float:
    """How long the sim's odometry may outlive the episode: the landing wait's bound + a margin, with a
    real vehicle on --gnss-denied external-nav; 0 otherwise."""
    if not options.vehicle_url or options.gnss_denied != "external-nav":
        return 0.0
    return landing_timeout_s(float(options.handover_alt_m)) + ODOMETRY_TAIL_MARGIN_S

# A real vehicle flying a rendered world: the controller's geofence keeps it over the world, the
# radius the start's distance to the nearest edge, within these bounds (the smallest leaves a
# policy room to search; the largest is the controller's own default for any real vehicle).
WORLD_FENCE_MIN_M = 50.0


def world_geofence_m(world: Any, start: tuple[float, float, float]) -> float:
    """The geofence radius that keeps a real vehicle over the world it sees (x east, y north from 0)."""
    x_m, y_m, _ = start
    nearest_m = min(x_m, world.width_m - x_m, y_m, world.height_m - y_m)
    return float(min(max(nearest_m, WORLD_FENCE_MIN_M), DEFAULT_VEHICLE_GEOFENCE_M))


def child_configs(options: UpOptions, start: tuple[float, float, float], world: Any = None) -> ChildConfigs:
    """Each service's config for this run; a value a service refuses is a ConfigError naming it.

    With a real vehicle and the `world` it flies over, the controller's geofence keeps it over
    that world (the paper's RESTARTING move once flew 600 m and left a 400 m world)."""
    sim = SimServiceConfig(
        sim=SimConfig(vehicle_id=options.vehicle_id, timing=options.timing, time_limit_s=float(options.time_limit_s),
                      seed=options.seed, vehicle_profile=options.sim_vehicle_profile,
                      handover_alt_m=float(options.handover_alt_m),
                      person_separation_m=float(options.person_separation_m),
                      vehicle_separation_m=float(options.vehicle_separation_m),
                      odometry_rate_hz=GNSS_DENIED_ODOMETRY_HZ if options.gnss_denied not in (None, "off") else 0.0),
        world=options.world, start_xy_alt_m=tuple(float(v) for v in start), lockstep=options.lockstep,
        # Camera mode: the sim renders at the autopilot's state, which the controller (the one owner
        # of the MAVLink link) publishes on the state key; against SITL with --sitl-truth it renders
        # at SITL's true pose, read on a separate SITL output (never the autopilot's link).
        external_pose=bool(options.vehicle_url), sitl_truth=options.sitl_truth, wait_for=("segmenter", "controller"),
        odometry_after_result_s=odometry_after_result_s(options))
    perception: dict[str, object] = {"backend": options.segmenter, "sim_seed": options.seed,
                                     "sim_profile": options.perception}
    fusion = fusion_for(options.policy)  # the paper's policies fly the reference's fusion, as in bench
    if fusion is not None:
        perception["fusion"] = fusion
    if options.noise is not None:
        perception["sim_noise"] = float(options.noise)
    if options.model:
        perception["model"] = options.model
    segmenter = SegmenterServiceConfig(segmenter=SegmenterConfig(**perception), vehicle_id=options.vehicle_id,
                                       lockstep=options.lockstep)
    steering: dict[str, object] = {}
    if options.heatmap_wait_s is not None:
        steering["lockstep_heatmap_wait_s"] = float(options.heatmap_wait_s)
    if options.heatmap_hold_after_s is not None:
        steering["heatmap_hold_after_s"] = float(options.heatmap_hold_after_s)
    if options.takeoff:
        # The controller, the link's one owner, arms and climbs to the start before it steers.
        steering["takeoff_alt_m"] = float(start[2])
    if options.vehicle_url and world is not None:
        steering["geofence_radius_m"] = world_geofence_m(world, start)
    # The real autopilot's flags: each reaches the controller only when given (its defaults otherwise).
    for field, value in (("handover_action", options.handover_action),
                         ("mavlink_yaw_control", options.yaw_control),
                         ("mavlink_signing_key_file", None if options.signing_key is None else str(options.signing_key)),
                         ("mavlink_system_id", options.autopilot_system_id),
                         ("gnss_denied", options.gnss_denied)):
        if value is not None:
            steering[field] = value
    controller = ControllerConfig(vehicle_id=options.vehicle_id, policy=options.policy, timing=options.timing,
                                  lockstep=options.lockstep, vehicle_url=options.vehicle_url or "zenoh",
                                  handover_alt_m=float(options.handover_alt_m), close_look=options.close_look,
                                  policy_config_file=(None if options.policy_config is None
                                                      else str(Path(options.policy_config).resolve())), **steering)
    return ChildConfigs(sim, segmenter, controller)


def child_commands(options: UpOptions, configs: ChildConfigs, ports: Mapping[str, int],
                   out: Path) -> dict[str, list[str]]:
    """The full argv of each service: interpreter, module, its config's flags, process and Zenoh flags.

    The flags come from each service's own `to_argv`, which proves they parse back to the config.
    """
    flags = {"sim": sim_service.to_argv(configs.sim), "segmenter": segmenter_service.to_argv(configs.segmenter),
             "controller": controller_service.to_argv(configs.controller)}
    return {name: [sys.executable, "-m", MODULES[name], *flags[name],
                   *PROCESS.to_argv(ProcessOptions(options.log_level, out / "stats" / f"{name}.json")),
                   *zenoh_flags(name, ports, options.connect)] for name in SERVICES}


def child_env(name: str, options: UpOptions) -> dict[str, str]:
    """Extra environment of a child: `auto` means weights found LOCALLY, so no Hub lookups."""
    if name == "segmenter" and options.segmenter == "auto":
        # Without this an offline host spends minutes in the Hub client's retries before falling back.
        return {"HF_HUB_OFFLINE": "1"}
    return {}


def mavlink_links(commands: Mapping[str, Sequence[str]]) -> dict[str, list[MavlinkEndpoint]]:
    """Every MAVLink URL found among the children's flag values, by child."""
    links: dict[str, list[MavlinkEndpoint]] = {}
    for name, argv in commands.items():
        for value in argv:
            if value.partition(":")[0] in MAVLINK_SCHEMES:
                links.setdefault(name, []).append(parse_mavlink_url(value))
    return links


def check_link_owners(commands: Mapping[str, Sequence[str]]) -> None:
    """Refuse two children opening one MAVLink endpoint as listeners.

    Linux hands every datagram of a shared UDP port to the socket bound last: against ArduPilot
    SITL the controller lost its link 2 s into the flight and the vehicle hovered until the time
    limit. Only the controller should ever open the link; this catches any regression.
    """
    owners: dict[tuple[str, int], str] = {}
    for name, endpoints in mavlink_links(commands).items():
        for ep in endpoints:
            if not ep.binds:
                continue
            other = owners.setdefault(ep.endpoint, name)
            if other != name:
                raise ConfigError(f"--vehicle-url {ep.url!r}: both {other} and {name} would bind {ep.host}:{ep.port}; "
                                  "only the controller may open the autopilot's link")


def check_endpoint_free(ep: MavlinkEndpoint, flag: str = "--vehicle") -> None:
    """A listening URL whose port another process on this host already holds cannot work: say so now."""
    if not ep.binds or ep.scheme == "serial":
        return
    kind = socket.SOCK_STREAM if ep.scheme == "tcpin" else socket.SOCK_DGRAM
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind((ep.host, ep.port))
        except OSError as exc:
            raise ConfigError(f"{flag} {ep.url!r}: cannot bind {ep.host}:{ep.port} ({exc.strerror}); another "
                              "process (a ground station, an earlier run) holds it") from None
