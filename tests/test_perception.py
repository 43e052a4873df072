"""Kinect camera sources and CAD-registration perception (hardware/kinect.py, perception.py)."""

import sys
import types

import numpy as np
import pytest
import trimesh
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from dexdrake.errors import DexdrakeError
from dexdrake.hardware.kinect import (
    KINECT_COLOR_720P, CameraIntrinsics, DepthNoiseModel, DrakeRenderedCamera, EndOfSequence,
    FrameError, K4ADevice, RecordedSequence, RgbdFrame, load_frame, look_at, save_frame,
    save_sequence,
)
from dexdrake.hardware.perception import (
    GreenScreenConfig, ObjectPoseEstimator, RegistrationConfig, backproject, segment_object,
    transform_points,
)

K_SMALL = KINECT_COLOR_720P.scaled(160, 90)
GREEN = (40, 170, 50)
RED = (200, 60, 40)


def _frame(color=None, depth=None, k=K_SMALL, t=0.0, X_WC=None) -> RgbdFrame:
    if color is None:
        color = np.zeros((k.height, k.width, 3), np.uint8)
        color[:] = GREEN
    if depth is None:
        depth = np.full((k.height, k.width), 700, np.uint16)
    return RgbdFrame(color, depth, k, t, X_WC)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("DEXDRAKE_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield
    mp.undo()


@pytest.fixture(scope="module")
def l_shape(tmp_path_factory):
    """A non-symmetric watertight object (bar + side block + peg), origin at the COM."""
    a = trimesh.creation.box((0.10, 0.04, 0.03))
    b = trimesh.creation.box((0.03, 0.06, 0.03))
    b.apply_translation((0.035, 0.05, 0.0))
    c = trimesh.creation.cylinder(0.012, 0.05)
    c.apply_translation((-0.03, 0.0, 0.035))
    mesh = trimesh.boolean.union([a, b, c])
    mesh.apply_translation(-mesh.center_mass)
    path = tmp_path_factory.mktemp("mesh") / "l_shape.obj"
    mesh.export(path)
    return path, float(-mesh.bounds[0, 2])


# ---------------------------------------------------------------- frames and sources

def test_intrinsics_scaling_round_trips_and_keeps_pixel_centres():
    k = KINECT_COLOR_720P.scaled(640, 360)
    assert k.fx == pytest.approx(305.9) and k.cx == pytest.approx(319.4)
    back = k.scaled(1280, 720)
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((611.8, 611.9, 639.3, 365.9))


@pytest.mark.parametrize("make, match", [
    (lambda: _frame(color=np.zeros((90, 160, 3), np.float32)), "color"),
    (lambda: _frame(color=np.zeros((90, 160), np.uint8)), "color"),
    (lambda: _frame(depth=np.zeros((90, 160), np.float32)), "depth"),
    (lambda: _frame(depth=np.zeros((80, 160), np.uint16)), "not aligned"),
    (lambda: _frame(np.zeros((90, 160, 3), np.uint8), np.zeros((90, 160), np.uint16),
                    k=KINECT_COLOR_720P.scaled(320, 180)), "intrinsics are for"),
    (lambda: _frame(t=float("nan")), "timestamp"),
    (lambda: _frame(X_WC=np.eye(4)), "X_WC"),
    (lambda: CameraIntrinsics(160, 90, -1.0, 70.0, 80.0, 45.0), "focal"),
    (lambda: CameraIntrinsics(160, 90, 70.0, 70.0, 200.0, 45.0), "principal point"),
    (lambda: CameraIntrinsics(160, 90, float("inf"), 70.0, 80.0, 45.0), "finite"),
])
def test_frame_validation_refuses_bad_frames(make, match):
    with pytest.raises(FrameError, match=match):
        make()


@pytest.mark.parametrize("make, match", [
    (lambda: RegistrationConfig(voxel=0.0), "voxel"),
    (lambda: RegistrationConfig(min_fitness=1.5), "min_fitness"),
    (lambda: RegistrationConfig(max_contradicted=-0.1), "max_contradicted"),
    (lambda: RegistrationConfig(free_space_window_factor=-1), "free_space_window_factor"),
    (lambda: GreenScreenConfig(min_depth_mm=900, max_depth_mm=500), "depth range"),
    (lambda: GreenScreenConfig(min_component_px=-1), "min_component_px"),
    (lambda: DepthNoiseModel(dropout=-0.1), "dropout"),
])
def test_bad_configurations_are_refused(make, match):
    with pytest.raises(DexdrakeError, match=match):
        make()


def test_recorded_sequence_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    X = RigidTransform(RollPitchYaw(0.1, -0.2, 0.3), [0.1, 0.2, 0.3])
    frames = [
        _frame(color=rng.integers(0, 256, (90, 160, 3), dtype=np.uint8),
               depth=rng.integers(0, 4000, (90, 160), dtype=np.uint16), t=0.1 * i,
               X_WC=X if i == 0 else None)
        for i in range(3)
    ]
    assert save_sequence(frames, tmp_path / "seq") == 3
    seq = RecordedSequence(tmp_path / "seq")
    played = list(seq)
    assert len(played) == len(seq) == 3
    for a, b in zip(frames, played):
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.depth, b.depth)
        assert a.intrinsics == b.intrinsics and a.timestamp == b.timestamp
    np.testing.assert_allclose(played[0].X_WC.GetAsMatrix4(), X.GetAsMatrix4())
    assert played[1].X_WC is None
    with pytest.raises(EndOfSequence):
        seq.read()
    looped = RecordedSequence(tmp_path / "seq", loop=True)
    assert [looped.read().timestamp for _ in range(4)] == pytest.approx([0.0, 0.1, 0.2, 0.0])


