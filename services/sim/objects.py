"""People and vehicles as objects of a world: where each one is at any time, drawn at any resolution.

The world's texture is an orthophoto at its ground sample distance (0.25 m/px for the synthetic
worlds): a person there is a 2-pixel blob. An `ObjectLayer` holds the people and vehicles of a
world as geometry instead, so every renderer (the downward camera at 352 px, a crop of a 10 m
square at 2.8 cm/px, a map picture) draws them at its own resolution, and the judge measures
separations to their true footprints:

    ObjectLayer (per object: kind, path start, heading, speed, back-and-forth path length, size,
                 colour, whether the world's texture already holds it)
      .at(t_s)               -> ObjectStates: positions (x_m east, y_m north), headings, velocities
      .nearest_m(x, y, t_s)  -> distance from a ground point to the nearest person / vehicle footprint
      .draw(image, labels, world_m_to_px, t_s) -> objects painted into any view, cm detail when
                                                  its pixels are that small

Motion: an object walks or drives back and forth along one straight path (`path_m` long, from
(x_m, y_m) towards `heading_rad`) at a constant speed, turning round at each end; `speed_m_s` 0
is a person standing or a car parked. The position at a time is a pure function of the layer and
the time, so an episode is deterministic and any process can ask where the people are.

Frames: world metres, x east, y north (`World`); headings are NED-like, 0 = north, +pi/2 = east,
as every yaw in dovesei. Footprints: a person is a disc of diameter `width_m` (0.45-0.6 m); a
vehicle is a rectangle `length_m` along its heading by `width_m` across (a car 4.5 x 1.8 m).

`world_m_to_px` is the 3x3 matrix taking homogeneous world metres (x, y, 1) to output pixel
(col, row, w) with integers at pixel centres: an affine view (a level camera, a crop) has a last
row (0, 0, 1), a tilted camera a general homography. `camera.world_m_to_output_px` builds it for
camera views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import cached_property

import cv2
import numpy as np

from dovesei.shared.errors import DoveseiError

PERSON, VEHICLE = 0, 1
KIND_NAMES = ("person", "vehicle")
PERSON_HEIGHT_M, VEHICLE_HEIGHT_M = 1.7, 1.5  # for their shadows

_SHIFT = 4  # OpenCV sub-pixel bits: polygons placed to 1/16 px
_ONE = 1 << _SHIFT
# Unit outlines in object-local (along heading, across to the right) coordinates, scaled by the size.
_DISC = np.stack([np.cos(np.linspace(0, 2 * math.pi, 16, endpoint=False)),
                  np.sin(np.linspace(0, 2 * math.pi, 16, endpoint=False))], 1)
_CAR_BODY = np.array([(1.0, -0.8), (0.92, -1.0), (-0.94, -1.0), (-1.0, -0.85), (-1.0, 0.85), (-0.94, 1.0),
                      (0.92, 1.0), (1.0, 0.8)])
_CAR_WINDSCREEN = np.array([(0.62, -0.82), (0.62, 0.82), (0.3, 0.74), (0.3, -0.74)])
_CAR_REAR_WINDOW = np.array([(-0.55, -0.74), (-0.55, 0.74), (-0.78, 0.8), (-0.78, -0.8)])
_GLASS = (38, 44, 52)
_HAIR = ((40, 30, 24), (70, 50, 34), (20, 20, 22), (120, 96, 60), (150, 150, 150))
_SKIN = (196, 160, 130)


class ObjectLayerError(DoveseiError, ValueError):
    """An object layer whose arrays disagree or hold impossible values."""


@dataclass(frozen=True)
class ObjectStates:
    """Where every object of a layer is at one time (arrays of the layer's length)."""

    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray  # the way the object faces (a walker turns round at each end)
    vel_east_m_s: np.ndarray
    vel_north_m_s: np.ndarray


# eq=False: arrays compare element-wise; identity is what a cache needs.
@dataclass(frozen=True, eq=False)
class ObjectLayer:
    """The people and vehicles of one world (struct of arrays, one entry per object)."""

    kind: np.ndarray  # (N,) uint8: PERSON or VEHICLE
    x_m: np.ndarray  # (N,) path start, world metres east
    y_m: np.ndarray  # (N,) path start, world metres north
    heading_rad: np.ndarray  # (N,) direction of the path (and of the body at rest), 0 north, +pi/2 east
    speed_m_s: np.ndarray  # (N,) 0: standing / parked
    path_m: np.ndarray  # (N,) length of the back-and-forth path (0 when static)
    phase_m: np.ndarray  # (N,) distance already travelled at t = 0 (spreads the walkers out)
    length_m: np.ndarray  # (N,) along the heading (a person: its diameter)
    width_m: np.ndarray  # (N,) across
    rgb: np.ndarray  # (N, 3) uint8 body / clothes colour
    baked: np.ndarray  # (N,) bool: the world's texture and labels already show it (static only)

    def __post_init__(self) -> None:
        n = self.kind.shape[0] if isinstance(self.kind, np.ndarray) and self.kind.ndim == 1 else -1
        for f in fields(self):
            a = getattr(self, f.name)
            want = (n, 3) if f.name == "rgb" else (n,)
            if not isinstance(a, np.ndarray) or a.shape != want:
                raise ObjectLayerError(f"object layer: {f.name} must be an array of shape {want}, got "
                                       f"{getattr(a, 'shape', type(a).__name__)}")
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ObjectLayerError(f"object layer: {f.name} holds NaN or infinity")
            a.flags.writeable = False
        if n and not np.isin(self.kind, (PERSON, VEHICLE)).all():
            raise ObjectLayerError("object layer: kind must be PERSON (0) or VEHICLE (1)")
        if (self.speed_m_s < 0).any() or (self.path_m < 0).any() or (self.length_m <= 0).any() \
                or (self.width_m <= 0).any():
            raise ObjectLayerError("object layer: speeds and paths must be >= 0, sizes > 0")
        if (self.baked & (self.speed_m_s > 0)).any():
            raise ObjectLayerError("object layer: a moving object cannot be baked into the texture")

    # --- construction -------------------------------------------------------------------

    @staticmethod
    def build(rows: list[tuple]) -> "ObjectLayer":
        """From rows (kind, x_m, y_m, heading_rad, speed_m_s, path_m, phase_m, length_m, width_m,
        (r, g, b), baked)."""
        if not rows:
            return empty_layer()
        cols = list(zip(*rows))
        f64 = [np.asarray(c, np.float64) for c in cols[1:9]]
        return ObjectLayer(np.asarray(cols[0], np.uint8), *f64, np.asarray(cols[9], np.uint8).reshape(-1, 3),
                           np.asarray(cols[10], bool))

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def to_arrays(self, prefix: str = "obj_") -> dict[str, np.ndarray]:
        """The layer as named arrays (for an .npz next to a world)."""
        return {prefix + f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_arrays(arrays, prefix: str = "obj_") -> "ObjectLayer":
        """The inverse of `to_arrays` (KeyError when a field is missing)."""
        return ObjectLayer(**{f.name: np.array(arrays[prefix + f.name]) for f in fields(ObjectLayer)})

    def concat(self, other: "ObjectLayer") -> "ObjectLayer":
        return ObjectLayer(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)])
                              for f in fields(self)})

    def subset(self, keep: np.ndarray) -> "ObjectLayer":
        return ObjectLayer(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def count(self, kind: int, moving: bool | None = None) -> int:
        sel = self.kind == kind
        if moving is not None:
            sel &= (self.speed_m_s > 0) == moving
        return int(sel.sum())

    # --- motion -------------------------------------------------------------------------

    def at(self, t_s: float) -> ObjectStates:
        """Every object's position, heading and velocity at time t_s (seconds since the episode began)."""
        if not math.isfinite(t_s):
            raise ObjectLayerError(f"object layer: time must be finite, got {t_s!r}")
        dist = self.phase_m + self.speed_m_s * t_s
        two = np.maximum(2.0 * self.path_m, 1e-9)
        u = np.mod(dist, two)
        back = u > self.path_m  # on the way back to the start
        s = np.where(back, two - u, u)
        s = np.where(self.path_m > 0, s, 0.0)
        de, dn = np.sin(self.heading_rad), np.cos(self.heading_rad)
        sign = np.where(back, -1.0, 1.0) * (self.path_m > 0)
        return ObjectStates(self.x_m + s * de, self.y_m + s * dn,
                            np.where(back, self.heading_rad + math.pi, self.heading_rad),
                            sign * self.speed_m_s * de, sign * self.speed_m_s * dn)

    def distances_m(self, x_m: float, y_m: float, t_s: float) -> np.ndarray:
        """Distance from a ground point to each object's footprint at t_s (0 inside it)."""
        st = self.at(t_s)
        dx, dy = x_m - st.x_m, y_m - st.y_m
        # Into the object's frame: a along its heading, b across it.
        sh, ch = np.sin(st.heading_rad), np.cos(st.heading_rad)
        a, b = dx * sh + dy * ch, dx * ch - dy * sh
        person = self.kind == PERSON
        disc = np.maximum(np.hypot(dx, dy) - 0.5 * self.width_m, 0.0)
        box = np.hypot(np.maximum(np.abs(a) - 0.5 * self.length_m, 0.0), np.maximum(np.abs(b) - 0.5 * self.width_m, 0.0))
        return np.where(person, disc, box)

    def nearest_m(self, x_m: float, y_m: float, t_s: float, kind: int) -> float | None:
        """Distance from the point to the nearest footprint of that kind at t_s (None: the layer has none)."""
        sel = self.kind == kind
        if not sel.any():
            return None
        return float(self.subset(sel).distances_m(x_m, y_m, t_s).min())

    # --- drawing ------------------------------------------------------------------------

    def draw(self, image: np.ndarray | None, labels: np.ndarray | None, world_m_to_px: np.ndarray, t_s: float,
             label_ids: tuple[int, int], *, shadow_per_m: tuple[float, float] = (0.0, 0.0),
             valid: np.ndarray | None = None, skip_baked: bool = False, baked_labels: bool = True,
             cull: bool = True) -> int:
        """Paint the objects visible in a view into its image (RGB uint8, anti-aliased, in place) and
        labels (class ids, in place; `label_ids` = (person id, vehicle id)); returns how many were
        placed in or near the view.

        `world_m_to_px` maps world metres to the view's pixels (module docstring). Detail follows
        the view's own scale: at centimetres a person has shoulders, head and shadow, a car its
        windows; at decimetres both are a blob of their size, as an orthophoto shows them.
        `shadow_per_m`: ground offset (east, north metres) of a shadow per metre of height (away
        from the sun). Pixels with `valid` False (beyond the world) are left alone.
        `skip_baked`: leave out the objects the world's texture already holds (a view no finer
        than the texture). `baked_labels` False: paint those into the image only, their labels
        being the world's label map's own (which the judge and the camera's labels read).
        `cull` False: place every object of the world before choosing the visible ones (the same
        pixels, slower; for tests of the culling). With no image and `baked_labels` False the
        texture's objects paint nothing, so they are not placed (nor counted) at all: a camera that
        renders labels alone (the simulated perception's) then tests a few hundred objects, not
        the world's thousands.
        """
        h_px, w_px = (image.shape[:2] if image is not None else labels.shape if labels is not None else (0, 0))
        if not len(self) or not h_px:
            return 0
        if image is None and not baked_labels:
            skip_baked = True
        m = np.asarray(world_m_to_px, np.float64)
        inv = np.linalg.inv(m)  # view pixels -> world metres, shared by the culling and the labels
        # Only the objects whose paths come near the view are placed and tested (a world holds
        # thousands, a view a few dozen); the test below then picks the same ones as over all.
        near = self._near_view(m, w_px, h_px, skip_baked, inv) if cull else None
        if near is None:
            return self._draw_rows(image, labels, m, inv, t_s, label_ids, shadow_per_m, valid, skip_baked,
                                   baked_labels, np.arange(len(self)))
        if not near.size:
            return 0
        return self._rows(near)._draw_rows(image, labels, m, inv, t_s, label_ids, shadow_per_m, valid, skip_baked,
                                           baked_labels, near)

    def _draw_rows(self, image: np.ndarray | None, labels: np.ndarray | None, m: np.ndarray, inv: np.ndarray,
                   t_s: float, label_ids: tuple[int, int], shadow_per_m: tuple[float, float],
                   valid: np.ndarray | None, skip_baked: bool, baked_labels: bool, origin: np.ndarray) -> int:
        """`draw` over this layer's every object; `inv` = inverse of `m`; `origin`: each one's index
        in the world's layer (its looks, such as the colour of its hair, follow that index)."""
        h_px, w_px = (image.shape[:2] if image is not None else labels.shape)
        st = self.at(t_s)
        pc = _project(m, np.stack([st.x_m, st.y_m], 1))
        # Pixels per metre at each object (from the map's local Jacobian: exact for an affine view).
        step = _project(m, np.stack([st.x_m + 1.0, st.y_m], 1)) - pc
        ppm = np.hypot(step[:, 0], step[:, 1])
        reach = 0.5 * np.hypot(self.length_m, self.width_m) * ppm + 2.0 + 3.0 * ppm
        show = (pc[:, 0] > -reach) & (pc[:, 0] < w_px + reach) & (pc[:, 1] > -reach) & (pc[:, 1] < h_px + reach)
        if skip_baked:
            show &= ~self.baked
        idx = np.flatnonzero(show)
        # Nothing on or behind the camera's plane is in its view, but such an object projects
        # through infinity to a huge reach and a polygon OpenCV fills as a band across the whole
        # view (a full column of "person" labels in a third of a tilted flight's frames, measured).
        idx = idx[self._in_front(idx, st, m)]
        if not idx.size:
            return 0
        keep_img = image[~valid].copy() if (image is not None and valid is not None and not valid.all()) else None
        keep_lab = labels[~valid].copy() if (labels is not None and valid is not None and not valid.all()) else None
        sx, sy = shadow_per_m
        for kind, local in ((VEHICLE, _CAR_BODY), (PERSON, _DISC)):
            sel = idx[self.kind[idx] == kind]
            if not sel.size:
                continue
            if image is not None:
                bodies = self._outlines(sel, st, local)  # (n, V, 2) world metres
                self._paint(image, m, st, sel, kind, bodies, self._outline_px(m, bodies), ppm[sel], (sx, sy), origin)
            if labels is not None and not baked_labels:
                sel = sel[~self.baked[sel]]
            if labels is not None and sel.size:
                # A pixel takes the class id when its centre lies on the object, as the camera's
                # nearest lookup labels the world. OpenCV's polygon fill also takes every pixel the
                # outline touches: right for large objects, four times too many for one pixel's size.
                small = ppm[sel] * np.maximum(self.length_m[sel], self.width_m[sel]) < 4.0
                if (~small).any():
                    # Outlines element by element: those of a subset are those of the whole, to the bit.
                    body_px = self._outline_px(m, self._outlines(sel[~small], st, local))
                    cv2.fillPoly(labels, list(body_px), int(label_ids[kind]), cv2.LINE_8, _SHIFT)
                if small.any():
                    self._label_centres(labels, inv, st, sel[small], pc[sel[small]], int(label_ids[kind]))
        if keep_img is not None:
            image[~valid] = keep_img
        if keep_lab is not None:
            labels[~valid] = keep_lab
        return int(idx.size)

    # --- culling ------------------------------------------------------------------------

    @cached_property
    def _path_box_m(self) -> np.ndarray:
        """(4, N) world box (west, east, south, north) of every place each object can be: its path
        from the start to the far end, 1 m wider all round (the positions are computed in floating point)."""
        far_x = self.x_m + self.path_m * np.sin(self.heading_rad)
        far_y = self.y_m + self.path_m * np.cos(self.heading_rad)
        return np.stack([np.minimum(self.x_m, far_x) - 1.0, np.maximum(self.x_m, far_x) + 1.0,
                         np.minimum(self.y_m, far_y) - 1.0, np.maximum(self.y_m, far_y) + 1.0])

    @cached_property
    def _reach_m(self) -> float:
        """The largest half-diagonal of an object (m): how far its outline reaches from its centre."""
        return float(0.5 * np.hypot(self.length_m, self.width_m).max())

    def _near_view(self, m: np.ndarray, w_px: int, h_px: int, skip_baked: bool,
                   inv: np.ndarray | None = None) -> np.ndarray | None:
        """Indices (ascending) of the objects whose paths meet the world box of what `_draw_rows`
        could show in a w x h view: every object it draws that is in front of the camera and
        reaches into the view. None: the margin such a box needs reaches the horizon; draw over all.

        `_draw_rows` paints an object's outline and shadow, (half-diagonal + 3 m) about its centre
        (its `reach`). Let M be a margin (pixels) and S a bound on the pixels per metre, in any
        direction, over the view widened by M: when (largest half-diagonal + 3 m) x S + 2 <= M, an
        object whose centre lies beyond the widened view would have to cross a band M pixels wide,
        at least M / S metres, to paint a pixel of the view, and none reaches that far. The widened
        view is a convex quadrilateral on the ground while it stays below the horizon, so its
        world box holds every centre that can paint. Pixel p = (A x + t) / w moves by
        |A e - p m_e| / w per metre along e (east or north; m_e the map's perspective entry): the
        numerator is convex in p and 1 / w affine, so both are largest at the quadrilateral's
        corners and S comes from the four corners alone (exact for an affine view).
        """
        inv = np.linalg.inv(m) if inv is None else inv
        margin_px = 2.0
        for _ in range(6):
            corners = np.array([(-margin_px, -margin_px), (w_px + margin_px, -margin_px),
                                (-margin_px, h_px + margin_px), (w_px + margin_px, h_px + margin_px)])
            z = corners @ inv[2, :2] + inv[2, 2]  # 1 / w at each corner
            if (z <= 0.0).any():
                return None  # past the horizon: points behind the camera project into the margin
            # |dp/de| = |A e - p m_e| / w: each factor largest at a corner (module docstring of the
            # method); the two directions' bounds give one for any direction (Frobenius norm).
            per_m = math.hypot(*(np.hypot(m[0, e] - corners[:, 0] * m[2, e], m[1, e] - corners[:, 1] * m[2, e]).max()
                                 for e in (0, 1))) * float(z.max())
            need_px = (self._reach_m + 3.0) * per_m + 2.0
            if need_px <= margin_px:
                break
            margin_px = 1.2 * need_px
        else:
            return None
        ground = corners @ inv[:2, :2].T + inv[:2, 2]
        ground /= z[:, None]
        west, east, south, north = ground[:, 0].min(), ground[:, 0].max(), ground[:, 1].min(), ground[:, 1].max()
        # Without the texture's objects, only the others' boxes are tested (a world's objects are
        # mostly baked: 654 of 14,607 are not in the default synthetic world).
        idx, box = self._unbaked_boxes if skip_baked else (None, self._path_box_m)
        near = (box[0] <= east) & (box[1] >= west) & (box[2] <= north) & (box[3] >= south)
        return np.flatnonzero(near) if idx is None else idx[near]

    @cached_property
    def _unbaked_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """(indices, path boxes) of the objects the texture does not hold, ascending."""
        idx = np.flatnonzero(~self.baked)
        return idx, self._path_box_m[:, idx]

    def _rows(self, idx: np.ndarray) -> "ObjectLayer":
        """The objects at `idx`, unchecked (a view of a checked layer for drawing; `subset` checks)."""
        rows = object.__new__(ObjectLayer)
        for f in fields(self):
            object.__setattr__(rows, f.name, getattr(self, f.name)[idx])
        return rows

    def _in_front(self, idx: np.ndarray, st: ObjectStates, m: np.ndarray) -> np.ndarray:
        """Whether each object at `idx`, its shadow's 3 m included, lies wholly in front of the
        camera's plane (w > 0 over the box of its reach: w is affine in world metres)."""
        r = 0.5 * np.hypot(self.length_m[idx], self.width_m[idx]) + 3.0
        w = st.x_m[idx] * m[2, 0] + st.y_m[idx] * m[2, 1] + m[2, 2]
        return w - r * (abs(m[2, 0]) + abs(m[2, 1])) > 0.0

    def _paint(self, image: np.ndarray, m: np.ndarray, st: ObjectStates, sel: np.ndarray, kind: int,
               bodies: np.ndarray, body_px: np.ndarray, ppm: np.ndarray, shadow: tuple[float, float],
               origin: np.ndarray) -> None:
        """Shadows, bodies and, where an object spans ~6 px or more, its parts (head, windows)."""
        sx, sy = shadow
        height = PERSON_HEIGHT_M if kind == PERSON else VEHICLE_HEIGHT_M
        for j, i in enumerate(sel):
            across_px = ppm[j] * self.width_m[i]
            if (sx or sy) and across_px >= 1.0:
                streak = bodies[j] + (sx * height, sy * height) if kind == VEHICLE else \
                    self._shadow_streak(i, st, sx * height, sy * height)
                _darken(image, _fixed(_project(m, streak)), 0.55)
            rgb = tuple(int(c) for c in self.rgb[i])
            if kind == PERSON and across_px >= 6.0:
                # Seen from above: shoulders deeper than wide, a head of hair, a glimpse of face.
                one = np.array([i])
                for local, colour in ((_DISC * (0.55, 1.0), rgb), (_DISC * 0.36, _HAIR[origin[i] % len(_HAIR)]),
                                      (_DISC * 0.2 + (0.12, 0.0), _SKIN)):
                    part = self._outlines(one, st, local)[0]
                    cv2.fillPoly(image, [_fixed(_project(m, part))], colour, cv2.LINE_AA, _SHIFT)
                continue
            cv2.fillPoly(image, [body_px[j]], rgb, cv2.LINE_AA, _SHIFT)
            if kind == VEHICLE and across_px >= 6.0:
                one = np.array([i])
                for local in (_CAR_WINDSCREEN, _CAR_REAR_WINDOW):
                    part = self._outlines(one, st, local)[0]
                    cv2.fillPoly(image, [_fixed(_project(m, part))], _GLASS, cv2.LINE_AA, _SHIFT)

    def _label_centres(self, labels: np.ndarray, inv: np.ndarray, st: ObjectStates, sel: np.ndarray,
                       pc: np.ndarray, label_id: int) -> None:
        """Label the pixels around each small object whose centres lie on its footprint (`inv`:
        the view's pixels -> world metres)."""
        cells = np.round(pc)[:, None, :] + _CENTRE_OFFSETS[None]  # (n, 25, 2) candidate pixel centres
        world = _project(inv, cells.reshape(-1, 2)).reshape(len(sel), -1, 2)
        dx, dy = world[..., 0] - st.x_m[sel][:, None], world[..., 1] - st.y_m[sel][:, None]
        sh, ch = np.sin(st.heading_rad[sel])[:, None], np.cos(st.heading_rad[sel])[:, None]
        a, b = dx * sh + dy * ch, dx * ch - dy * sh
        half_l, half_w = 0.5 * self.length_m[sel][:, None], 0.5 * self.width_m[sel][:, None]
        person = (self.kind[sel] == PERSON)[:, None]
        inside = np.where(person, a * a + b * b <= half_w * half_w, (np.abs(a) <= half_l) & (np.abs(b) <= half_w))
        col, row = cells[..., 0].astype(np.int64), cells[..., 1].astype(np.int64)
        inside &= (col >= 0) & (col < labels.shape[1]) & (row >= 0) & (row < labels.shape[0])
        labels[row[inside], col[inside]] = label_id

    @staticmethod
    def _outline_px(m: np.ndarray, bodies: np.ndarray) -> np.ndarray:
        """(n, V, 1, 2) fixed-point pixels of (n, V, 2) outlines in world metres, as fillPoly takes them."""
        return _fixed(_project(m, bodies.reshape(-1, 2))).reshape(len(bodies), -1, 1, 2)

    def _outlines(self, sel: np.ndarray, st: ObjectStates, local: np.ndarray) -> np.ndarray:
        """(n, V, 2) world metres of a unit outline (along, across) scaled to each selected object
        and placed at its pose."""
        a = local[None, :, 0] * (0.5 * self.length_m[sel])[:, None]
        b = local[None, :, 1] * (0.5 * self.width_m[sel])[:, None]
        sh, ch = np.sin(st.heading_rad[sel])[:, None], np.cos(st.heading_rad[sel])[:, None]
        # along -> (east sin h, north cos h); across (to the right) -> (east cos h, north -sin h)
        return np.stack([st.x_m[sel][:, None] + a * sh + b * ch, st.y_m[sel][:, None] + a * ch - b * sh], 2)

    def _shadow_streak(self, i: int, st: ObjectStates, dx_m: float, dy_m: float) -> np.ndarray:
        """A standing person's shadow: a thin band from the feet to where the sun throws the head."""
        r = 0.3 * self.width_m[i]
        norm = math.hypot(dx_m, dy_m) or 1.0
        px, py = -dy_m / norm * r, dx_m / norm * r
        x, y = st.x_m[i], st.y_m[i]
        return np.array([(x + px, y + py), (x + dx_m + px, y + dy_m + py), (x + dx_m - px, y + dy_m - py),
                         (x - px, y - py)])


def empty_layer() -> ObjectLayer:
    """A layer without objects (worlds nobody populated)."""
    z = np.zeros(0)
    return ObjectLayer(np.zeros(0, np.uint8), z, z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(),
                       np.zeros((0, 3), np.uint8), np.zeros(0, bool))


# The 5 x 5 pixels around an object's centre pixel, (col, row) offsets, rows first.
_CENTRE_OFFSETS = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2)
_CENTRE_OFFSETS.flags.writeable = False


