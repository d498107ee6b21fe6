"""The typed config <-> command line mechanism (dovesei.shared.cliconfig) and every service's table.

Round trip: for each service, a default config renders to no flags, and a config with every flag
changed renders to flags that the service's own parser turns back into an equal config. Bad
values exit 2 with one error line naming the flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dovesei.camera import service as camera_service
from dovesei.camera.service import CameraConfig
from dovesei.controller import service as controller_service
from dovesei.controller.core import ControllerConfig
from dovesei.segmenter import service as segmenter_service
from dovesei.segmenter.core import SegmenterConfig
from dovesei.segmenter.prompts import PromptSet
from dovesei.segmenter.service import ServiceConfig
from dovesei.segmenter.simulated import CALIBRATED_NOISE
from dovesei.shared import validate
from dovesei.shared.cliconfig import PROCESS, CommandLine, Flag, ProcessOptions, _build
from dovesei.shared.errors import ConfigError
from dovesei.shared.timing import DEFAULT_TIMING
from dovesei.sim import service as sim_service
from dovesei.sim.core import SimConfig
from dovesei.sim.dynamics import VehicleParams
from dovesei.sim.service import SimServiceConfig

# A config per service that changes every field that has a flag (the test below checks that).
NON_DEFAULT = {
    "sim": SimServiceConfig(
        sim=SimConfig(vehicle_id="uav-7", timing="real", frame_period_s=1.25, latency_s=0.1 + 0.2,
                      handover_alt_m=12.5, time_limit_s=77.7, seed=-3, attach_truth=False,
                      vehicle=VehicleParams(cmd_timeout_s=0.8), odometry_rate_hz=12.5, vehicle_profile="harsh",
                      odometry_width_px=176, external_nav=True,
                      person_separation_m=2.5, vehicle_separation_m=6.5),
        world="synthetic:seed=3,size_m=400", start_xy_alt_m=(120.0, 80.5, 61.0), lockstep=False, speed=4.5,
        jpeg_quality=80, external_pose=True, sitl_truth="udpin:127.0.0.1:14552", wait_for=("controller", "segmenter"),
        wait_timeout_s=2.5, odometry_after_result_s=40.0,
        cmd_timeout_s=0.75),
    "segmenter": ServiceConfig(
        segmenter=SegmenterConfig(
            backend="sim", model="models/clipseg-rd64-refined", device="cuda:1", dtype="bfloat16", compile=True,
            threads=3, fusion="dovesei", fusion_temperature=0.5, sim_profile="harsh", sim_noise=0.3, sim_seed=9,
            heatmap_dtype="float16",
            expected_size_px=(240, 320), max_side_px=2048,
            prompts=PromptSet(positive=["grass, \"soft\""], negative=["road", "car"], template="a photo of {}."),
            never=("people", "horse, cow")),
        vehicle_id="base", all_vehicles=True, lockstep=True, overload_report_s=2.5,
        variant="onnx-int8"),
    "controller": ControllerConfig(
        vehicle_id="uav3", policy="dovesei-nofocus", timing="real", lockstep=False, rate_hz=12.5, close_look=True,
        heatmap_hold_after_s=2.0, heatmap_climb_after_s=12.0, state_stale_after_s=0.8, climb_speed_m_s=1.5,
        search_alt_m=80.0, handover_alt_m=15.0, handover_action="land", vehicle_url="udpin:0.0.0.0:14550",
        mavlink_alt_source="rangefinder", mavlink_allow_mode_switch=True, mavlink_yaw_control="autopilot",
        lockstep_heatmap_wait_s=7.5, policy_dt_max_s=0.8, future_tolerance_s=0.6, mavlink_system_id=7,
        mavlink_max_horizontal_m_s=8.0, mavlink_max_up_m_s=2.0, mavlink_max_down_m_s=1.0,
        mavlink_signing_key_file="keys/uav3.key", mavlink_require_home=False, takeoff_alt_m=60.0,
        takeoff_ready_timeout_s=90.0, record_path="flights/uav3.mcap", geofence_radius_m=250.0,
        gnss_denied="attitude", ekf_source_set=3, external_nav_message="delta", odometry_min_quality=0.6, odometry_max_age_s=0.4,
        attitude_max_tilt_deg=12.0, camera_hfov_deg=58.5, nav_retreat_speed_m_s=2.5, nav_retreat_max_s=45.0,
        policy_config_file=str(Path(__file__).parent / "data" / "nofocus-policy.toml")),
    "camera": CameraConfig(source="rtsp://10.0.0.2/cam", vehicle_id="uav2", width_px=320, height_px=240,
                           hfov_deg=90.0, rotate_deg=180, rate_hz=5.0, jpeg_quality=85, stall_timeout_s=3.0,
                           state_timeout_s=0.5, loop_file=True, record_path="flights/cam.mcap", odometry_rate_hz=15.0,
                           odometry_width_px=256, crop_rate_hz=2.5),
}
MODULES = {"sim": sim_service, "segmenter": segmenter_service, "controller": controller_service,
           "camera": camera_service}
DEFAULTS = {"sim": SimServiceConfig(), "segmenter": ServiceConfig(), "controller": ControllerConfig(),
            "camera": CameraConfig(source="0")}


def parse_with_service_parser(name: str, argv: list[str]):
    module = MODULES[name]
    return module.config_from_args(module.build_parser().parse_args(argv))


@pytest.mark.parametrize("name", sorted(MODULES))
def test_default_config_round_trips(name: str) -> None:
    argv = MODULES[name].to_argv(DEFAULTS[name])
    assert argv == ([] if name != "camera" else ["--source", "0"])
    assert parse_with_service_parser(name, argv) == DEFAULTS[name]


@pytest.mark.parametrize("name", sorted(MODULES))
def test_non_default_config_round_trips_through_the_service_parser(name: str) -> None:
    config = NON_DEFAULT[name]
    argv = MODULES[name].to_argv(config)
    assert parse_with_service_parser(name, argv) == config
    # Every field with a flag was changed, so every flag (or its 'off' twin) is on the line.
    given = {a.split("=", 1)[0] for a in argv if a.startswith("--")}
    cli = MODULES[name].CLI
    derived = cli.derive({"vehicle_url": config.vehicle_url}) if cli.derive else {}
    for entry in cli.entries:
        names = {entry.flag.name, entry.flag.off} - {None}
        if entry.flag.group == "start" and entry.flag.name == "--start-seed":
            continue  # exclusive with --start: covered by the next test
        if entry.path in derived and derived[entry.path] == getattr(config, entry.path):
            continue  # follows from another flag (the controller's loop from its vehicle)
        assert names & given, f"{name}: {entry.flag.name} not exercised"


def test_start_seed_round_trips_and_excludes_start() -> None:
    config = SimServiceConfig(start_seed=11)
    assert sim_service.to_argv(config) == ["--start-seed", "11"]
    assert parse_with_service_parser("sim", ["--start-seed", "11"]) == config
    with pytest.raises(ConfigError, match="--start and --start-seed"):
        sim_service.to_argv(SimServiceConfig(start_xy_alt_m=(1.0, 2.0, 3.0), start_seed=4))


def test_a_value_that_starts_with_a_dash_survives() -> None:
    config = SimServiceConfig(sim=SimConfig(seed=-5), world="-odd-name")
    argv = sim_service.to_argv(config)
    assert "--seed=-5" in argv and "--world=-odd-name" in argv
    assert parse_with_service_parser("sim", argv) == config


def test_to_argv_refuses_what_no_flag_can_say() -> None:
    with pytest.raises(ConfigError, match=r"sim\.dt_s=0\.1 has no flag"):
        sim_service.to_argv(SimServiceConfig(sim=SimConfig(dt_s=0.1, frame_period_s=0.5)))
    with pytest.raises(ConfigError, match="climb_gain_per_s"):
        controller_service.to_argv(ControllerConfig(climb_gain_per_s=0.9))
    with pytest.raises(ConfigError, match="expected a SimServiceConfig"):
        sim_service.to_argv(ControllerConfig())


def test_one_owner_of_the_timing_and_perception_defaults() -> None:
    sim = parse_with_service_parser("sim", [])
    ctrl = parse_with_service_parser("controller", [])
    assert sim.sim.timing == ctrl.timing == DEFAULT_TIMING  # compose starts both without --timing
    assert parse_with_service_parser("segmenter", []).segmenter.sim_noise == CALIBRATED_NOISE
    # A MAVLink vehicle runs in real time on true seconds unless told otherwise, and says so back.
    real = parse_with_service_parser("controller", ["--vehicle-url", "udpin:0.0.0.0:14550"])
    assert (real.lockstep, real.timing) == (False, "real")
    assert controller_service.to_argv(real) == ["--vehicle-url", "udpin:0.0.0.0:14550"]
    # With the sim, the same values are not the defaults and are spelled out.
    sim_real = ControllerConfig(timing="real", lockstep=False)
    assert controller_service.to_argv(sim_real) == ["--timing", "real", "--realtime"]
    assert parse_with_service_parser("controller", ["--timing", "real", "--realtime"]) == sim_real


def test_process_options_round_trip(tmp_path: Path) -> None:
    options = ProcessOptions(log_level="DEBUG", stats_out=tmp_path / "stats" / "sim.json")
    argv = PROCESS.to_argv(options)
    assert argv == ["--log-level", "DEBUG", "--stats-out", str(tmp_path / "stats" / "sim.json")]
    args = sim_service.build_parser().parse_args(argv)
    assert PROCESS.from_args(args) == options and sim_service.config_from_args(args) == SimServiceConfig()
    assert PROCESS.from_args(sim_service.build_parser().parse_args([])) == ProcessOptions()


BAD = [
    ("sim", ["--speed", "0"], "--speed", "> 0"),
    ("sim", ["--speed", "fast"], "--speed", "not a number"),
    ("sim", ["--speed", "nan"], "--speed", "finite"),
    ("sim", ["--jpeg-quality", "101"], "--jpeg-quality", "1..100"),
    ("sim", ["--wait-for", "camera"], "--wait-for", "segmenter"),
    ("sim", ["--start", "1"], "--start", "X_M,Y_M"),
    ("sim", ["--start", "a,b"], "--start", "numbers"),
    ("sim", ["--start", "1,2", "--start-seed", "3"], "--start-seed", "not allowed with"),
    ("sim", ["--timing", "fast"], "--timing", "reference"),
    ("sim", ["--seed", "1.5"], "--seed", "not an integer"),
    ("sim", ["--vehicle-id", "a/b"], "--vehicle-id", "letters, digits"),
    ("segmenter", ["--noise", "5"], "--noise", "[0, 4]"),
    ("segmenter", ["--perception", "dreamy"], "--perception", "realistic"),
    ("segmenter", ["--frame-size", "352"], "--frame-size", "WIDTHxHEIGHT"),
    ("segmenter", ["--threads", "0"], "--threads", ">= 1"),
    ("segmenter", ["--prompts", "/nonexistent/prompts.json"], "--prompts", "cannot read"),
    ("segmenter", ["--prompts", '{"positive": ["x"], "negatives": []}'], "--prompts", "positive, negative"),
    ("segmenter", ["--vehicle", "uav2"], "--vehicle", "unrecognized"),  # no prefix expansion
    ("controller", ["--rate-hz", "-1"], "--rate-hz", "> 0"),
    ("controller", ["--policy", "nope"], "--policy", "dovesei"),
    ("controller", ["--vehicle", "udpin:0.0.0.0:14550"], "--vehicle", "unrecognized"),
    ("camera", ["--source", "0", "--rotate", "45"], "--rotate", "90"),
    ("camera", ["--source", "0", "--width", "8"], "--width", "16..4096"),
    ("camera", [], "--source", "required"),
]


@pytest.mark.parametrize(("name", "argv", "flag", "hint"), BAD, ids=[" ".join(b[1]) for b in BAD])
def test_a_bad_flag_exits_2_with_one_line_naming_it(name, argv, flag, hint, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        MODULES[name].build_parser().parse_args(argv)
    assert exc.value.code == 2
    errors = capsys.readouterr().err.splitlines()  # one line: no usage block above it
    assert len(errors) == 1 and "error:" in errors[0] and flag in errors[0] and hint in errors[0], errors
    assert "Traceback" not in errors[0]


def test_a_cross_field_problem_is_reported_by_main_as_a_usage_error(capsys) -> None:
    # Each value is fine alone; together they break "hold first, then climb".
    with pytest.raises(SystemExit) as exc:
        controller_service.main(["--heatmap-hold-after-s", "20", "--log-level", "ERROR"])
    assert exc.value.code == 2
    assert "heatmap_climb_after_s" in capsys.readouterr().err


def test_prompts_from_a_file_and_inline_are_the_same(tmp_path: Path) -> None:
    text = '{"positive": ["grass"], "negative": ["road"], "template": "a {}"}'
    (tmp_path / "p.json").write_text(text, encoding="utf-8")
    from_file = parse_with_service_parser("segmenter", ["--prompts", str(tmp_path / "p.json")])
    inline = parse_with_service_parser("segmenter", ["--prompts", text])
    assert from_file == inline and from_file.segmenter.prompts.positive == ("grass",)


# ------------------------------------------------------------------ the mechanism on its own


@dataclass(frozen=True)
class Inner:
    gain: float = 1.0
    tags: tuple[str, ...] = ()


@dataclass(frozen=True)
class Outer:
    name: str  # required: no default
    inner: Inner = field(default_factory=Inner)
    count: int | None = None
    fast: bool = True
    no_flag: float = 3.0


TOY = CommandLine(Outer, {
    "name": Flag("--name", "a name"),
    "inner.gain": Flag("--gain", "a gain", check=validate.positive),
    "inner.tags": Flag("--tags", "tags", choices=("a", "b", "c")),
    "count": Flag("--count", "a count"),
    "fast": Flag("--fast", "fast", off="--slow"),
})


def test_toy_round_trip_covers_nesting_optionals_switches_and_lists() -> None:
    config = Outer(name="x", inner=Inner(gain=0.1 + 0.2, tags=("c", "a")), count=7, fast=False)
    argv = TOY.to_argv(config)
    assert argv == ["--name", "x", "--gain", repr(0.1 + 0.2), "--tags", "c,a", "--count", "7", "--slow"]
    assert TOY.parse(argv) == config  # floats exactly: repr round-trips
    with pytest.raises(ConfigError, match="required"):
        TOY.parse([])
    with pytest.raises(ConfigError, match="--gain"):
        TOY.parse(["--name", "x", "--gain", "-1"])
    with pytest.raises(ConfigError, match="no_flag=4.0 has no flag"):
        TOY.to_argv(Outer(name="x", no_flag=4.0))


def test_a_table_naming_no_field_fails_when_built() -> None:
    with pytest.raises(ConfigError, match="no field 'gian'"):
        CommandLine(Outer, {"inner.gian": Flag("--gain")})
    with pytest.raises(ConfigError, match="declared twice"):
        CommandLine(Outer, {"name": Flag("--x"), "count": Flag("--x")})
    with pytest.raises(ConfigError, match="defaults to True"):
        CommandLine(Outer, {"fast": Flag("--fast")})  # could never say False


# ------------------------------------------------------------------ any number survives the trip

NUMBER_FIELDS = [(name, entry) for name in sorted(MODULES) for entry in MODULES[name].CLI.entries
                 if entry.kind in (float, int)]


@pytest.mark.parametrize(("name", "entry"), NUMBER_FIELDS, ids=[f"{n}:{e.flag.name}" for n, e in NUMBER_FIELDS])
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_any_accepted_number_round_trips_exactly(name, entry, data) -> None:
    if entry.kind is float:
        value = data.draw(st.floats(min_value=1e-6, max_value=1e6, allow_nan=False, allow_infinity=False))
    else:
        value = data.draw(st.integers(min_value=0, max_value=10_000))
    base = {"source": "0"} if name == "camera" else {}
    try:
        config = _build(MODULES[name].CLI.cls, {**base, entry.path: value})
        if entry.flag.check is not None:
            entry.flag.check(entry.flag.name, value)
    except ConfigError:
        return  # a value this field refuses (alone or with the defaults): nothing to render
    assert parse_with_service_parser(name, MODULES[name].to_argv(config)) == config