def test_recorded_frame_with_bad_content_is_refused(tmp_path):
    np.savez(tmp_path / "frame_000000.npz", color=np.zeros((4, 4, 3), np.uint8),
             depth=np.zeros((4, 4), np.float32), intrinsics=np.array([3.0, 3.0, 2.0, 2.0]),
             timestamp=np.float64(0))
    with pytest.raises(FrameError, match="depth"):
        RecordedSequence(tmp_path).read()
    np.savez(tmp_path / "partial.npz", color=np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(FrameError, match="missing"):
        load_frame(tmp_path / "partial.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FrameError, match="not a readable"):
        load_frame(tmp_path / "junk.npz")
    with pytest.raises(DexdrakeError, match="does not exist"):
        RecordedSequence(tmp_path / "nowhere")


def test_single_file_sequence(tmp_path):
    path = save_frame(_frame(t=2.5), tmp_path / "one.npz")
    assert [f.timestamp for f in RecordedSequence(path)] == [2.5]


def _fake_pyk4a(width=64, height=36):
    """A stand-in for pyk4a (its own tests mock the device the same way)."""
    mod = types.ModuleType("pyk4a")
    mod.ColorResolution = types.SimpleNamespace(RES_720P="720P")
    mod.DepthMode = types.SimpleNamespace(NFOV_UNBINNED="NFOV")
    mod.ImageFormat = types.SimpleNamespace(COLOR_BGRA32="BGRA32")
    mod.CalibrationType = types.SimpleNamespace(COLOR="color", DEPTH="depth")
    mod.Config = lambda **kw: kw

    class Calibration:
        def get_camera_matrix(self, which):
            assert which == "color"
            return np.array([[30.0, 0, 31.5], [0, 30.5, 17.5], [0, 0, 1]])

    class PyK4A:
        def __init__(self, config, device_id=0):
            self.config, self.started, self.n = config, False, 0
            self.calibration = Calibration()

        def start(self):
            self.started = True

        def stop(self):
            self.started = False

        def get_capture(self, timeout=-1):
            self.n += 1
            bgra = np.zeros((height, width, 4), np.uint8)
            bgra[..., 0], bgra[..., 1], bgra[..., 2] = 10, 20, 30
            return types.SimpleNamespace(
                color=bgra, transformed_depth=np.full((height, width), 800, np.uint16),
                color_timestamp_usec=self.n * 33_333)

    mod.PyK4A = PyK4A
    return mod


def test_k4a_device_converts_bgra_and_reads_calibration(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyk4a", _fake_pyk4a())
    with K4ADevice(warmup_frames=2) as cam:
        assert cam._k4a.config["color_format"] == "BGRA32"
        frame = cam.read()
        assert frame.color[0, 0].tolist() == [30, 20, 10]  # RGB
        assert frame.depth.dtype == np.uint16 and frame.depth[0, 0] == 800
        assert (frame.intrinsics.fx, frame.intrinsics.cy) == (30.0, 17.5)
        assert frame.timestamp == pytest.approx(3 * 0.033333)
    assert not cam._k4a.started


def test_latest_frame_never_blocks_and_reports_a_stalled_camera():
    """LatestFrame keeps the newest frame of a slow source (read returns at once) and raises
    FrameError once its frames stop for longer than the timeout; close stops the source."""
    import threading
    import time

    from dexdrake.hardware.kinect import CameraSource, LatestFrame

    class Slow(CameraSource):  # a frame every 0.1 s until stalled; then reads fail
        def __init__(self):
            self.count, self.stalled, self.closed = 0, threading.Event(), False

        def read(self):
            time.sleep(0.1)
            if self.stalled.is_set():
                raise FrameError("capture timed out")
            self.count += 1
            return _frame(t=float(self.count))

        def close(self):
            self.closed = True

    source = Slow()
    reader = LatestFrame(source, timeout_s=0.5)
    first = reader.read()  # waits for the first frame only
    t0 = time.perf_counter()
    again = reader.read()  # not for the next one (0.1 s away)
    assert time.perf_counter() - t0 < 0.05 and again.timestamp >= first.timestamp
    time.sleep(0.25)
    assert reader.read().timestamp > first.timestamp  # newer frames arrived meanwhile
    source.stalled.set()
    time.sleep(0.8)
    with pytest.raises(FrameError, match="no camera frame for .* capture timed out"):
        reader.read()
    reader.close()
    assert source.closed and not reader._thread.is_alive()


def test_k4a_device_without_pyk4a_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyk4a", None)
    with pytest.raises(DexdrakeError, match="pyk4a"):
        K4ADevice()


def test_depth_noise_model_is_seeded_and_kinect_like():
    depth = np.full((200, 200), 1.0)
    depth[:, :5] = np.inf
    model = DepthNoiseModel(edge_jump_mm=0.0)
    a = model.apply(depth, np.random.default_rng(3))
    np.testing.assert_array_equal(a, model.apply(depth, np.random.default_rng(3)))
    assert np.all(a[:, :5] == 0)
    valid = a[:, 5:] > 0
    assert 0.97 < valid.mean() < 1.0                 # 1 % dropout
    err = a[:, 5:][valid].astype(float) - 1000.0
    assert err.mean() == pytest.approx(3.0, abs=0.2)  # 2 mm + 0.1 % of 1 m
    assert err.std() == pytest.approx(2.5, abs=0.2)   # 1 + 1.5 * 1**2 mm


# ---------------------------------------------------------------- perception

def test_segmentation_keeps_object_and_thin_parts_drops_specks_and_out_of_range():
    frame_color = np.zeros((90, 160, 3), np.uint8)
    frame_color[:] = GREEN
    frame_color[30:60, 40:80] = RED     # the object
    frame_color[44:46, 80:110] = RED    # its handle, 2 px wide
    frame_color[10:11, 100:130] = RED   # a thin object of its own, 1 px wide
    frame_color[5:7, 5:7] = RED         # a 2x2 speck
    frame_color[20, 20:23] = RED        # a 1x3 speck
    frame_color[70:85, 120:150] = RED   # red but beyond the depth range
    depth = np.full((90, 160), 700, np.uint16)
    depth[70:85, 120:150] = 2500
    depth[40, 50] = 0                   # a hole: no data
    mask = segment_object(_frame(frame_color, depth), GreenScreenConfig(max_depth_mm=1500))
    expected = np.zeros((90, 160), bool)
    expected[30:60, 40:80] = True
    expected[44:46, 80:110] = True
    expected[10:11, 100:130] = True
    expected[40, 50] = False
    np.testing.assert_array_equal(mask, expected)
    everything = segment_object(_frame(frame_color, depth),
                                GreenScreenConfig(max_depth_mm=1500, min_component_px=1))
    assert everything[5:7, 5:7].all() and everything[20, 20:23].all()


def test_backprojection_is_exact_on_a_known_plane():
    k = KINECT_COLOR_720P.scaled(320, 180)
    n, d = np.array([0.2, -0.3, 1.0]), 0.9       # plane n . p = d in the camera frame
    u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u, float)], -1)
    z_m = d / (rays @ n)
    depth = np.round(z_m * 1000).astype(np.uint16)
    depth[:10] = 0
    points = backproject(depth, k)
    assert len(points) == (k.height - 10) * k.width
    # On the plane up to the 0.5 mm depth quantisation along each ray.
    residual = np.abs(points @ n - d) / np.linalg.norm(n)
    bound = 0.5e-3 * np.abs(rays[10:] @ n).ravel() / np.linalg.norm(n)
    assert np.all(residual <= bound + 1e-12)
    np.testing.assert_allclose(points[:, 2], depth[10:].ravel() * 1e-3)
    # Pixel (cx, cy) direction: the principal ray.
    np.testing.assert_allclose(points[:, :2] / points[:, 2:], rays[10:, :, :2].reshape(-1, 2),
                               atol=1e-12)