def _project(m: np.ndarray, pts_m: np.ndarray) -> np.ndarray:
    """(n, 2) world metres -> (n, 2) output pixels (col, row) through a 3x3 map.

    Element by element, not a matrix product: BLAS rounds a product's rows differently with the
    number of rows, and a culled view must place each object exactly as the whole layer would."""
    x, y = pts_m[:, 0:1], pts_m[:, 1:2]
    h = x * m[:, 0] + y * m[:, 1] + m[:, 2]
    return h[:, :2] / h[:, 2:3]


def _fixed(px: np.ndarray) -> np.ndarray:
    # OpenCV's sub-pixel polygons put integer pixel centres at k * 2^shift; clamp to keep int32 safe.
    return np.round(np.clip(px, -1e5, 1e5) * _ONE).astype(np.int32).reshape(-1, 1, 2)


def _darken(image: np.ndarray, poly: np.ndarray, k: float) -> None:
    """Multiply the image by k inside a polygon (a shadow falls on whatever is there)."""
    x, y, w, h = cv2.boundingRect(poly // _ONE)
    x0, y0 = max(x - 1, 0), max(y - 1, 0)
    x1, y1 = min(x + w + 2, image.shape[1]), min(y + h + 2, image.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [poly - np.array([x0, y0], np.int32) * _ONE], 255, cv2.LINE_AA, _SHIFT)
    patch = image[y0:y1, x0:x1].astype(np.float32)
    f = 1.0 - (1.0 - k) * mask.astype(np.float32)[..., None] / 255.0
    image[y0:y1, x0:x1] = (patch * f).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class Population:
    """A world's object layer with what drawing it needs from the world: the class ids a person
    and a vehicle take in its label map, and where its sun throws shadows."""

    layer: ObjectLayer
    label_ids: tuple[int, int]  # (person id, vehicle id) of the world's classes
    shadow_per_m: tuple[float, float] = (0.0, 0.0)  # ground offset (east, north) per metre of height

    def draw(self, image: np.ndarray | None, labels: np.ndarray | None, world_m_to_px: np.ndarray, t_s: float,
             valid: np.ndarray | None = None, skip_baked: bool = False, baked_labels: bool = True,
             cull: bool = True) -> int:
        """`ObjectLayer.draw` with this world's label ids and sun."""
        return self.layer.draw(image, labels, world_m_to_px, t_s, self.label_ids, shadow_per_m=self.shadow_per_m,
                               valid=valid, skip_baked=skip_baked, baked_labels=baked_labels, cull=cull)

    def nearest_m(self, x_m: float, y_m: float, t_s: float) -> tuple[float | None, float | None]:
        """(nearest person, nearest vehicle) footprint distances from a ground point at t_s (None: none)."""
        return self.layer.nearest_m(x_m, y_m, t_s, PERSON), self.layer.nearest_m(x_m, y_m, t_s, VEHICLE)
