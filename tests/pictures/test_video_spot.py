"""The `clearance` policy's panel in the video: the chosen spot as a circle of its clearance radius
(metres -> pixels with the footprint at the frame's altitude) where the status places it, the
policy's reason as text, and no focus circle (that policy has none)."""

from __future__ import annotations

import math

import numpy as np

from dovesei.pictures.video import POLICY_TEXT_PX, VideoFrame, _compose

SIDE = 352
HFOV_RAD = math.radians(73.0)


def _frame(**kw: object) -> VideoFrame:
    image = np.full((SIDE, SIDE, 3), 128, np.uint8)
    prob = np.full((88, 88), 0.9, np.float32)  # a heatmap coarser than the panel: pixels scale by 4
    base = dict(t_s=10.0, image_rgb=image, prob_safe=prob, alt_agl_m=60.0, state="approach", focus_radius_px=20.0,
                target_px=(30.0, 60.0), threshold=0.5, policy="clearance", hfov_rad=HFOV_RAD, spot_clearance_m=8.0,
                policy_reason="spot 25 m away: clearance 8.0 m, confidence 0.80")
    return VideoFrame(**{**base, **kw})


def _magenta(panel: np.ndarray) -> np.ndarray:
    return (panel[..., 0] > 200) & (panel[..., 2] > 200) & (panel[..., 1] < 80)


def _cyan(panel: np.ndarray) -> np.ndarray:
    return (panel[..., 0] > 200) & (panel[..., 1] > 200) & (panel[..., 2] < 80)


def _policy_panel(img: np.ndarray) -> np.ndarray:
    return img[:SIDE, 2 * SIDE:3 * SIDE]


def _text_row(img: np.ndarray) -> np.ndarray:
    return img[SIDE:SIDE + POLICY_TEXT_PX]


def test_spot_circle_has_the_clearance_radius_at_the_status_target() -> None:
    frame = _frame()
    panel = _policy_panel(_compose(frame, SIDE))
    # Expected geometry: footprint 2 x 60 x tan(36.5 deg) = 88.8 m over 88 heatmap px, 4 panel px each.
    footprint_m = 2 * 60.0 * math.tan(HFOV_RAD / 2)
    radius_px = 8.0 * 88 / footprint_m * (SIDE / 88)
    cx, cy = (60.0 + 0.5) * 4, (30.0 + 0.5) * 4
    ys, xs = np.nonzero(_magenta(panel))
    dist = np.hypot(xs - cx, ys - cy)
    ring = dist[dist > 16]  # leave out the cross marking the centre
    assert ring.size > 50
    assert abs(np.median(ring) - radius_px) < 3.0, (np.median(ring), radius_px)
    # The circle follows the altitude: 1.5 x as high, 2/3 of the radius in pixels.
    high = _policy_panel(_compose(_frame(alt_agl_m=90.0), SIDE))
    ys, xs = np.nonzero(_magenta(high))
    dist = np.hypot(xs - cx, ys - cy)
    assert abs(np.median(dist[dist > 16]) - radius_px * 2 / 3) < 2.0


def test_clearance_draws_no_focus_circle_and_writes_its_reason() -> None:
    spot = _compose(_frame(), SIDE)
    assert not _cyan(spot[30:SIDE]).any()  # no focus circle on any panel
    # No focus dimming either: a safe pixel far from the centre stays bright in the policy view.
    assert _policy_panel(spot)[200, 340][1] > 180
    # The reason is written in the row under the panels (white text), not over the policy view.
    silent = _compose(_frame(policy_reason=""), SIDE)
    white = lambda img: ((_text_row(img) > 220).all(axis=-1)).sum()  # noqa: E731
    assert white(spot) > white(silent) + 50
    assert np.array_equal(_policy_panel(spot), _policy_panel(silent))
    # The same frame from the dovesei policy keeps its focus circle and has no spot circle.
    focus = _compose(_frame(policy="dovesei", focus_radius_px=40.0), SIDE)
    assert _cyan(focus[30:SIDE]).any()
    ys, xs = np.nonzero(_magenta(_policy_panel(focus)))
    assert (np.hypot(xs - 242, ys - 122) < 16).all()  # only the cross


