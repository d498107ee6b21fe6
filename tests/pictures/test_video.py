"""The episode video plays anywhere: H.264 in MP4 (read back with PyAV, as ffprobe would), every
frame kept after the opening, a legend, and no focus circle where there is no heatmap."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np

from dovesei.pictures.video import BAR_PX, LEGEND_PX, PANELS, VideoFrame, _compose, write_video

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
    assert frames[0].shape[:2] == (SIDE_PX + BAR_PX + LEGEND_PX, PANELS * SIDE_PX)
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
