"""What `dovesei up` was asked to do: its flags, the typed options built from them, and every check
that can be made before a process starts.

    argv --build_parser--> Namespace --options_from_args--> UpOptions (checked on construction)
         --preflight--> world, model directory, MAVLink URL, policy: one line naming the flag

A user error never reaches a child: `main` turns any `ConfigError` or `WorldError` from here into
one line on stderr and exit code 2, before the output folder exists.
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared import keys, validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.mavurl import FORMS as MAVLINK_FORMS
from dovesei.shared.mavurl import MavlinkEndpoint, check_serial_device, parse_mavlink_url
from dovesei.shared.mission import (
    HANDOVER_ALT_M, MIN_DESCENT_M, PERSON_SEPARATION_M, VEHICLE_SEPARATION_M, check_handover_below_start,
)
from dovesei.shared.timing import DEFAULT_TIMING, TIMING_NAMES, timing
from dovesei.controller.core import HANDOVER_ACTIONS
from dovesei.controller.gnss_denied import GNSS_DENIED_MODES
from dovesei.controller.mavlink.proto import load_signing_key
from dovesei.controller.policies.registry import policy_names
from dovesei.controller.policies.config_file import load_policy_config
from dovesei.flight_defaults import default_start_margin_m, default_timing
from dovesei.flight_defaults import starts as bench_starts
from dovesei.segmenter.simulated import DEFAULT_PROFILE, PROFILE_NAMES
from dovesei.sim.estimator import VEHICLE_PROFILE_NAMES, default_vehicle_profile
from dovesei.sim.service import parse_start as sim_parse_start
from dovesei.sim.sitl_truth import parse_truth_url
from dovesei.sim.starts import check_start_alt_m

DESCRIPTION = "`dovesei up`: fly one episode with the three services as separate OS processes on Zenoh."
SEGMENTERS = ("auto", "clipseg", "sim")
YAW_CONTROLS = ("rate", "autopilot")  # the controller's --yaw-control choices
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
SEED_MAX = 2**32 - 1  # numpy's SeedSequence takes any int >= 0; the services' seeds fit 32 bits

_HUB_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*$")


def check_model(model: str) -> str:
    """A CLIPSeg model is a local directory with config.json, or a Hub id `owner/name`."""
    path = Path(model).expanduser()
    if path.is_dir():
        if not (path / "config.json").is_file():
            raise ConfigError(f"--model {model!r}: the directory has no config.json (expected a saved CLIPSeg "
                              "model: config.json and model.safetensors or pytorch_model.bin)")
        if not any(path.glob("*.safetensors")) and not (path / "pytorch_model.bin").is_file():
            raise ConfigError(f"--model {model!r}: the directory has no weights (model.safetensors or "
                              "pytorch_model.bin)")
        return model
    looks_local = model.startswith((".", "/", "~")) or model.count("/") != 1 or path.exists()
    if looks_local or not _HUB_ID.match(model):
        raise ConfigError(f"--model {model!r}: no such directory and not a Hub id; give a local model "
                          "directory or a Hub id such as CIDAS/clipseg-rd64-refined")
    return model


@dataclass(frozen=True)
class UpOptions:
    """Everything `up` was asked to do (built from flags; tests may build it directly)."""

    world: str = "synthetic"
    segmenter: str = "auto"
    policy: str = "dovesei"
    policy_config: Path | None = None  # TOML file of the policy's constants (--policy-config)
    timing: str = DEFAULT_TIMING
    seed: int = 0
    noise: float | None = None  # None: the simulated perception's calibrated default
    perception: str = DEFAULT_PROFILE  # simulated perception profile (clean | realistic | harsh)
    # Simulated vehicle (ideal | realistic | harsh); None: the timing preset's default
    # (dovesei.sim.estimator.default_vehicle_profile). A real vehicle (--vehicle) is itself.
    vehicle_profile: str | None = None
    start: tuple[float, float, float] | None = None  # (x_m, y_m, alt_m); None: from start_seed
    start_seed: int | None = None  # None: --seed
    start_alt_m: float = 100.0
    # The controller hands over (and hands it to its policy) and the sim's judge judges here.
    handover_alt_m: float = HANDOVER_ALT_M
    # The sim's judge: no person / vehicle closer than these to the touchdown (0: that rule off).
    person_separation_m: float = PERSON_SEPARATION_M
    vehicle_separation_m: float = VEHICLE_SEPARATION_M
    # `clearance` looks at its spot at full resolution before committing (issue 24), as `bench` flies it.
    close_look: bool = True
    out: Path = Path("runs/up")
    # True for the default runs/up-<time>: `run` then claims a folder no other run has (adding -2, -3
    # when one started in the same second), so two runs never write into one folder.
    out_unique: bool = False
    realtime: bool = False
    connect: tuple[str, ...] = ()
    vehicle_url: str | None = None  # MAVLink URL of a real autopilot (--vehicle-url); None: simulated
    # ArduPilot SITL only: a SEPARATE SITL output (udpin:HOST:PORT) where the sim reads SIM_STATE, the
    # simulator's true pose, to render and judge at; None: frames follow the controller's estimate.
    sitl_truth: str | None = None
    takeoff: bool = False
    # What the controller does with a real autopilot (None: the controller's own default). Each is
    # refused without --vehicle-url: the simulated vehicle has no hand-over mode, heading control,
    # signing or system id, and a flag that silently does nothing is worse than an error.
    handover_action: str | None = None  # hold, land, precland or none
    yaw_control: str | None = None  # rate (hold the heading) or autopilot (WP_YAW_BEHAVIOR)
    signing_key: Path | None = None  # MAVLink 2 signing key file
    autopilot_system_id: int | None = None  # fly only the autopilot with this MAVLink system id
    gnss_denied: str | None = None  # off, external-nav or attitude (docs/GNSS-DENIED.md)
    time_limit_s: float = 1200.0
    video: bool = True
    record: bool = True  # recording.mcap in the report folder (dovesei.shared.recording)
    view: bool = False  # stream to a Rerun viewer on loopback (dovesei.view)
    rrd: Path | None = None  # also save the Rerun recording here
    model: str | None = None
    vehicle_id: str = "uav1"
    heatmap_wait_s: float | None = None
    heatmap_hold_after_s: float | None = None
    after_failure_s: float = 5.0
    startup_timeout_s: float = 120.0
    stall_s: float = 8.0  # wall seconds without a service's stream before it is reported hung
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        keys.check_vehicle_id(self.vehicle_id)
        validate.one_of("--segmenter", self.segmenter, SEGMENTERS)
        validate.one_of("--log-level", self.log_level, LOG_LEVELS)
        timing(self.timing)  # names the presets when unknown
        for flag, seed in (("--seed", self.seed), ("--start-seed", self.start_seed)):
            if seed is not None and not (isinstance(seed, int) and not isinstance(seed, bool)
                                         and 0 <= seed <= SEED_MAX):
                raise ConfigError(f"{flag} {seed!r}: a seed is an integer in 0..{SEED_MAX}")
        for flag, given in (("--takeoff", self.takeoff), ("--handover-action", self.handover_action is not None),
                            ("--yaw-control", self.yaw_control is not None),
                            ("--signing-key", self.signing_key is not None),
                            ("--autopilot-system-id", self.autopilot_system_id is not None),
                            ("--gnss-denied", self.gnss_denied is not None),
                            ("--sitl-truth", self.sitl_truth is not None)):
            if given and not self.vehicle_url:
                raise ConfigError(f"{flag} only applies with --vehicle-url (a real autopilot)")
        if self.sitl_truth is not None:
            parse_truth_url(self.sitl_truth)
        if self.vehicle_url:
            parse_mavlink_url(self.vehicle_url)
            if self.timing != "real":
                # A real vehicle flies in true seconds: the reference preset's 60 s limit and 5 % timers
                # would end a real flight at ~30 m (measured against ArduPilot SITL).
                raise ConfigError("--vehicle-url flies in true seconds: use --timing real (or leave --timing out)")
        if self.handover_action is not None:
            validate.one_of("--handover-action", self.handover_action, HANDOVER_ACTIONS)
        if self.yaw_control is not None:
            validate.one_of("--yaw-control", self.yaw_control, YAW_CONTROLS)
        if self.gnss_denied is not None:
            validate.one_of("--gnss-denied", self.gnss_denied, GNSS_DENIED_MODES)
        if self.signing_key is not None:
            try:
                load_signing_key(self.signing_key)  # read now: a missing key is a usage error, not a dead child
            except ConfigError as exc:
                raise ConfigError(f"--signing-key: {exc}") from None
        if self.autopilot_system_id is not None and not (
                isinstance(self.autopilot_system_id, int) and not isinstance(self.autopilot_system_id, bool)
                and 1 <= self.autopilot_system_id <= 255):
            raise ConfigError(f"--autopilot-system-id {self.autopilot_system_id!r}: a MAVLink system id is an "
                              "integer in 1..255")
        if self.vehicle_profile is not None:
            validate.one_of("--vehicle-profile", self.vehicle_profile, VEHICLE_PROFILE_NAMES)
        if self.start is not None:
            validate.finite_vector("--start", self.start, 3)
            check_start_alt_m("--start altitude", self.start[2])
        check_start_alt_m("--start-alt-m", self.start_alt_m)
        if self.policy_config is not None:
            load_policy_config(self.policy, self.policy_config, self.timing)  # one line naming the file and key
        check_handover_below_start(self.handover_alt_m, self.start[2] if self.start is not None else self.start_alt_m)
        validate.non_negative("--person-separation-m", self.person_separation_m)
        validate.non_negative("--vehicle-separation-m", self.vehicle_separation_m)
        for flag, value in (("--heatmap-wait-s", self.heatmap_wait_s),
                            ("--heatmap-hold-after-s", self.heatmap_hold_after_s)):
            if value is not None:
                validate.positive(flag, value)
        validate.positive("--time-limit-s", self.time_limit_s)
        validate.positive("--stall-s", self.stall_s)
        validate.positive("startup_timeout_s", self.startup_timeout_s)
        if self.noise is not None:
            validate.non_negative("--noise", self.noise)
        validate.one_of("--perception", self.perception, PROFILE_NAMES)
        validate.non_negative("--after-failure-s", self.after_failure_s)
        if self.model is not None:
            if self.segmenter == "sim":
                raise ConfigError("--model only applies to a model segmenter (--segmenter auto or clipseg)")
            check_model(self.model)

    @property
    def sim_vehicle_profile(self) -> str:
        """The vehicle profile the sim flies: the one asked for, else the timing preset's default."""
        return default_vehicle_profile(self.timing) if self.vehicle_profile is None else self.vehicle_profile

    @property
    def lockstep(self) -> bool:
        # A real autopilot cannot wait for anyone: real time whenever one flies.
        return not self.realtime and not self.vehicle_url


