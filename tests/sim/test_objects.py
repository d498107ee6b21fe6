"""People and vehicles as objects of the world: motion, placement rules, drawing at any resolution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dovesei.sim.camera import CameraModel, render
from dovesei.sim.objects import PERSON, VEHICLE, ObjectLayer, ObjectLayerError, Population, empty_layer
from dovesei.sim.populate import Density, class_roles, populate
from dovesei.sim.synthetic.generate import CAR, GRASS, PERSON as PERSON_ID, PLAZA, ROAD, SIDEWALK, SyntheticParams, \
    generate_world
from dovesei.sim.world import ClassInfo, World, load_world


def one(kind=PERSON, x=50.0, y=50.0, heading=math.pi / 2, speed=1.2, path=10.0, phase=0.0, length=0.5,
        width=0.5, baked=False) -> ObjectLayer:
    return ObjectLayer.build([(kind, x, y, heading, speed, path, phase, length, width, (200, 40, 40), baked)])


def test_a_walking_person_goes_back_and_forth_along_its_path_at_its_speed() -> None:
    layer = one()  # heading east, 10 m path, 1.2 m/s
    ts = np.arange(0.0, 40.0, 0.25)
    xs = np.array([layer.at(t).x_m[0] for t in ts])
    ys = np.array([layer.at(t).y_m[0] for t in ts])
    assert np.allclose(ys, 50.0) and xs.min() == pytest.approx(50.0) and xs.max() == pytest.approx(60.0, abs=0.3)
    steps = np.abs(np.diff(xs)) / 0.25
    assert np.all(steps <= 1.2 + 1e-9) and np.median(steps) == pytest.approx(1.2)
    # Out and back: 10 m at 1.2 m/s takes 8.33 s; then it faces the other way and walks west.
    back = layer.at(10.0)
    assert back.x_m[0] == pytest.approx(60.0 - 1.2 * (10.0 - 10.0 / 1.2))
    assert back.vel_east_m_s[0] == pytest.approx(-1.2) and back.heading_rad[0] == pytest.approx(1.5 * math.pi)
    assert layer.at(100.0).x_m[0] == layer.at(100.0).x_m[0]  # a pure function of time


def test_distances_are_to_the_footprint() -> None:
    person = one(speed=0.0, path=0.0, width=0.6)
    assert person.nearest_m(53.3, 50.0, 0.0, PERSON) == pytest.approx(3.0)  # centre 3.3 m, radius 0.3 m
    assert person.nearest_m(50.1, 50.0, 0.0, PERSON) == 0.0
    assert person.nearest_m(50.0, 50.0, 0.0, VEHICLE) is None
    car = one(kind=VEHICLE, heading=0.0, speed=0.0, path=0.0, length=4.5, width=1.8)  # facing north
    assert car.nearest_m(50.0, 50.0 + 2.25 + 5.0, 0.0, VEHICLE) == pytest.approx(5.0)  # off its bumper
    assert car.nearest_m(50.0 + 0.9 + 5.0, 50.0, 0.0, VEHICLE) == pytest.approx(5.0)  # off its side
    assert car.nearest_m(50.0 + 0.9 + 3.0, 50.0 + 2.25 + 4.0, 0.0, VEHICLE) == pytest.approx(5.0)  # off a corner


def test_bad_layers_are_refused_with_the_field_named() -> None:
    with pytest.raises(ObjectLayerError, match="speeds"):
        one(speed=-1.0)
    with pytest.raises(ObjectLayerError, match="moving object cannot be baked"):
        one(baked=True)
    with pytest.raises(ObjectLayerError, match="x_m"):
        ObjectLayer(**{**{k: v for k, v in vars(one()).items()}, "x_m": np.array([np.nan])})
    with pytest.raises(ObjectLayerError, match="time"):
        one().at(float("nan"))


def _strip_world(size_m: float = 200.0, gsd_m: float = 0.25) -> World:
    """A road running north-south through grass, a sidewalk strip beside it."""
    n = int(size_m / gsd_m)
    lab = np.full((n, n), GRASS, np.uint8)
    lab[:, n // 2 - 40: n // 2 + 40] = ROAD  # 20 m wide
    lab[:, n // 2 + 40: n // 2 + 48] = SIDEWALK
    img = np.full((n, n, 3), 90, np.uint8)
    classes = {GRASS: ClassInfo("grass", True), ROAD: ClassInfo("road", False), SIDEWALK: ClassInfo("sidewalk", False),
               PERSON_ID: ClassInfo("person", False), CAR: ClassInfo("car", False)}
    layer = populate(lab, gsd_m, {c: i.name for c, i in classes.items()}, 3,
                     Density(walkers_per_ha=20.0, standing_per_ha=5.0, cars_per_ha_road=30.0))
    return World(img, lab, gsd_m, classes, "strip", population=Population(layer, (PERSON_ID, CAR)))


def test_cars_drive_on_the_road_and_people_walk_on_walkable_ground_the_whole_time() -> None:
    world = _strip_world()
    layer = world.population.layer
    cars, people = layer.kind == VEHICLE, layer.kind == PERSON
    assert (cars & (layer.speed_m_s > 0)).sum() >= 5 and (people & (layer.speed_m_s > 0)).sum() >= 20
    assert np.all(layer.speed_m_s[cars] >= 4.0) and np.all(layer.speed_m_s[cars] <= 12.0)
    walking = people & (layer.speed_m_s > 0)
    assert np.all(layer.speed_m_s[walking] >= 1.0) and np.all(layer.speed_m_s[walking] <= 1.5)
    for t in np.arange(0.0, 120.0, 1.7):
        st = layer.at(t)
        ids = world.labels[world.height_px - 1 - np.floor(st.y_m / world.gsd_m).astype(int),
                           np.floor(st.x_m / world.gsd_m).astype(int)]
        assert np.all(ids[cars] == ROAD)
        assert np.all(np.isin(ids[people], (GRASS, SIDEWALK)))
        # The whole car stays on the road: its corners too (road spans x in [90, 110) m).
        sh, ch = np.sin(st.heading_rad[cars]), np.cos(st.heading_rad[cars])
        for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            cx = st.x_m[cars] + a * 0.5 * layer.length_m[cars] * sh + b * 0.5 * layer.width_m[cars] * ch
            assert np.all((cx >= 90.0) & (cx < 110.0))
    # North-south road: every car drives along it.
    assert np.allclose(np.abs(np.cos(layer.heading_rad[cars])), 1.0, atol=1e-9)


def test_placement_reads_class_names_never_the_safe_flag() -> None:
    walk, drive, crowd = class_roles({1: "road", 2: "land (unpaved area)", 3: "building", 4: "plaza", 5: "car"})
    assert drive[1] and not walk[1] and walk[2] and not walk[3] and crowd[4] and not (walk[5] or drive[5])
    lab = np.full((400, 400), 3, np.uint8)
    assert len(populate(lab, 0.25, {3: "building"}, 0)) == 0  # nowhere to stand


def test_the_same_seed_gives_the_same_population_and_another_seed_another() -> None:
    world = _strip_world()
    names = {c: i.name for c, i in world.classes.items()}
    dens = Density(walkers_per_ha=20.0, cars_per_ha_road=30.0)
    a, b = populate(world.labels, 0.25, names, 3, dens), populate(world.labels, 0.25, names, 3, dens)
    c = populate(world.labels, 0.25, names, 4, dens)
    assert np.array_equal(a.x_m, b.x_m) and np.array_equal(a.phase_m, b.phase_m)
    assert len(a) != len(c) or not np.array_equal(a.x_m, c.x_m)


def test_a_person_is_drawn_at_the_views_resolution_with_its_label() -> None:
    world = _strip_world()
    layer = ObjectLayer.build([(PERSON, 40.0, 60.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, (200, 40, 40), False)])
    w = World(world.image_rgb, world.labels, world.gsd_m, world.classes, "one", population=Population(layer, (PERSON_ID, CAR)))
    counts = {}
    for alt in (100.0, 40.0, 10.0, 3.0):
        img, lab, _ = render(w, 40.0, 60.0, alt, 0.0, CameraModel())
        px_m = CameraModel().metres_per_px(alt)
        counts[alt] = int((lab == PERSON_ID).sum())
        # About its area in pixels (a disc of 0.25 m radius; centre-sampled, so a few pixels either way).
        assert counts[alt] == pytest.approx(max(1.0, math.pi * 0.25 ** 2 / px_m ** 2), rel=0.35, abs=3.0)
        assert tuple(img[175:177, 175:177].reshape(-1, 3).max(0)) != (90, 90, 90)  # drawn where it stands
    assert counts[3.0] > 100 * counts[100.0]


def test_the_synthetic_generator_keeps_its_people_and_cars_as_baked_objects() -> None:
    gen = generate_world(SyntheticParams(seed=3, size_m=300.0, gsd_m=0.25))
    baked = gen.baked
    assert baked.baked.all() and (baked.speed_m_s == 0).all()
    assert baked.count(PERSON) > 5 and baked.count(VEHICLE) > 5
    h = gen.labels.shape[0]
    rows = h - 1 - np.floor(baked.y_m / 0.25).astype(int)
    cols = np.floor(baked.x_m / 0.25).astype(int)
    ids = gen.labels[np.clip(rows, 0, h - 1), np.clip(cols, 0, h - 1)]
    # Most stand on their own label; the rest have their centre under a crown or just off the edge.
    assert np.mean(ids[baked.kind == PERSON] == PERSON_ID) > 0.8 and np.mean(ids[baked.kind == VEHICLE] == CAR) > 0.8
    for kind, label in ((PERSON, PERSON_ID), (VEHICLE, CAR)):
        for i in np.flatnonzero(baked.kind == kind):  # each one's label shows within its footprint
            reach = int(np.ceil(0.5 * max(baked.length_m[i], baked.width_m[i]) / 0.25)) + 1
            window = gen.labels[max(0, rows[i] - reach):rows[i] + reach + 1, max(0, cols[i] - reach):cols[i] + reach + 1]
            assert (window == label).any(), (kind, baked.x_m[i], baked.y_m[i])


@pytest.mark.parametrize("spec", ["synthetic:style=coast,seed=4,size_m=400", "synthetic:style=parkland,seed=5,size_m=400"])
def test_every_person_the_judge_counts_is_a_person_the_simulator_draws(spec: str) -> None:
    # The judge reads the labels; the camera and the close look draw the object layer. A person
    # whose centre a tree's crown covered, or who stood on the world's edge, once left label
    # pixels and no object: a "person" no perception could ever see (the coast had 50 of 2059).
    import cv2

    world = load_world(spec)
    person_id = next(c for c, i in world.classes.items() if i.name == "person")
    n, blobs = cv2.connectedComponents((world.labels == person_id).astype(np.uint8), connectivity=8)
    layer = world.population.layer
    people = np.flatnonzero((layer.kind == PERSON) & layer.baked)
    st = layer.at(0.0)
    assert n > 20
    for k in range(1, n):
        r, c = np.nonzero(blobs == k)
        x, y = (c + 0.5) * world.gsd_m, (world.height_px - r - 0.5) * world.gsd_m
        gap_m = np.hypot(st.x_m[people][:, None] - x, st.y_m[people][:, None] - y).min()
        assert gap_m <= 0.5 * layer.width_m[people].max() + world.gsd_m, (k, x.mean(), y.mean(), gap_m)


def test_every_style_has_people_and_cars_and_the_crowded_one_has_crowds() -> None:
    moving = {}
    for style in ("city", "downtown", "villas", "desert", "coast", "parkland", "crowded"):
        world = load_world(f"synthetic:style={style},seed=3,size_m=400,gsd_m=0.5")
        layer = world.population.layer
        assert layer.count(PERSON) > 0 and layer.count(VEHICLE) > 0, style
        assert layer.count(PERSON, moving=True) > 0, style
        moving[style] = layer.count(PERSON)
    assert moving["crowded"] > 3 * moving["city"]


def test_a_labelled_world_folder_gets_people_and_cars_by_the_same_rules() -> None:
    world = load_world("dubai")
    pop = world.population
    assert pop is not None and pop.layer.count(PERSON, moving=True) > 0 and pop.layer.count(VEHICLE, moving=True) > 0
    person_id, car_id = pop.label_ids
    assert world.classes[person_id].name == "person" and not world.classes[person_id].safe
    assert world.classes[car_id].name == "car" and not world.classes[car_id].safe
    st = pop.layer.at(30.0)
    ids = world.labels[world.height_px - 1 - np.floor(st.y_m / world.gsd_m).astype(int),
                       np.floor(st.x_m / world.gsd_m).astype(int)]
    names = np.array([world.classes[int(i)].name for i in ids])
    assert np.all(names[pop.layer.kind == VEHICLE] == "road")
    assert not np.any(names[pop.layer.kind == PERSON] == "building")


def test_an_empty_layer_draws_nothing() -> None:
    img = np.zeros((10, 10, 3), np.uint8)
    assert empty_layer().draw(img, None, np.eye(3), 0.0, (1, 2)) == 0 and not img.any()


def _edge_layer(world: World) -> ObjectLayer:
    """The strip world's population plus people and cars placed across the edges of the test views."""
    extra = []
    for i, (x, y) in enumerate([(100.0 + dx, 100.0 + dy) for dx in (-30.0, -18.3, 0.0, 17.9, 29.6)
                                for dy in (-29.8, -17.6, 18.1, 30.2)]):
        kind = VEHICLE if i % 3 == 0 else PERSON
        size = (4.5, 1.8) if kind == VEHICLE else (0.55, 0.55)
        extra.append((kind, x, y, 0.3 * i, 1.3 if i % 2 else 0.0, 6.0 if i % 2 else 0.0, 0.7 * i, *size,
                      (30 + 7 * i, 200 - 5 * i, 90), i % 4 == 0))  # some standing ones in the texture (baked)
    return world.population.layer.concat(ObjectLayer.build(extra))