def test_empty_mask_is_a_failure_result_not_an_exception(l_shape, cache):
    estimator = ObjectPoseEstimator(l_shape[0], registration=RegistrationConfig(ransac_runs=1))
    result = estimator.estimate(_frame())         # all green: nothing to register
    assert not result.success and "too few object pixels" in result.reason
    assert result.X_WO is None and result.num_mask_pixels == 0
    result = estimator.estimate(None)             # not a frame at all
    assert not result.success and "RgbdFrame" in result.reason


def test_missing_mesh_is_a_clear_error(tmp_path, cache):
    with pytest.raises(DexdrakeError, match="does not exist"):
        ObjectPoseEstimator(tmp_path / "missing.obj")


@pytest.fixture(scope="module")
def rendered(l_shape, cache):
    X_WC = look_at([-0.45, 0.0, 0.45], [0.0, 0.0, 0.02])
    return DrakeRenderedCamera(X_WC, {"l_shape": l_shape[0]}, width=640, height=360,
                               noise=None, seed=0)


def test_rendered_table_backprojects_onto_z0(rendered):
    rendered.hide_object("l_shape")
    frame = rendered.read()
    assert frame.color.shape == (360, 640, 3) and frame.depth.dtype == np.uint16
    mask = segment_object(frame)
    assert not mask.any()                         # green table and wall only
    points_W = transform_points(frame.X_WC, backproject(frame.depth, frame.intrinsics))
    on_table = (points_W[:, 0] < 0.55) & (np.abs(points_W[:, 1]) < 0.55)
    assert on_table.sum() > 50_000
    assert np.abs(points_W[on_table, 2]).max() < 2e-3   # within depth quantisation


