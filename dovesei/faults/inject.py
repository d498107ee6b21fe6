"""What an intruder on the plain (unsecured) network sends: forged, skewed and garbage messages.

Each `put_*` publishes from the intruder's own client session, never from a service's: that is
the threat of an open router (anyone reaching the port can put on any key). Forged samples carry
sequence numbers from FORGED_SEQ_BASE up, so the checks can tell them from the services' own.
"""

from __future__ import annotations

import random
from typing import Any

import msgpack
import numpy as np
import zenoh

from dovesei.shared import keys
from dovesei.shared.codec import encode
from dovesei.shared.messages import EpisodeResult, PromptSetMsg, SafetyHeatmap, Stamp, VehicleState, VelocityCommand
from dovesei.shared.mission import HANDOVER_ALT_M

FORGED_SEQ_BASE = 1_000_000
FORGED_RESULT_DETAIL = "forged by dovesei faults"
SKEW_S = 30.0  # how far ahead (and behind) the skewed stamps are


def restamped(payload: bytes, t_s: float) -> bytes:
    """The same message with its stamp replaced on the wire: a sender is not bound by our constructors."""
    body = msgpack.unpackb(payload, raw=False)
    body["stamp"]["t_s"] = float(t_s)
    return msgpack.packb(body, use_bin_type=True)


class Intruder:
    """One client session on the shared router, putting what a hostile host would."""

    def __init__(self, config: zenoh.Config, vehicle_id: str, seed: int) -> None:
        self.vehicle_id = vehicle_id
        self.session = zenoh.open(config)
        self.rng = random.Random(seed)
        self.sent = 0
        self._n = 0

    def _seq(self) -> int:
        self._n += 1
        return FORGED_SEQ_BASE + self._n

    def put(self, topic: str, payload: bytes) -> None:
        self.session.put(getattr(keys, topic)(self.vehicle_id), payload)
        self.sent += 1

    def skewed_heatmap(self, now_s: float, offset_s: float, alt_m: float) -> None:
        """An all-safe heatmap stamped `offset_s` from the vehicle's clock: adopted, it would steer anywhere."""
        prob = np.full((88, 88), 255, dtype=np.uint8)
        hm = SafetyHeatmap(vehicle_id=self.vehicle_id, seq=self._seq(), stamp=Stamp(0.0, "sim"),
                           prob_safe=prob, alt_agl_m=alt_m, hfov_rad=1.274, backend="simulated", simulated=True,
                           prompt_set_id="forged", fusion="forged", inference_s=0.0)
        self.put("heatmap", restamped(encode(hm), now_s + offset_s))

    def skewed_state(self, now_s: float, offset_s: float, alt_m: float) -> None:
        st = VehicleState(vehicle_id=self.vehicle_id, seq=self._seq(), stamp=Stamp(0.0, "sim"),
                          alt_agl_m=alt_m, vel_body_frd_m_s=(0.0, 0.0, 0.0))
        self.put("state", restamped(encode(st), now_s + offset_s))

    def forged_command(self, stamp_s: float) -> None:
        """A 5 m/s descent: obeyed, it would fly the vehicle into the ground."""
        cmd = VelocityCommand(vehicle_id=self.vehicle_id, seq=self._seq(), stamp=Stamp(0.0, "sim"),
                              vel_body_frd_m_s=(0.0, 0.0, 5.0))
        self.put("cmd", restamped(encode(cmd), stamp_s))

    def forged_result(self, last_state: VehicleState | None, start: tuple[float, float, float]) -> None:
        """'safe' at the vehicle's last known position (so a position check alone cannot tell)."""
        x0, y0, _ = start
        north_m, east_m, _ = last_state.pos_local_ned_m if last_state is not None else (0.0, 0.0, 0.0)
        t_s = last_state.stamp.t_s if last_state is not None else 0.0
        res = EpisodeResult(vehicle_id=self.vehicle_id, stamp=Stamp(t_s, "sim"), outcome="safe", sim_time_s=t_s,
                            path_length_m=1.0, final_x_m=x0 + east_m, final_y_m=y0 + north_m,
                            final_alt_m=last_state.alt_agl_m if last_state is not None else HANDOVER_ALT_M,
                            detail=FORGED_RESULT_DETAIL)
        self.put("episode", encode(res))

    def bad_prompts(self) -> None:
        """Prompt sets the segmenter must refuse: empty, no placeholder, thousands of prompts, not msgpack."""
        good = encode(PromptSetMsg(stamp=Stamp(0.0, "wall"), positive=("grass",), negative=("road",)))
        body: dict[str, Any] = msgpack.unpackb(good, raw=False)
        variants = [
            {**body, "positive": []},
            {**body, "negative": [""]},
            {**body, "template": "no placeholder"},
            {**body, "positive": [f"p{i}" for i in range(5000)]},
        ]
        for v in variants:
            self.put("prompts", msgpack.packb(v, use_bin_type=True))
        self.put("prompts", b"\xc1" * 64)

    def garbage(self, topic: str) -> None:
        """Random bytes, or a well-formed msgpack map of the right schema with nonsense inside."""
        if self.rng.random() < 0.5:
            self.put(topic, self.rng.randbytes(self.rng.randint(1, 512)))
        else:
            schema = {"heatmap": SafetyHeatmap.SCHEMA, "state": VehicleState.SCHEMA}[topic]
            self.put(topic, msgpack.packb({"_schema": schema, "_v": 1, "seq": "x", "stamp": [1, 2]},
                                          use_bin_type=True))

    def close(self) -> None:
        self.session.close()