@pytest.mark.parametrize("pose", [
    # (x_m, y_m, alt_m, yaw_rad, roll_rad, pitch_rad, t_s): nadir high and low, tilted both ways.
    (100.0, 100.0, 100.0, 0.0, 0.0, 0.0, 0.0),
    (100.0, 100.0, 40.0, 0.7, 0.0, 0.0, 12.5),
    (96.0, 104.0, 20.0, -2.1, 0.0, 0.0, 33.0),
    (100.0, 100.0, 45.0, 0.4, 0.3, -0.25, 7.0),
    (103.0, 98.0, 25.0, 2.9, -0.35, 0.2, 51.0),
    (100.0, 100.0, 60.0, -1.0, 0.5, 0.4, 90.0),
    (12.0, 190.0, 30.0, 1.2, 0.2, 0.1, 3.0),  # over the world's corner: part of the view is beyond it
])
def test_the_culled_drawing_is_pixel_equal_to_placing_every_object(pose) -> None:
    from dovesei.sim.camera import pixel_to_world_affine, pixel_to_world_homography, world_m_to_output_px

    world = _strip_world()
    pop = Population(_edge_layer(world), (PERSON_ID, CAR), shadow_per_m=(0.4, -0.3))
    x, y, alt, yaw, roll, pitch, t = pose
    cam = CameraModel()
    m0 = pixel_to_world_affine(world, x, y, alt, yaw, cam) if roll == pitch == 0.0 else \
        pixel_to_world_homography(world, x, y, alt, yaw, roll, pitch, cam)
    m = world_m_to_output_px(world, m0)
    base_img = np.random.default_rng(1).integers(0, 255, (cam.height_px, cam.width_px, 3), dtype=np.uint8)
    base_lab = np.full((cam.height_px, cam.width_px), GRASS, np.uint8)
    out = {}
    for cull in (True, False):
        for baked_labels in (True, False):
            img, lab = base_img.copy(), base_lab.copy()
            n = pop.draw(img, lab, m, t, skip_baked=False, baked_labels=baked_labels, cull=cull)
            out[cull, baked_labels] = (n, img, lab)
    for baked_labels in (True, False):
        (n_c, img_c, lab_c), (n_a, img_a, lab_a) = out[True, baked_labels], out[False, baked_labels]
        # Placing every object also counts ones just in front of the camera's plane, far behind
        # the view, whose huge scale there stretches their reach over it: they paint nothing.
        assert 0 < n_c <= n_a
        assert np.array_equal(img_c, img_a) and np.array_equal(lab_c, lab_a)
    # Labels alone (the simulated perception's camera): the texture's own objects paint nothing
    # there and are not even placed; the labels are those drawn beside an image.
    assert pop.layer.baked.any() and (~pop.layer.baked).any()
    for cull in (True, False):
        lab = base_lab.copy()
        n_lab = pop.draw(None, lab, m, t, skip_baked=False, baked_labels=False, cull=cull)
        assert np.array_equal(lab, out[True, False][2]) and n_lab <= out[cull, False][0]
    # Objects straddling the view's edge are drawn (some pixels, not all of them, inside the view).
    assert (out[True, True][2] == PERSON_ID).any() or (out[True, True][2] == CAR).any()
    # And the cull left part of the world out (the 100 m view sees nearly all of this 200 m world);
    # a view tilted 37 deg needs a margin up to the horizon and is drawn over every object.
    near = pop.layer._near_view(np.asarray(m, np.float64), cam.width_px, cam.height_px, False)
    if math.hypot(roll, pitch) < 0.6:
        assert near is not None and (alt >= 100.0 or near.size < 0.8 * len(pop.layer))