def parse_start(text: str) -> tuple[float, float, float | None]:
    """`X,Y` or `X,Y,ALT` in world metres (x east, y north); ALT None when not given (--start-alt-m then).

    The sim's own parser reads it, so `up` and the sim accept exactly the same forms.
    """
    try:
        x_m, y_m, alt_m = sim_parse_start(text)
    except ValueError as exc:
        raise ConfigError(f"--start {text!r}: {exc}") from None
    return x_m, y_m, (alt_m if text.count(",") == 2 else None)


def resolve_start(world: Any, options: UpOptions) -> tuple[float, float, float]:
    """The start `up` hands the sim explicitly, so it also knows where the local frame's origin is.

    Without --start it is the start 0 of `dovesei bench --policy P` for the same seed and start
    altitude (the same margin, fitted to the world the same way: `dovesei.flight_defaults`).
    """
    if options.start is not None:
        x_m, y_m, alt_m = options.start
        if not world.contains(x_m, y_m):
            raise ConfigError(f"--start {x_m:g},{y_m:g} lies outside the world "
                              f"({world.width_m:.0f} x {world.height_m:.0f} m, x east, y north)")
        return float(x_m), float(y_m), float(alt_m)
    home = getattr(world, "home_xy_m", None)
    if home is not None:  # a preset built around one start (paper-paris): fly from it, as the paper did
        return float(home[0]), float(home[1]), float(options.start_alt_m)
    seed = options.seed if options.start_seed is None else options.start_seed
    st = bench_starts(world, 1, seed, alt_m=options.start_alt_m, margin_m=default_start_margin_m([options.policy]))[0]
    return st.x_m, st.y_m, st.alt_m