def test_rendered_object_backprojects_onto_its_true_surface(rendered, l_shape):
    """No systematic offset between the rendered image and the intrinsics it carries: the
    masked, back-projected points lie on the true surface with a mean residual under
    0.1 mm per axis (a half-pixel principal-point mismatch gives about 0.5 mm here)."""
    from scipy.spatial import cKDTree

    path, rest_height = l_shape
    X_WO = RigidTransform(RollPitchYaw(0.0, 0.0, 0.7), [0.02, 0.01, rest_height])
    rendered.set_object_pose("l_shape", X_WO)
    frame = rendered.read()
    cloud_W = transform_points(frame.X_WC, backproject(frame.depth, frame.intrinsics, segment_object(frame)))
    surface, _ = trimesh.sample.sample_surface(trimesh.load(path, force="mesh"), 200_000, seed=0)
    true_W = transform_points(X_WO, surface)
    dist, index = cKDTree(true_W).query(cloud_W)
    near = dist < 0.005
    assert near.sum() > 1000
    residual_C = (cloud_W - true_W[index])[near] @ frame.X_WC.rotation().matrix()
    assert np.all(np.abs(residual_C.mean(axis=0)) < 1e-4), residual_C.mean(axis=0)


def test_registration_recovers_a_rendered_pose(rendered, l_shape, cache):
    path, rest_height = l_shape
    X_WO = RigidTransform(RollPitchYaw(0.0, 0.0, 2.1), [0.03, -0.02, rest_height])
    rendered.set_object_pose("l_shape", X_WO)
    frame = rendered.read()
    estimator = ObjectPoseEstimator(path, registration=RegistrationConfig(ransac_runs=3))
    result = estimator.estimate(frame)
    assert result.success, result.reason
    assert result.fitness > 0.9 and result.num_points >= 100
    err = X_WO.inverse() @ result.X_WO
    assert np.linalg.norm(err.translation()) < 1e-3
    assert np.degrees(err.rotation().ToAngleAxis().angle()) < 2.0
    np.testing.assert_allclose((frame.X_WC @ result.X_CO).GetAsMatrix4(),
                               result.X_WO.GetAsMatrix4())


