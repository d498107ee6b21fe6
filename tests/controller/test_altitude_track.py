"""AltitudeTrack.nearest is exactly min(states, key=|t - t_s|), the first of equally near ones."""

import random

from dovesei.controller.continuity import AltitudeTrack


def _reference(states, t_s):
    return min(states, key=lambda ta: abs(ta[0] - t_s), default=None)


def test_nearest_matches_the_scan_over_flights_with_repeats_and_jumps_back():
    rng = random.Random(7)
    n = 20
    for trial in range(300):
        track, kept = AltitudeTrack(n), []
        t = 0.0
        for step in range(rng.randint(0, 80)):
            r = rng.random()
            if r < 0.15:
                pass  # a re-ticked state: the same time again
            elif r < 0.2:
                t -= rng.choice([0.05, 1.0, 30.0])  # a time that goes back (a new episode, a reset)
            else:
                t += rng.choice([0.05, 0.05, 0.1, 0.025])
            alt = float(step)  # tells equal times apart
            track.add(t, alt)
            kept = (kept + [(t, alt)])[-n:]
            for query in (t, t - 0.025, t - 0.05, t + 0.3, t - 5.0, t - 100.0, rng.uniform(t - 3.0, t + 1.0)):
                assert track.nearest(query) == _reference(kept, query), (trial, step, query)


def test_an_empty_track_has_no_nearest_state():
    assert AltitudeTrack(5).nearest(3.0) is None
