"""The episode video plays anywhere: H.264 in MP4 (read back with PyAV, as ffprobe would), every
frame kept after the opening, a legend, and no focus circle where there is no heatmap."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np

from dovesei.pictures.video import BAR_PX, LEGEND_PX, PANELS, POLICY_TEXT_PX, VideoFrame, _compose, write_video

SIDE_PX = 352


def _frames(n: int, blind_first: int = 0) -> list[VideoFrame]:
    image = np.full((SIDE_PX, SIDE_PX, 3), 128, np.uint8)
    prob = np.zeros((SIDE_PX, SIDE_PX), np.float32)
    prob[:, SIDE_PX // 2:] = 1.0
    blind = [VideoFrame(t_s=0.25 * i, image_rgb=image, prob_safe=None, alt_agl_m=100.0, state="SENSOR_ERROR",
                        focus_radius_px=150.0) for i in range(blind_first)]
    return blind + [VideoFrame(t_s=0.25 * (blind_first + i), image_rgb=image, prob_safe=prob, alt_agl_m=100.0 - i,
                               state="AIMING", focus_radius_px=100.0, target_px=(176.0, 260.0), threshold=0.5)
                    for i in range(n)]


def test_video_is_h264_mp4_and_opens_on_the_first_heatmap(tmp_path: Path) -> None:
    out = write_video(_frames(12, blind_first=3), tmp_path / "episode.mp4", fps=10.0)
    assert out.suffix == ".mp4"
    with av.open(str(out)) as container:
        assert "mp4" in container.format.name
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"  # what browsers decode
        frames = [f.to_ndarray(format="bgr24") for f in container.decode(video=0)]
    assert len(frames) == 12  # the three blind frames before the first heatmap are not the opening
    assert frames[0].shape[:2] == (SIDE_PX + POLICY_TEXT_PX + BAR_PX + LEGEND_PX, PANELS * SIDE_PX)
    # Policy view (third panel): inside the focus circle, below the 0.5 threshold is dimmed and the
    # safe half bright green; outside the circle the safe half is dimmed too.
    panel = frames[0][:SIDE_PX, 2 * SIDE_PX:3 * SIDE_PX].astype(int)
    assert panel[230, 130].max() < 90 and panel[230, 236][1] > 180
    assert panel[330, 330][1] < 90


def test_no_focus_circle_over_no_heatmap() -> None:
    blind = _frames(0, blind_first=1)[0]
    img = _compose(blind, SIDE_PX)
    heat = img[30:SIDE_PX, SIDE_PX:2 * SIDE_PX]
    cyan = (heat[..., 0] > 200) & (heat[..., 1] > 200) & (heat[..., 2] < 80)
    assert not cyan.any()
    with_hm = _compose(_frames(1)[0], SIDE_PX)[30:SIDE_PX, SIDE_PX:2 * SIDE_PX]
    assert ((with_hm[..., 0] > 200) & (with_hm[..., 1] > 200) & (with_hm[..., 2] < 80)).any()


def test_state_changes_between_frames_are_counted_and_shown() -> None:
    from dovesei.pictures.video import changes_before, state_change_times

    states = {0.0: "AIMING", 0.05: "LANDING", 0.1: "AIMING", 0.15: "AIMING", 0.2: "LANDING", 2.0: "LANDING"}
    times = state_change_times(states)
    assert list(times) == [0.05, 0.1, 0.2]
    assert changes_before(times, 0.25) == 3 and changes_before(times, 1.15) == 1 and changes_before(times, 2.0) == 0
    quiet = _compose(_frames(1)[0], SIDE_PX)
    busy = _compose(VideoFrame(**{**_frames(1)[0].__dict__, "recent_changes": 5}), SIDE_PX)
    bar = slice(SIDE_PX + POLICY_TEXT_PX, SIDE_PX + POLICY_TEXT_PX + BAR_PX)
    assert (busy[bar] > 128).sum() > (quiet[bar] > 128).sum()  # the count is written in the bar


def _decode(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="bgr24") for f in container.decode(video=0)]


def test_the_last_frame_shows_the_outcome_and_the_policy_flown(tmp_path: Path) -> None:
    """The controller stops before the recorder: the last frames carry no status. They keep the
    clearance policy's panel (not the default one) and the video ends on the outcome, held."""
    from dovesei.pictures.video import ENDING_HOLD_S, OUTCOME_BGR

    flown = [VideoFrame(**{**f.__dict__, "policy": "clearance", "focus_radius_px": 0.0, "hfov_rad": 1.0,
                           "target_px": None, "state": "DESCEND"}) for f in _frames(4)]
    blank = [VideoFrame(**{**flown[-1].__dict__, "t_s": 2.0 + 0.25 * i, "state": "", "policy": "", "threshold": None})
             for i in range(2)]
    fps = 10.0
    frames = _decode(write_video(flown + blank, tmp_path / "e.mp4", fps=fps, outcome="safe",
                                 detail="0.0% of the disk is unsafe", policy="clearance"))
    assert len(frames) == 6 + round(ENDING_HOLD_S * fps)
    caption = (slice(0, 22), slice(2 * SIDE_PX, 3 * SIDE_PX))
    # The status-less frame is drawn as the clearance policy's view (same panel title), not dovesei's.
    first, plain_last = frames[0][caption].astype(int), frames[5][caption].astype(int)
    assert np.abs(first - plain_last).mean() < 3
    default = _compose(blank[0], SIDE_PX)[caption].astype(int)  # what a blank status used to draw
    assert np.abs(default - plain_last).mean() > 3
    # The outcome band, in the outcome's colour across the panels, only on the ending frames.
    def band(img: np.ndarray) -> int:
        return int((np.abs(img[:SIDE_PX].astype(int) - np.array(OUTCOME_BGR["safe"])) < 25).all(axis=-1).sum())
    assert band(frames[-1]) > 10 * SIDE_PX and band(frames[5]) < SIDE_PX
    unsafe = _decode(write_video(flown, tmp_path / "u.mp4", fps=fps, outcome="unsafe", detail="on a road"))[-1]
    assert band(unsafe) < SIDE_PX  # another outcome, another colour