def check_policy(name: str) -> None:
    validate.one_of("--policy", name, policy_names())


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dovesei up", description=DESCRIPTION,
                                epilog="exit codes: 0 landed safely, 3 the episode ran but ended unsafe, timed out "
                                       "or left the world, 1 an error (a service died or hung), 2 bad usage, "
                                       "130 interrupted",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default="synthetic", help="synthetic[:seed=N,size_m=X,...] or a world folder")
    p.add_argument("--segmenter", default="auto", choices=SEGMENTERS,
                   help="auto: CLIPSeg when its weights load locally, else the simulated perception")
    p.add_argument("--model", help="CLIPSeg Hub id or local directory (default: the segmenter's)")
    p.add_argument("--policy", default="dovesei", help=f"landing policy: {', '.join(policy_names())}")
    p.add_argument("--policy-config", type=Path, metavar="FILE",
                   help="TOML file of the policy's constants, any subset (`dovesei policy-config --defaults POLICY` "
                        "prints them all); recorded in the report")
    p.add_argument("--timing", choices=TIMING_NAMES,
                   help=f"timing preset (default: {DEFAULT_TIMING}; real with --vehicle-url or --policy clearance, as `dovesei bench`)")
    p.add_argument("--seed", type=int, default=0, help="seed of the perception noise and of the start")
    p.add_argument("--perception", default=DEFAULT_PROFILE, choices=PROFILE_NAMES,
                   help=f"simulated perception profile (default: {DEFAULT_PROFILE}); a test instrument")
    p.add_argument("--noise", type=float, help="error scale within the perception profile (default: 1)")
    p.add_argument("--vehicle-profile", choices=VEHICLE_PROFILE_NAMES,
                   help="simulated vehicle: ideal (reports the truth, a gimbal), realistic (an optical-flow EKF "
                        "without GNSS, a body-fixed camera, ArduCopter's limits) or harsh (default: "
                        f"{default_vehicle_profile('real')} with real timing, {default_vehicle_profile('reference')} "
                        "with reference timing); ignored with --vehicle")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--start", metavar="X,Y[,ALT]", help="start position in world metres (x east, y north)")
    where.add_argument("--start-seed", type=int, help="draw the start like the bench's start 0 with this seed")
    p.add_argument("--start-alt-m", type=float, default=100.0,
                   help="start altitude when --start gives none (25-200 m; a flow-navigating ArduCopter holds 48-69 m)")
    p.add_argument("--handover-alt-m", type=float, default=HANDOVER_ALT_M,
                   help=f"hand-over altitude: the controller and its policy hand over, and the sim judges, here "
                        f"(default: {HANDOVER_ALT_M:g} m; at least {MIN_DESCENT_M:g} m below the start)")
    p.add_argument("--person-separation-m", type=float, default=PERSON_SEPARATION_M,
                   help="the judge calls a landing unsafe with a person closer than this to the touchdown "
                        f"(default: {PERSON_SEPARATION_M:g} m; 0 turns the rule off)")
    p.add_argument("--vehicle-separation-m", type=float, default=VEHICLE_SEPARATION_M,
                   help=f"... or a vehicle closer than this (default: {VEHICLE_SEPARATION_M:g} m; 0 turns the rule off)")
    p.add_argument("--no-close-look", dest="close_look", action="store_false",
                   help="clearance without its close looks (full-resolution crops of the spot before committing)")
    p.add_argument("--time-limit-s", type=float, default=None,
                   help="sim-time limit of the episode (default: the paper's 1200 s on the preset's clock, "
                        "as `dovesei bench`: 60 s with --timing reference, 1200 s with --timing real)")
    p.add_argument("--out", type=Path, help="report folder (default: runs/up-<timestamp>)")
    p.add_argument("--realtime", action="store_true", help="wall-clock rate instead of lockstep")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="use a Zenoh router at this endpoint instead of loopback peers (repeatable)")
    real = p.add_argument_group("a real autopilot (MAVLink; every flag here needs --vehicle-url)")
    real.add_argument("--vehicle-url", "--vehicle", metavar="URL", dest="vehicle_url",
                      help=f"fly a real autopilot over MAVLink ({MAVLINK_FORMS}); it must already fly in "
                           "GUIDED/OFFBOARD unless --takeoff (--vehicle is the same flag)")
    real.add_argument("--takeoff", action="store_true", help="arm and climb to the start altitude first")
    real.add_argument("--handover-action", choices=HANDOVER_ACTIONS,
                      help="at the hand-over altitude: hold (zero velocity), land (LAND mode), precland (LAND "
                           "with LANDING_TARGET on the chosen spot) or none (stop streaming) (default: hold)")
    real.add_argument("--yaw-control", choices=YAW_CONTROLS,
                      help="rate: hold the heading with a yaw rate; autopilot: velocity only, the autopilot "
                           "turns by WP_YAW_BEHAVIOR (default: rate)")
    real.add_argument("--signing-key", type=Path, metavar="FILE",
                      help="MAVLink 2 signing key file (32 raw bytes, 64 hex digits or a passphrase line); with "
                           "--autopilot-system-id it keeps a spoofer off the link")
    real.add_argument("--autopilot-system-id", type=int, metavar="ID",
                      help="fly only the autopilot with this MAVLink system id (1..255; default: the first heard)")
    real.add_argument("--gnss-denied", choices=GNSS_DENIED_MODES,
                      help="when the autopilot loses GNSS: external-nav (the camera's velocity to its EKF), "
                           "attitude (GUIDED_NOGPS, dovesei's own velocity loop) or off (report and hold; the "
                           "default); autopilot parameters in docs/GNSS-DENIED.md")
    real.add_argument("--sitl-truth", metavar="URL",
                      help="ArduPilot SITL: the camera renders and the judge judges at the simulator's TRUE pose "
                           "(SIM_STATE), read on a SEPARATE SITL output (udpin:HOST:PORT, e.g. udpin:127.0.0.1:14552 "
                           "for SITL's --serial2 udpclient:127.0.0.1:14552), never the controller's link; the policy "
                           "still sees only the autopilot's estimate")
    p.add_argument("--video", action=argparse.BooleanOptionalAction, default=True, help="write episode.mp4")
    p.add_argument("--record", action=argparse.BooleanOptionalAction, default=True,
                   help="record the flight to recording.mcap (replay with `dovesei replay`)")
    p.add_argument("--view", action="store_true", help="live view in Rerun (viewer on loopback; extra 'view')")
    p.add_argument("--rrd", type=Path, metavar="PATH", help="save a Rerun recording (.rrd) of the flight here")
    p.add_argument("--vehicle-id", default="uav1", help="vehicle id in the Zenoh keys (default: uav1)")
    p.add_argument("--heatmap-wait-s", type=float,
                   help="controller, lockstep: wall seconds to wait for a due heatmap (default: the controller's)")
    p.add_argument("--heatmap-hold-after-s", type=float,
                   help="controller watchdog: hold when the heatmap is older than this (default: the controller's)")
    p.add_argument("--after-failure-s", type=float, default=5.0,
                   help="after a service dies or hangs, keep recording this long before stopping the others")
    p.add_argument("--stall-s", type=float, default=8.0,
                   help="report a service as hung when its stream is silent this many wall seconds "
                        "(one still using CPU through the silence, slow on a loaded host, gets 6 times this)")
    p.add_argument("--log-level", default="INFO", choices=LOG_LEVELS)
    return p