@pytest.mark.parametrize("name, seed", [("wrench", 0), ("jack", 2)])
def test_thin_library_objects_register_in_the_hil_camera(name, seed, cache):
    """A wrench (an 18 mm bar, 3-4 px wide) and a jack (rods, most of their pixels lost at
    depth edges) at an episode's placement, seen by configs/hil.yaml's camera with depth noise,
    segment to enough points and register to the true pose (ADD-S under 5 mm)."""
    from scipy.spatial import cKDTree

    from dexdrake.objects.library import get_object
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.scene import ObjectPlacement

    cam = load_scenario("hil").drivers.camera
    info = get_object(name)
    camera = DrakeRenderedCamera(look_at(cam.eye, cam.target), {name: info.mesh_path}, cam.width,
                                 cam.height, noise=DepthNoiseModel(), seed=seed)
    X_WO = ObjectPlacement.from_seed(seed).pose(info)
    camera.set_object_pose(name, X_WO)
    estimator = ObjectPoseEstimator(info.mesh_path)
    result = estimator.estimate(camera.read())
    assert result.success, result.reason
    assert result.num_points >= estimator.registration.min_points
    model = estimator.model.points
    true_W, est_W = transform_points(X_WO, model), transform_points(result.X_WO, model)
    assert cKDTree(true_W).query(est_W)[0].mean() < 5e-3


def test_symmetric_twins_are_found_and_the_one_nearest_the_prior_is_reported():
    """A cylinder registers equally well upside down: the estimator reports the upright twin
    (library objects start upright) and later the twin nearest the previous pose."""
    from dexdrake.hardware.perception import model_symmetries, nearest_twin

    rng = np.random.default_rng(0)
    theta, z = rng.uniform(-np.pi, np.pi, 3000), rng.uniform(-0.05, 0.05, 3000)
    cyl = np.c_[0.03 * np.cos(theta), 0.03 * np.sin(theta), z]
    twins = model_symmetries(cyl, 0.004)
    assert len(twins) > 2  # half turns about z and horizontal axes
    flips = [F for F in twins if F[2, 2] < 0]
    assert flips and np.all([np.allclose(F[:3, :3] @ F[:3, :3].T, np.eye(3)) for F in twins])
    lumpy = np.r_[cyl, [[0.05, 0.0, 0.04]] * 200]  # a handle-like lump: no symmetry left
    assert len(model_symmetries(lumpy, 0.004)) == 1
    upright = RigidTransform(RollPitchYaw(0.0, 0.0, 0.7), [0.0, 0.0, 0.05])
    flipped = upright @ RigidTransform(flips[0])
    chosen = nearest_twin(flipped, twins, prior=None)
    assert chosen.rotation().matrix()[2, 2] > 0.999
    tilted = RigidTransform(RollPitchYaw(0.0, np.pi - 0.3, 0.0), [0.0, 0.0, 0.05])
    kept = nearest_twin(tilted, twins, prior=tilted)  # the prior wins over uprightness
    assert np.allclose(kept.GetAsMatrix4(), tilted.GetAsMatrix4())
    assert np.allclose(nearest_twin(upright, twins, None).GetAsMatrix4(), upright.GetAsMatrix4())


# ---------------------------------------------------------------- tracking

