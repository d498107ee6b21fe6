"""The crop queryable over real Zenoh sessions: the sim in lockstep answers good crops, refuses bad
requests with a one-line reason, and keeps serving (and flying) after each."""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.shared import keys
from dovesei.shared.crop_server import QueryFailed, ask_crop, query_one, wait_served
from dovesei.shared.messages import CropRequest, Stamp
from dovesei.sim.world import World
from tests.sim.test_sim_service_zenoh import DESCEND, VID, Recorder, SimThread, lockstep_config, pair  # noqa: F401
from tests.sim.test_sim_core import command, split_world


@pytest.fixture(scope="module")
def world() -> World:
    return split_world()


def _req(seq: int, side_m: float = 6.0, out_px: int = 96) -> CropRequest:
    return CropRequest(VID, seq, Stamp(0.0, "sim"), (1.0, -2.0), side_m, out_px)


def test_the_sim_answers_crops_refuses_bad_ones_and_flies_on(pair, world: World) -> None:
    sim_session, rec = pair
    with SimThread(sim_session, lockstep_config(), world) as sim:
        rec.announce()
        topic, state = rec.next()
        while topic != "state":  # the first frame, then state 0: the sim waits for our answer
            topic, state = rec.next()
        assert wait_served(rec.session, keys.crop(VID), 10.0)
        crop = ask_crop(rec.session, _req(1), timeout_s=10.0)
        assert crop.request_seq == 1 and crop.frame_seq == 0 and crop.image_rgb.shape == (96, 96, 3)
        assert crop.truth is not None and crop.truth.labels.shape == (96, 96) and crop.side_m == 6.0
        assert crop.image_rgb.std() > 0  # rendered ground, through JPEG
        with pytest.raises(QueryFailed, match=r"crop refused: crop 2 refused: side 5000 m outside"):
            ask_crop(rec.session, _req(2, side_m=5000.0), timeout_s=10.0)
        with pytest.raises(QueryFailed, match="crop refused: .*not a msgpack payload"):
            query_one(rec.session, keys.crop(VID), b"\xc1garbage", timeout_s=10.0)
        with pytest.raises(QueryFailed, match="crop refused: .*finer than the frame"):
            ask_crop(rec.session, _req(3, side_m=0.6, out_px=1024), timeout_s=10.0)
        assert ask_crop(rec.session, _req(4), timeout_s=10.0).request_seq == 4  # still serving
        rec.send(command(state, DESCEND))
        result = rec.until_result(lambda state: rec.send(command(state, DESCEND)))
        assert result.outcome == "safe"
        sim.join()
    assert sim.stats.crops_answered == 2 and sim.stats.crops_refused == 3