def test_a_crop_draws_the_same_culled_or_not() -> None:
    from dovesei.sim.camera import pixel_to_world_affine, world_m_to_output_px

    world = _strip_world()
    pop = Population(_edge_layer(world), (PERSON_ID, CAR), shadow_per_m=(0.4, -0.3))
    for cx, cy, yaw, t in ((100.0, 100.0, 0.3, 4.0), (117.9, 82.4, -1.4, 20.0), (70.0, 129.8, 2.0, 0.0)):
        side_m, px = 10.0, 356  # a close look: 2.8 cm per pixel
        cam = CameraModel(px, px, 73.0)
        m = world_m_to_output_px(world, pixel_to_world_affine(world, cx, cy, side_m / (2 * math.tan(math.radians(36.5))),
                                                              yaw, cam))
        imgs = []
        for cull in (True, False):
            img = np.full((px, px, 3), 120, np.uint8)
            lab = np.full((px, px), GRASS, np.uint8)
            imgs.append((pop.draw(img, lab, m, t, cull=cull), img, lab))
        assert imgs[0][0] == imgs[1][0]
        assert np.array_equal(imgs[0][1], imgs[1][1]) and np.array_equal(imgs[0][2], imgs[1][2])


def test_people_on_the_cameras_plane_paint_no_band_across_a_tilted_view() -> None:
    """A person where the tilted camera's plane meets the ground projects through infinity; drawn,
    OpenCV fills that outline as a band across the whole view. Nothing there is in the view."""
    from dovesei.sim.camera import pixel_to_world_homography, world_m_to_output_px

    world = _strip_world()
    cam = CameraModel()
    m = world_m_to_output_px(world, pixel_to_world_homography(world, 100.0, 100.0, 30.0, 0.4, 0.2, 0.1, cam))
    # Points on w = 0 along the line m[2] . (x, y, 1) = 0, across the world.
    a, b, c = m[2]
    rows = []
    for x in np.linspace(-100.0, 300.0, 81):
        y = -(a * x + c) / b
        rows.append((PERSON, float(x), float(y), 0.3, 0.0, 0.0, 0.0, 0.55, 0.55, (200, 40, 40), False))
    pop = Population(ObjectLayer.build(rows), (PERSON_ID, CAR))
    for cull in (True, False):
        lab = np.full((cam.height_px, cam.width_px), GRASS, np.uint8)
        img = np.zeros((cam.height_px, cam.width_px, 3), np.uint8)
        with np.errstate(divide="ignore", invalid="ignore"):  # the centres project to infinity
            pop.draw(img, lab, m, 0.0, cull=cull)
        assert (lab == GRASS).all() and not img.any()