@pytest.fixture(scope="module")
def finger_scene(l_shape, cache, tmp_path_factory):
    """The L shape and a finger-like bar (not green: segmented with the object) at 320x180,
    as in configs/hil.yaml, with Kinect-like depth noise."""
    finger = tmp_path_factory.mktemp("finger") / "finger.obj"
    trimesh.creation.box((0.018, 0.018, 0.12)).export(finger)
    X_WC = look_at([0.5, 0.0, 0.45], [0.0, 0.0, 0.03])
    camera = DrakeRenderedCamera(X_WC, {"l_shape": l_shape[0], "finger": finger}, width=320,
                                 height=180, noise=DepthNoiseModel(), seed=1)
    return camera, ObjectPoseEstimator(l_shape[0], registration=RegistrationConfig(ransac_runs=3))


def _pose_error(X_true: RigidTransform, X: RigidTransform) -> tuple[float, float]:
    err = X_true.inverse() @ X
    return float(np.linalg.norm(err.translation())), float(np.degrees(err.rotation().ToAngleAxis().angle()))


def test_tracking_follows_the_object_behind_an_occluding_finger(finger_scene, l_shape):
    """Frame to frame, the tracked pose follows a lifted, turning object to within 4 mm and
    3 deg while a finger in front of it hides part of it and adds points of its own, at a
    small fraction of a global registration's cost. The track starts at the true pose: the
    global registration's accuracy is another test's subject (at 320x180 this object has a
    tilted twin that fits 88 % of the points and that the depth check does not always refute
    from this view)."""
    camera, estimator = finger_scene
    rest = l_shape[1]
    X0 = RigidTransform(RollPitchYaw(0.0, 0.0, 0.4), [0.0, 0.0, rest])
    camera.hide_object("finger")
    camera.set_object_pose("l_shape", X0)
    first = estimator.estimate(camera.read())
    assert first.success, first.reason
    prior, occluded_fitness, costs = X0, [], []
    for k in range(1, 13):  # 3 mm and 0.03 rad per frame: 0.075 m/s at 25 frames/s
        X = RigidTransform(RollPitchYaw(0.0, 0.0, 0.4 + 0.03 * k), [0.002 * k, 0.0, rest + 0.003 * k])
        camera.set_object_pose("l_shape", X)
        if k >= 4:  # a finger between the camera and the object, touching it
            camera.set_object_pose("finger", RigidTransform(X.translation() + [0.04, -0.01, 0.02]))
        result = estimator.track(camera.read(), prior)
        assert result.success, (k, result.reason)
        dp, dr = _pose_error(X, result.X_WO)
        assert dp < 4e-3 and dr < 3.0, (k, dp, dr)
        if k >= 4:
            occluded_fitness.append(result.fitness)
        costs.append(result.elapsed_s)
        prior = result.X_WO
    assert min(occluded_fitness) < 0.99  # the finger's own points are seen, and rejected
    assert np.median(costs) < first.elapsed_s / 10


def _half_turn(X_WO: RigidTransform, axis_O: list[float]) -> RigidTransform:
    """X_WO turned by pi about `axis_O` (object frame) through the object's origin."""
    return X_WO @ RigidTransform(RotationMatrix(AngleAxis(np.pi, np.array(axis_O) / np.linalg.norm(axis_O))),
                                 np.zeros(3))


