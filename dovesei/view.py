"""The Rerun view of a flight: live from `dovesei up --view`, or `dovesei view <report | recording>`.

    message (from up's monitor, or read from recording.mcap) --LiveView.write--> Rerun entities
        camera/image      the frame;  camera/heatmap  P(safe) as a red-green overlay (alpha)
        camera/focus      the policy's focus circle (or clearance radius) and camera/target, its spot
        world/ground      the world image as a textured quad (metres, z up); world/path, world/vehicle
        map/image, map/path  the path over the world, top-down (pixels of a reduced world image)
        plots/*           altitude, speed, commanded descent over sim time; log/state on each change
    Timeline "sim_time": the data's clock (DESIGN 4), so a lockstep run plays back at sim speed.

The viewer listens on loopback only (`rerun --bind 127.0.0.1`): the live view is for the operator's
machine, never an open port on the vehicle's network. Without a display the web viewer is served
on loopback instead and its address logged. rerun-sdk is the optional extra 'view'.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rerun as rr
from rerun.chunk import RrdReader

from dovesei.shared.cliconfig import OneLineParser
from dovesei.shared.errors import ConfigError
from dovesei.shared.messages import (
    CameraFrame, ControllerStatus, EpisodeResult, Message, SafetyHeatmap, VehicleState, VelocityCommand,
)
from dovesei.shared.recording import FlightRecording, find_recording
from dovesei.shared.zconfig import free_port
from dovesei.sim.world import WorldError, load_world

log = logging.getLogger("dovesei.view")

MAP_SIDE_PX = 1024  # the world image is reduced to this for the ground texture and the map view
PATH_EVERY_S = 0.5  # sim seconds between re-sent path polylines (each send carries the whole path)


def _overlay_rgba(prob_safe: np.ndarray) -> np.ndarray:
    """P(safe) as an overlay: red (unsafe) to green (safe), half transparent."""
    p = prob_safe.astype(np.float32) / 255.0 if prob_safe.dtype == np.uint8 else prob_safe.astype(np.float32)
    rgba = np.empty((*p.shape, 4), np.uint8)
    rgba[..., 0] = np.round((1.0 - p) * 255)
    rgba[..., 1] = np.round(p * 255)
    rgba[..., 2] = 0
    rgba[..., 3] = 110
    return rgba


def _circle(centre_rc: tuple[float, float], radius_px: float, n: int = 64) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * math.pi, n)
    return np.column_stack([centre_rc[1] + radius_px * np.cos(a), centre_rc[0] + radius_px * np.sin(a)])


class LiveView:
    """A Rerun recording stream fed message by message; `write`/`close` like a FlightRecorder."""

    def __init__(self, world: Any, start: tuple[float, float, float], *, spawn: bool = False,
                 rrd: str | Path | None = None, vehicle_id: str = "uav1", application_id: str = "dovesei") -> None:
        self.rec = rr.RecordingStream(application_id, recording_id=None)
        self.start = start
        self.viewer: subprocess.Popen | None = None
        sinks: list[Any] = []
        if rrd is not None:
            Path(rrd).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd)))
        if spawn:
            sinks.append(rr.GrpcSink(self._start_viewer()))
        if not sinks:
            raise ConfigError("the live view needs a viewer or an .rrd file to write to")
        self.rec.set_sinks(*sinks)
        self._path_xyz: list[tuple[float, float, float]] = []
        self._next_path_t_s = -math.inf
        self._last_state = ""
        self._heatmap_side: tuple[int, int] | None = None
        self._map_px_per_m = 1.0
        self._world_h_m = 0.0
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log("vehicle_id", rr.TextDocument(vehicle_id), static=True)
        if world is not None:
            self._log_world(world)

    def _start_viewer(self) -> str:
        """A Rerun viewer bound to loopback; the SDK's gRPC URL to send to."""
        exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
        port = free_port()
        cmd = [exe, "--bind", "127.0.0.1", "--port", str(port)]
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            web_port = free_port()
            cmd += ["--serve-web", "--web-viewer-port", str(web_port)]
            log.info("no display: Rerun web viewer at http://127.0.0.1:%d (loopback only)", web_port)
        # Its own session: the viewer outlives `up`, so the operator can keep looking after landing.
        self.viewer = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                       start_new_session=True)
        log.info("Rerun viewer started (pid %d) on 127.0.0.1:%d", self.viewer.pid, port)
        return f"rerun+http://127.0.0.1:{port}/proxy"

    def _log_world(self, world: Any) -> None:
        img = world.image_rgb
        scale = min(1.0, MAP_SIDE_PX / max(img.shape[:2]))
        small = cv2.resize(img, (max(1, round(img.shape[1] * scale)), max(1, round(img.shape[0] * scale))),
                           interpolation=cv2.INTER_AREA)
        self._map_px_per_m = scale / world.gsd_m
        self._world_h_m = world.height_m
        w_m, h_m = world.width_m, world.height_m
        # Ground quad in world metres (x east, y north, z up); image row 0 is the north edge.
        self.rec.log("world/ground", rr.Mesh3D(
            vertex_positions=[[0, 0, 0], [w_m, 0, 0], [w_m, h_m, 0], [0, h_m, 0]],
            triangle_indices=[[0, 1, 2], [0, 2, 3]],
            vertex_texcoords=[[0, 1], [1, 1], [1, 0], [0, 0]], albedo_texture=small), static=True)
        self.rec.log("map/image", rr.Image(small), static=True)
        self.rec.log("world/start", rr.Points3D([self.start], radii=1.5, colors=[[255, 255, 255]]), static=True)

    def _map_px(self, xyz: np.ndarray) -> np.ndarray:
        # Map pixels: column = east / gsd, row = (world height - north) / gsd, times the reduction.
        return np.column_stack([xyz[:, 0], self._world_h_m - xyz[:, 1]]) * self._map_px_per_m

    def write(self, msg: Message, recv_wall_s: float | None = None) -> None:
        stamp = getattr(msg, "stamp", None)
        if stamp is not None:
            self.rec.set_time("sim_time", duration=float(stamp.t_s))
        if isinstance(msg, CameraFrame):
            ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(msg.image_rgb, cv2.COLOR_RGB2BGR),
                                    [cv2.IMWRITE_JPEG_QUALITY, 85])
            if ok:  # JPEG: a long flight in a viewer's memory is otherwise ~0.4 MB per frame
                self.rec.log("camera/image", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        elif isinstance(msg, SafetyHeatmap):
            self._heatmap_side = msg.prob_safe.shape[:2]
            # PNG: lossless and a tenth of the raw RGBA (a long flight stays a file you can send).
            ok, png = cv2.imencode(".png", cv2.cvtColor(_overlay_rgba(np.asarray(msg.prob_safe)), cv2.COLOR_RGBA2BGRA))
            if ok:
                self.rec.log("camera/heatmap", rr.EncodedImage(contents=png.tobytes(), media_type="image/png"))
            self.rec.log("plots/heatmap_p_mean", rr.Scalars(float(np.mean(msg.prob_safe)) /
                                                            (255.0 if msg.prob_safe.dtype == np.uint8 else 1.0)))
        elif isinstance(msg, ControllerStatus):
            self._on_status(msg)
        elif isinstance(msg, VehicleState):
            self._on_state(msg)
        elif isinstance(msg, VelocityCommand):
            self.rec.log("plots/cmd_down_m_s", rr.Scalars(msg.vel_body_frd_m_s[2]))
        elif isinstance(msg, EpisodeResult):
            self.rec.log("log/state", rr.TextLog(f"episode: {msg.outcome} ({msg.detail})", level=rr.TextLogLevel.INFO))
            self.rec.log("world/final", rr.Points3D([[msg.final_x_m, msg.final_y_m, msg.final_alt_m]], radii=2.0,
                                                    colors=[[0, 200, 255] if msg.outcome == "safe" else [255, 0, 0]]))

    def _on_status(self, st: ControllerStatus) -> None:
        if st.state != self._last_state:
            self.rec.log("log/state", rr.TextLog(f"{st.state} ({st.reason})" if st.reason else st.state,
                                                 level=rr.TextLogLevel.INFO))
            self._last_state = st.state
        if self._heatmap_side is None:
            return  # no heatmap yet: a focus circle over nothing would only mislead
        h, w = self._heatmap_side
        if st.focus_radius_px > 0:
            self.rec.log("camera/focus", rr.LineStrips2D([_circle((h / 2, w / 2), st.focus_radius_px)],
                                                         colors=[[255, 255, 0]], radii=1.0))
        if st.target_valid:
            self.rec.log("camera/target", rr.Points2D([[st.target_col_px, st.target_row_px]], radii=4.0,
                                                      colors=[[0, 200, 255]]))
        else:
            self.rec.log("camera/target", rr.Clear(recursive=False))

    def _on_state(self, st: VehicleState) -> None:
        north_m, east_m, _ = st.pos_local_ned_m
        x_m, y_m = self.start[0] + east_m, self.start[1] + north_m
        speed = float(np.linalg.norm(st.vel_body_frd_m_s[:2]))
        self.rec.log("plots/alt_agl_m", rr.Scalars(st.alt_agl_m))
        self.rec.log("plots/speed_horizontal_m_s", rr.Scalars(speed))
        if not st.pos_valid and st.pos_local_ned_m == (0.0, 0.0, 0.0):
            return  # a real vehicle without a local position: no path to draw
        self._path_xyz.append((x_m, y_m, st.alt_agl_m))
        self.rec.log("world/vehicle", rr.Points3D([[x_m, y_m, st.alt_agl_m]], radii=1.5, colors=[[255, 80, 0]]))
        if st.stamp.t_s >= self._next_path_t_s:
            self._next_path_t_s = st.stamp.t_s + PATH_EVERY_S
            self._log_path()

    def _log_path(self) -> None:
        xyz = np.asarray(self._path_xyz, dtype=np.float64)
        self.rec.log("world/path", rr.LineStrips3D([xyz], colors=[[255, 80, 0]], radii=0.4))
        self.rec.log("map/path", rr.LineStrips2D([self._map_px(xyz)], colors=[[255, 80, 0]], radii=1.5))

    def close(self) -> None:
        if self._path_xyz:
            self._log_path()
        self.rec.flush()
        self.rec.disconnect()


def rrd_entities(path: str | Path) -> dict[str, int]:
    """Entity path -> rows in an .rrd, read back with the Rerun SDK's own reader."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(path).store().stream():
        rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), 0) + chunk.num_rows
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="dovesei view", description=__doc__.split("\n")[0])
    parser.add_argument("target", type=Path, help="a report folder (with recording.mcap) or a recording .mcap")
    parser.add_argument("--rrd", type=Path, help="write the Rerun recording here (default: beside the recording)")
    parser.add_argument("--open", action=argparse.BooleanOptionalAction, default=True,
                        help="start a Rerun viewer on loopback (default: yes)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    recording = FlightRecording(find_recording(args.target))
    run = recording.meta("run")
    world = None
    if run.get("world"):
        try:
            world = load_world(str(run["world"]))
        except WorldError as exc:
            log.warning("world %s not loaded (%s): the view has no ground image", run["world"], exc)
    start = tuple(run.get("start") or (0.0, 0.0, 0.0))
    rrd = args.rrd or recording.path.with_suffix(".rrd")
    view = LiveView(world, start, spawn=args.open, rrd=rrd, vehicle_id=str(run.get("vehicle_id", "uav1")))
    n = 0
    for wall_s, msg in recording.messages():
        view.write(msg, wall_s)
        n += 1
    view.close()
    if recording.cut is not None:
        print(recording.describe())  # a crash or power loss cut it: everything before the cut is shown
    print(f"{n} messages from {recording.path} -> {rrd}")
    return 0