def test_no_spot_or_no_field_of_view_draws_no_circle() -> None:
    for frame in (_frame(spot_clearance_m=None), _frame(target_px=None, spot_clearance_m=None)):
        ys, xs = np.nonzero(_magenta(_policy_panel(_compose(frame, SIDE))))
        assert (np.hypot(xs - 242, ys - 122) < 16).all()
    # Without the field of view the radius cannot be known: the cross only, never a guessed circle.
    ys, xs = np.nonzero(_magenta(_policy_panel(_compose(_frame(hfov_rad=None), SIDE))))
    assert (np.hypot(xs - 242, ys - 122) < 16).all()


def test_the_confirming_look_is_marked_in_its_own_frame_only() -> None:
    """The look that confirmed the spot carries a cross at the confirmed pixel; a later frame only
    says how many frames ago that was (its own pixels show other ground)."""
    plain_img = _compose(_frame(), SIDE)
    plain = _policy_panel(plain_img)
    here = _policy_panel(_compose(_frame(confirmed_frames_ago=0, confirmed_px=(50.0, 40.0)), SIDE))
    changed = np.any(here != plain, axis=2)
    changed[:22, :] = False  # the caption bar
    ys, xs = np.nonzero(changed)
    assert xs.size > 0 and abs(np.median(xs) - 40.5 * 4) <= 3 and abs(np.median(ys) - 50.5 * 4) <= 3
    later_img = _compose(_frame(confirmed_frames_ago=3), SIDE)
    assert np.array_equal(_policy_panel(later_img), plain)  # no cross drawn
    assert not np.array_equal(_text_row(later_img), _text_row(plain_img))  # it says so in text


def test_near_20_m_the_spot_circle_and_the_words_leave_the_below_threshold_ground_readable() -> None:
    """At 20 m the spot's clearance circle spans most of the view: the policy's words are not written
    over the view (they hid the below-threshold ground), and the circle is an outline on a dark casing,
    so dimmed ground inside and outside it stays as the heatmap drew it."""
    prob = np.full((88, 88), 0.9, np.float32)
    prob[60:, :] = 0.2  # below the threshold: dimmed in the policy view
    low = _frame(alt_agl_m=20.0, prob_safe=prob, target_px=(44.0, 44.0), spot_clearance_m=6.0,
                 confirmed_frames_ago=2, policy_reason="locked within 3.2 m: descending, re-checking the footprint")
    img = _compose(low, SIDE)
    panel = _policy_panel(img)
    bare = _policy_panel(_compose(VideoFrame(**{**low.__dict__, "policy_reason": "", "spot_clearance_m": None,
                                                "confirmed_frames_ago": None}), SIDE))
    changed = np.any(panel != bare, axis=2)
    changed[:22] = False  # the caption names the view
    # Only the ring changed the view: every changed pixel lies within a few pixels of the circle.
    footprint_m = 2 * 20.0 * math.tan(HFOV_RAD / 2)
    radius_px = 6.0 * SIDE / footprint_m
    ys, xs = np.nonzero(changed)
    dist = np.hypot(xs - 44.5 * 4, ys - 44.5 * 4)
    assert xs.size > 100 and (np.abs(dist - radius_px) < 5).all()
    # The dimmed ground keeps its colour in the bottom corners, where the words were written.
    assert np.array_equal(panel[SIDE - 45:, :60], bare[SIDE - 45:, :60])
    ring = np.abs(dist - radius_px) < 5
    assert (panel[ys[ring], xs[ring]].max(axis=-1) < 40).any()  # the dark casing
    assert ((_text_row(img) > 220).all(axis=-1)).sum() > 100  # the words, under the panels
