"""Close looks in the segmenter: a crop is scored with the landing prompts and the "never" set, by
the real CLIPSeg code path (tiny random weights) and by the simulated perception, also over Zenoh."""

from __future__ import annotations

import numpy as np
import pytest

from dovesei.segmenter.core import (
    ClipSegFrameBackend, FrameRejected, SegmenterConfig, SegmenterCore, crop_probabilities, make_backend,
)
from dovesei.segmenter.fusion import FusionConfig
from dovesei.segmenter.prompts import NEVER_PROMPTS, REFERENCE_PROMPTS, crop_prompt_set
from dovesei.segmenter.service import ServiceConfig, SegmenterService
from dovesei.shared import keys
from dovesei.shared.codec import decode, encode
from dovesei.shared.crop_server import QueryFailed, query_one, wait_served
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import CropFrame, CropHeatmap, CropRequest, Stamp, replace
from dovesei.sim.core import SimConfig, SimCore
from dovesei.sim.starts import Start
from dovesei.sim.world import ClassInfo, World

GSD_M = 0.05
PERSON_XY_M = (62.0, 61.0)  # 2 m east and 1 m north of the vehicle


def person_world() -> World:
    """Grass with one 0.5 m person (labels only: the simulated perception reads them)."""
    n = 2400
    labels = np.ones((n, n), np.uint8)
    probe = World(np.zeros((n, n, 3), np.uint8), None, GSD_M, {}, "probe")
    r, c = probe.pixel_index(*PERSON_XY_M)
    labels[r - 5:r + 5, c - 5:c + 5] = 2
    return World(np.full((n, n, 3), 70, np.uint8), labels, GSD_M, {1: ClassInfo("grass", True),
                                                                  2: ClassInfo("person", False)}, "person")


@pytest.fixture(scope="module")
def person_crop() -> CropFrame:
    core = SimCore(person_world(), Start(60.0, 60.0, 40.0, 0.0), SimConfig(vehicle_profile="ideal"))
    core.reset()
    return core.crop(CropRequest("uav1", 4, Stamp(0.0, "sim"), (0.0, 0.0), 8.0, 352))


def test_the_simulated_perception_finds_the_person_in_a_crop(person_crop: CropFrame) -> None:
    config = SegmenterConfig(backend="sim", sim_profile="clean")
    core = SegmenterCore(make_backend(config), config)
    hm = core.process_crop(person_crop)
    assert isinstance(hm, CropHeatmap) and hm.prob_never.shape == (352, 352) and hm.request_seq == 4
    assert hm.simulated and hm.frame_seq == person_crop.frame_seq and hm.never_set_id
    safe, never = hm.probabilities()
    person = person_crop.truth.labels == 2
    far = np.ones_like(person)
    rows, cols = np.nonzero(person)
    far[max(0, rows.min() - 60):rows.max() + 60, max(0, cols.min() - 60):cols.max() + 60] = False
    assert never[person].max() > 0.9 and never[far].max() < 0.3  # seen where it is, nowhere else
    assert np.median(safe[far]) > 0.9 and core.processed_crops == 1


def test_a_square_reads_alike_from_any_height_and_differently_at_another_size(person_crop: CropFrame) -> None:
    """The same square cut from 22 m or 40 m is the same 352 px image to CLIPSeg, so the simulated
    misreadings follow the square's size, not the vehicle's altitude (read at the altitude, looks
    from two heights had missed someone independently, flattering every descent's looks)."""
    config = SegmenterConfig(backend="sim", sim_profile="harsh", sim_seed=3)
    core = SegmenterCore(make_backend(config), config)
    world = "synthetic:style=crowded,seed=6"  # its confusion draw: a world with every appearance in it
    crop = replace(person_crop, truth=replace(person_crop.truth, world=world))
    _, high = core.process_crop(crop).probabilities()
    _, low = core.process_crop(replace(crop, alt_agl_m=22.0)).probabilities()
    assert np.array_equal(high, low)
    _, wider = core.process_crop(replace(crop, side_m=11.4)).probabilities()
    assert not np.allclose(high, wider, atol=0.01)


def test_a_crop_without_truth_is_refused_by_the_simulated_backend(person_crop: CropFrame) -> None:
    config = SegmenterConfig(backend="sim")
    core = SegmenterCore(make_backend(config), config)
    with pytest.raises(FrameRejected, match="no_truth"):
        core.process_crop(replace(person_crop, truth=None))


def test_clipseg_scores_a_crop_with_one_pass_over_landing_and_never_prompts(tiny_clipseg_dir, person_crop) -> None:
    model_dir = str(tiny_clipseg_dir)
    config = SegmenterConfig(backend="clipseg", model=model_dir, threads=1)
    backend = make_backend(config)
    assert isinstance(backend, ClipSegFrameBackend)
    core = SegmenterCore(backend, config)
    hm = core.process_crop(replace(person_crop, truth=None))  # a real camera's crop: pixels only
    assert hm.backend == "clipseg" and not hm.simulated and hm.prob_safe.shape == (352, 352)
    # The same numbers as fusing the model's own logits of the combined prompt set by hand.
    combined = crop_prompt_set(REFERENCE_PROMPTS, NEVER_PROMPTS)
    logits = backend.model.logits(person_crop.image_rgb, combined)
    safe, never = crop_probabilities(logits, None, REFERENCE_PROMPTS, len(NEVER_PROMPTS), FusionConfig(), 352)
    got_safe, got_never = hm.probabilities()
    assert np.abs(got_safe - safe).max() <= 1 / 255 + 1e-6 and np.abs(got_never - never).max() <= 1 / 255 + 1e-6


def test_a_never_set_the_text_side_cannot_hold_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="never"):
        SegmenterConfig(never=())
    with pytest.raises(ConfigError, match="never"):
        SegmenterConfig(never=("",))


def test_the_segment_queryable_answers_crops_and_refuses_foreign_schemas(zenoh_pair, person_crop) -> None:
    import threading

    seg_session, ctrl_session = zenoh_pair
    config = ServiceConfig(segmenter=SegmenterConfig(backend="sim", sim_profile="clean"))
    core = SegmenterCore(make_backend(config.segmenter), config.segmenter)
    stop = threading.Event()
    with SegmenterService(seg_session, config, core) as service:
        thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
        thread.start()
        try:
            assert wait_served(ctrl_session, keys.segment("uav1"), 10.0), "the segment queryable never propagated"
            hm = decode(query_one(ctrl_session, keys.segment("uav1"), encode(person_crop, jpeg_quality=90), 20.0),
                        CropHeatmap)
            assert hm.request_seq == 4 and hm.prob_never.shape == (352, 352)
            assert hm.probabilities()[1][person_crop.truth.labels == 2].max() > 0.9
            req = CropRequest("uav1", 1, Stamp(0.0, "sim"), (0.0, 0.0), 8.0, 352)
            with pytest.raises(QueryFailed, match="CameraFrame or a CropFrame"):
                query_one(ctrl_session, keys.segment("uav1"), encode(req), 20.0)
        finally:
            stop.set()
            thread.join(10.0)
    assert service.queries_answered == 1 and service.queries_refused == 1