def options_from_args(args: argparse.Namespace) -> UpOptions:
    start = None
    if args.start:
        x_m, y_m, alt_m = parse_start(args.start)
        start = (x_m, y_m, args.start_alt_m if alt_m is None else alt_m)
    timing_name = args.timing or default_timing([args.policy], real_vehicle=bool(args.vehicle_url))
    out = args.out or Path("runs") / f"up-{datetime.now().strftime('%Y%m%d-%H%M%S')}"  # claimed unique in `run`
    limit_s = timing(timing_name).time_limit_s if args.time_limit_s is None else args.time_limit_s
    return UpOptions(world=args.world, segmenter=args.segmenter, policy=args.policy, policy_config=args.policy_config,
                     timing=timing_name,
                     seed=args.seed, noise=args.noise, perception=args.perception, vehicle_profile=args.vehicle_profile,
                     start=start, start_seed=args.start_seed,
                     start_alt_m=args.start_alt_m, handover_alt_m=args.handover_alt_m, close_look=args.close_look,
                     person_separation_m=args.person_separation_m, vehicle_separation_m=args.vehicle_separation_m, out=out, out_unique=args.out is None, realtime=args.realtime,
                     connect=tuple(args.connect), vehicle_url=args.vehicle_url, sitl_truth=args.sitl_truth,
                     takeoff=args.takeoff, handover_action=args.handover_action,
                     yaw_control=args.yaw_control, signing_key=args.signing_key,
                     autopilot_system_id=args.autopilot_system_id, gnss_denied=args.gnss_denied,
                     time_limit_s=limit_s, video=args.video,
                     record=args.record, view=args.view, rrd=args.rrd,
                     model=args.model, vehicle_id=args.vehicle_id, heatmap_wait_s=args.heatmap_wait_s,
                     heatmap_hold_after_s=args.heatmap_hold_after_s, after_failure_s=args.after_failure_s,
                     stall_s=args.stall_s, log_level=args.log_level)