def test_depth_check_passes_the_true_pose_behind_a_finger_and_refuses_twins(finger_scene, l_shape):
    """The depth image contradicts (`contradicted_fraction` above `max_contradicted`) the L
    shape's pose tilted by 30 deg about its bar, and its flipped twins refined by ICP onto
    the observed points (one fits most of them), but not its true pose while a finger in
    front of it hides a good part of it: points behind the observed depth do not count."""
    camera, estimator = finger_scene
    X0 = RigidTransform(RollPitchYaw(0.0, 0.0, 0.4), [0.0, 0.0, l_shape[1]])
    camera.hide_object("l_shape")
    camera.hide_object("finger")
    empty = camera.render_depth_m()
    camera.set_object_pose("l_shape", X0)
    bare = camera.render_depth_m()
    camera.set_object_pose("finger", RigidTransform(X0.translation() + [0.04, -0.01, 0.02]))
    occluded = camera.render_depth_m()
    on_object = bare < empty - 0.005
    assert (occluded[on_object] < bare[on_object] - 0.005).mean() > 0.15  # the finger hides > 15 %
    frame = camera.read()
    check, limit = estimator.depth_check(frame), estimator.registration.max_contradicted
    X_CW = frame.X_WC.inverse()
    assert check((X_CW @ X0).GetAsMatrix4()) < limit
    camera.hide_object("finger")
    frame = camera.read()
    check = estimator.depth_check(frame)
    for r in (0.5, -0.5):  # a tilt about the bar's axis lifts the side block off the table
        tilted = X0 @ RigidTransform(RollPitchYaw(r, 0.0, 0.0), np.zeros(3))
        assert check((X_CW @ tilted).GetAsMatrix4()) > limit, r
    fits = []
    for axis in ([1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0]):
        fitted = estimator.track(frame, _half_turn(X0, axis))  # ICP onto the observed points
        assert _pose_error(X0, fitted.X_WO)[1] > 90.0, axis  # still a flipped twin
        assert check((X_CW @ fitted.X_WO).GetAsMatrix4()) > limit, (axis, fitted.fitness)
        assert not fitted.success, axis  # so tracking reports it lost
        fits.append(fitted.fitness)
    assert max(fits) > 0.85


def test_tracking_refuses_the_wrong_pose_icp_settles_on_after_a_topple(cache):
    """An object that toppled (its last pose turned by up to 90 deg from the new one, the
    same centre) is either tracked to within 5 mm or reported lost: ICP may settle on a
    wrong pose that fits most of the visible points (fitness above `min_fitness`), which
    the depth image contradicts. The HIL camera, a hexagonal pyramid lying on a face."""
    from dexdrake.objects.library import get_object
    from dexdrake.systems.scenario import load_scenario

    cam, info = load_scenario("hil").drivers.camera, get_object("pyramid_hex")
    camera = DrakeRenderedCamera(look_at(cam.eye, cam.target), {info.name: info.mesh_path}, cam.width,
                                 cam.height, noise=DepthNoiseModel(), seed=0)
    mesh = trimesh.load(info.mesh_path, force="mesh")
    X = RigidTransform(trimesh.poses.compute_stable_poses(mesh)[0][0])  # on a face, centred at the origin
    camera.set_object_pose(info.name, X)
    frame = camera.read()
    estimator = ObjectPoseEstimator(info.mesh_path)
    centre = estimator.model.points.mean(axis=0)
    rng, refused, tracked = np.random.default_rng(1), 0, 0
    for _ in range(10):
        axis = rng.normal(size=3)
        R = RotationMatrix(AngleAxis(rng.uniform(0.4, 1.6), axis / np.linalg.norm(axis))) @ X.rotation()
        prior = RigidTransform(R, X @ centre - R @ centre + rng.normal(size=3) * 0.01)
        result = estimator.track(frame, prior)
        if result.success:
            assert np.linalg.norm(result.X_WO @ centre - X @ centre) < 5e-3
            tracked += 1
        else:
            assert "contradicts" in result.reason and result.fitness > estimator.tracking.min_fitness
            refused += 1
    assert refused >= 2 and tracked >= 5


def test_tracking_reports_a_lost_object(finger_scene, l_shape):
    """An object gone from view, or far from the last pose, is reported lost (for the caller's
    fall back to global registration), never followed onto something else."""
    camera, estimator = finger_scene
    X = RigidTransform([0.0, 0.0, l_shape[1]])
    camera.set_object_pose("l_shape", X)
    camera.set_object_pose("finger", RigidTransform([0.0, 0.12, 0.06]))  # in view, away from it
    assert estimator.track(camera.read(), X).success
    camera.hide_object("l_shape")
    gone = estimator.track(camera.read(), X)
    assert not gone.success and "tracking lost" in gone.reason
    camera.set_object_pose("l_shape", RigidTransform([0.0, -0.15, l_shape[1]]))
    moved = estimator.track(camera.read(), X)
    assert not moved.success and "tracking lost" in moved.reason
    assert not estimator.track(_frame(), X).success  # no camera pose: refused, not raised
