"""Keys are valid and scoped per vehicle; the Zenoh config helper honours its inputs; clocks."""

from __future__ import annotations

import json
import threading

import pytest
import zenoh

from dovesei.shared import keys
from dovesei.shared.clock import DataClock, WallClock
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import Stamp
from dovesei.shared.zconfig import zenoh_config

TOPIC_BUILDERS = [keys.camera, keys.state, keys.heatmap, keys.cmd, keys.status, keys.prompts, keys.episode, keys.segment]


@pytest.mark.parametrize("build", TOPIC_BUILDERS, ids=lambda f: f.__name__)
def test_keys_are_valid_and_carry_the_vehicle(build) -> None:
    key = build("uav-7")
    assert zenoh.KeyExpr(key) is not None
    assert keys.vehicle_of(key) == "uav-7"
    # The any-vehicle form used by a shared ground-station segmenter includes every vehicle's key.
    assert zenoh.KeyExpr(build(keys.ANY_VEHICLE)).includes(zenoh.KeyExpr(key))
    assert not zenoh.KeyExpr(build("uav-8")).intersects(zenoh.KeyExpr(key))


def test_topics_do_not_overlap() -> None:
    built = [zenoh.KeyExpr(b("uav1")) for b in TOPIC_BUILDERS]
    for i, a in enumerate(built):
        for b in built[i + 1:]:
            assert not a.intersects(b)


def test_liveliness_keys() -> None:
    assert keys.alive("uav1", "segmenter") == "dovesei/uav1/alive/segmenter"
    with pytest.raises(ConfigError, match="service 'x'"):
        keys.alive("uav1", "x")


@pytest.mark.parametrize("bad", ["", "a/b", "uav*", "$x", "a" * 65, "uav 1"])
def test_bad_vehicle_ids_are_refused(bad: str) -> None:
    with pytest.raises(ConfigError, match="vehicle id"):
        keys.camera(bad)


def test_config_layers_file_env_and_flags(tmp_path) -> None:
    env_file = tmp_path / "env.json5"
    env_file.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:1111"] } }')
    flag_file = tmp_path / "flag.json5"
    flag_file.write_text('{ mode: "peer" }')
    conf = zenoh_config(env={"ZENOH_CONFIG": str(env_file)})
    assert json.loads(conf.get_json("mode")) == "client"
    conf = zenoh_config(config_file=flag_file, env={"ZENOH_CONFIG": str(env_file)})
    assert json.loads(conf.get_json("mode")) == "peer"
    conf = zenoh_config(mode="client", connect=["tcp/127.0.0.1:2222"], multicast_scouting=False, env={})
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:2222"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def test_config_errors_name_the_input(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        zenoh_config(config_file=tmp_path / "missing.json5", env={})
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ConfigError, match="is invalid"):
        zenoh_config(config_file=bad, env={})
    with pytest.raises(ConfigError, match="--connect"):
        zenoh_config(connect=["localhost"], env={})
    with pytest.raises(ConfigError, match="ZENOH_CONFIG"):
        zenoh_config(env={"ZENOH_CONFIG": str(tmp_path / "nope")})


def test_data_clock_follows_stamps_and_never_goes_back() -> None:
    clock = DataClock("sim")
    assert not clock.started
    clock.observe(Stamp(2.0, "sim"))
    clock.observe(Stamp(1.0, "sim"))
    assert clock.now_s() == 2.0
    with pytest.raises(ValueError, match="'wall'"):
        clock.observe(Stamp(3.0, "wall"))


def test_wall_clock_sleep_is_interrupted_by_stop() -> None:
    clock, stop = WallClock(), threading.Event()
    stop.set()
    assert clock.sleep_until(clock.now_s() + 60.0, stop) is False
