"""Camera calibration and camera.json as a hostile user meets them (issue 43).

CLI cases (a table): ``calibrate-camera`` with board specs no printed board has, views that do not
determine the focal length (one view repeated, every view fronto-parallel), an ``--out`` it cannot
write; ``reconstruct`` on camera.json files no lens has (every field NaN, infinite, huge, tiny,
negative or of the wrong type, a distortion that folds or empties the frame); ``integrate
--camera`` and ``capture --camera`` with a camera calibrated for another frame size. The promise
is the README's (tests/helpers/hostile.py): exit 2, one ``error:`` line naming the file or option,
no traceback or warning, nothing changed in the case's folder, no temporary file left.

Unit cases: the degeneracy checks (:mod:`ps_lab.calibration._camera_views`) on corners projected
through a known camera at seeded poses with 0.1 px noise (the render's corner noise is ~0.07 px:
tests/test_camera_calibration.py), and :func:`ps_lab.io.camera.camera_problem` on lenses real and
impossible.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from ps_lab.calibration import Detection, calibrate_from_corners, parse_board
from ps_lab.calibration._camera_views import (
    MIN_TILT_SPREAD_DEG,
    WEAK_TILT_SPREAD_DEG,
    repeated_views,
    tilt_spread_deg,
)
from ps_lab.errors import CalibrationError, DatasetError
from ps_lab.io.camera import CameraModel, camera_json, camera_problem, read_camera_file
from ps_lab.io.codecs import imwrite
from ps_lab.render.board import (
    CharucoTarget,
    board_poses,
    render_charuco,
    write_board_frames,
)

from helpers.hostile import (
    assert_quiet,
    refused,
    run,
    tmpfs_prefix,
)

ROOT = Path(__file__).resolve().parents[1]
SIZE = (320, 240)
TARGET = CharucoTarget(9, 6, 20.0, 15.0, "DICT_5X5_100")
BOARD = "charuco:9x6:20:15"
LENS = CameraModel(400.0, 401.0, 161.3, 118.2, (-0.2, 0.05, 4e-4, -3e-4, 0.0), SIZE)


# --- templates (made once) ---------------------------------------------------------------------


def _frontal_poses(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Fronto-parallel board poses, turned about the view axis and shifted (seeded)."""
    rng = np.random.default_rng(seed)
    bw, bh = TARGET.size
    poses = []
    for _ in range(count):
        rotation, _ = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(rng.uniform(-20, 20))]))
        z = LENS.fx * bw / (0.7 * SIZE[0]) * rng.uniform(0.9, 1.2)
        shift = rng.uniform(-0.2, 0.2, 2) * np.array(SIZE)
        centre = np.array([shift[0] / LENS.fx * z, shift[1] / LENS.fy * z, z])
        tvec = centre - rotation @ np.array([bw / 2.0, bh / 2.0, 0.0])
        poses.append((cv2.Rodrigues(rotation)[0].reshape(3), tvec))
    return poses


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    """Board frames (varied, one view six times, fronto-parallel), a dataset, its result."""
    root = tmp_path_factory.mktemp("camera-made")
    home = tmp_path_factory.mktemp("camera-made-home")
    good = write_board_frames(root / "boards", TARGET, LENS, 8, seed=0)
    repeated = root / "repeated"
    repeated.mkdir()
    for k in range(6):
        shutil.copy(good[1], repeated / f"view_{k + 1}.png")
    (root / "frontal").mkdir()
    rng = np.random.default_rng(6)
    for k, (rvec, tvec) in enumerate(_frontal_poses(6, seed=5)):
        image = render_charuco(TARGET, LENS, rvec, tvec, supersample=2)
        image = image + rng.normal(0.0, 0.005, image.shape)
        assert imwrite(root / "frontal" / f"board_{k + 1:03d}.png",
                       np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8))
    assert run(["simulate", str(root / "data"), "--scene", "sphere", "--lights", "6", "--size",
                "32", "--lens", "-0.1"], root, home).code == 0
    shutil.copy(root / "data" / "camera_truth.json", root / "data" / "camera.json")
    done = run(["reconstruct", str(root / "data"), "--method", "ls", "--out",
                str(root / "result")], root, home)
    assert done.code == 0, done.stderr
    return {"boards": root / "boards", "repeated": root / "repeated",
            "frontal": root / "frontal", "data": root / "data", "result": root / "result"}


@dataclass
class W:
    """One case's folder (``root``, snapshotted) and home (cache, TMPDIR)."""

    root: Path
    home: Path
    made: dict[str, Path]

    def copy(self, name: str) -> Path:
        target = self.root / name
        shutil.copytree(self.made[name], target, symlinks=True)
        return target

    def frames(self, name: str) -> list[str]:
        return sorted(str(p) for p in self.copy(name).iterdir())

    def camera(self, change: Callable[[dict], None] | None = None, text: str | None = None,
               name: str = "data") -> Path:
        """A copy of the dataset ``name`` whose camera.json is changed (or replaced by text)."""
        folder = self.copy(name)
        data = json.loads((self.made["data"] / "camera.json").read_text())
        if change is not None:
            change(data)
        (folder / "camera.json").write_text(text if text is not None else json.dumps(data))
        return folder


def _set(path: tuple, value) -> Callable[[dict], None]:
    def change(data: dict) -> None:
        target = data
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return change


def _other_size(data: dict) -> None:
    """A valid camera for 64x64 frames (the dataset is 32x32)."""
    data["image_size"] = [64, 64]
    data["camera_matrix"] = [[64.0, 0.0, 31.5], [0.0, 64.0, 31.5], [0.0, 0.0, 1.0]]


def _camera_file(w: W, change: Callable[[dict], None]) -> Path:
    data = json.loads((w.made["data"] / "camera.json").read_text())
    change(data)
    path = w.root / "camera.json"
    path.write_text(json.dumps(data))
    return path


def _reconstruct(change=None, text=None):
    return lambda w: ["reconstruct", str(w.camera(change, text)), "--out", str(w.root / "out")]


def _calibrate(frames: str, board: str = BOARD):
    return lambda w: ["calibrate-camera", *w.frames(frames), "--board", board, "--out",
                      str(w.root / "cam")]


def _board(board: str):
    return lambda w: ["calibrate-camera", str(w.made["boards"] / "board_001.png"), "--board",
                      board, "--out", str(w.root / "cam")]


@dataclass
class Case:
    id: str
    build: Callable[[W], list[str]]
    names: tuple[str, ...]


CAMERA = ("camera.json",)
#: Through the CLI, one subprocess each (the rest of each kind is checked in-process below).
CASES = [
    # board specs no printed board has: refused before any frame is read
    Case("board-square-1e300", _board("charuco:9x6:1e300:1e299"), ("--board",)),
    Case("board-square-1e-300", _board("charuco:9x6:1e-300:1e-301"), ("--board",)),
    Case("board-square-1e30-chessboard", _board("chessboard:10x7:1e30"), ("--board",)),
    # views that do not determine the focal length
    Case("one-view-six-times", _calibrate("repeated"), ("view_1.png", "distinct")),
    Case("fronto-parallel-views", _calibrate("frontal"), ("board_001.png", "do not determine")),
    # an output it cannot write, named as the user gave it
    Case("out-is-a-file", lambda w: ["calibrate-camera", *(f := w.frames("boards")), "--board",
                                     BOARD, "--out", f[0]], ("--out",)),
    # camera.json values no lens has
    Case("focal-1e-300", _reconstruct(_set(("camera_matrix", 0, 0), 1e-300)), CAMERA),
    Case("k1-huge", _reconstruct(_set(("distortion", "k1"), 1e6)), CAMERA),
    Case("k1-huge-negative", _reconstruct(_set(("distortion", "k1"), -1e6)), CAMERA),
    Case("nested-deeply", _reconstruct(text="[" * 100_000 + "]" * 100_000), CAMERA),
    # one frame-size rule everywhere: reconstruct, integrate --camera, capture --camera
    Case("reconstruct-other-size", _reconstruct(_other_size), CAMERA),
    Case("integrate-camera-other-size",
         lambda w: ["integrate", str(w.copy("result")), "--camera",
                    str(_camera_file(w, _other_size)), "--out", str(w.root / "depth")], CAMERA),
    Case("capture-camera-other-size",
         lambda w: ["capture", "--rig", str(ROOT / "rigs" / "simulated.toml"), "--out",
                    str(w.root / "run"), "--camera", str(_camera_file(w, _other_size)),
                    "--dry-run"], ("--camera",)),
]

#: camera.json changes read_camera_file refuses, each with words of its line.
CAMERA_FILES = [
    ("focal-1e300", _set(("camera_matrix", 1, 1), 1e300), "implausible"),
    ("focal-negative", _set(("camera_matrix", 0, 0), -32.0), "positive"),
    ("focal-nan", _set(("camera_matrix", 0, 0), float("nan")), "finite"),
    ("focal-inf", _set(("camera_matrix", 0, 0), float("inf")), "finite"),
    ("focal-string", _set(("camera_matrix", 0, 0), "32"), "finite"),
    ("focal-bool", _set(("camera_matrix", 0, 0), True), "finite"),
    ("focal-huge-integer", _set(("camera_matrix", 0, 0), 10**400), "401 digits"),
    ("focal-aspect", _set(("camera_matrix", 1, 1), 320.0), "aspect"),
    ("skew", _set(("camera_matrix", 0, 1), 3.0), "[[fx,0,cx]"),
    ("matrix-string", _set(("camera_matrix",), "K"), "3 rows"),
    ("centre-far-outside", _set(("camera_matrix", 0, 2), 1e300), "outside"),
    ("centre-negative", _set(("camera_matrix", 1, 2), -40.0), "outside"),
    ("k1-folds-in-frame", _set(("distortion", "k1"), -3.0), "fold"),
    ("k3-1e300", _set(("distortion", "k3"), 1e300), "fold"),
    ("k3-minus-1e300", _set(("distortion", "k3"), -1e300), "fold"),
    ("p1-1e300", _set(("distortion", "p1"), 1e300), "fold"),
    ("k2-nan", _set(("distortion", "k2"), float("nan")), "finite"),
    ("k2-null", _set(("distortion", "k2"), None), "finite"),
    ("k2-list", _set(("distortion", "k2"), [0.1]), "finite"),
    ("distortion-list", _set(("distortion",), [0, 0, 0, 0, 0]), "distortion must be"),
    ("size-huge", _set(("image_size",), [10**30, 32]), "image_size"),
    ("size-float", _set(("image_size",), [32.0, 32.0]), "image_size"),
    ("size-zero", _set(("image_size",), [0, 32]), "image_size"),
    ("size-string", _set(("image_size",), "32x32"), "image_size"),
    ("rms-negative", _set(("rms_px",), -1.0), "rms_px"),
    ("rms-nan", _set(("rms_px",), float("nan")), "rms_px"),
]

@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_camera_input(case: Case, made, tmp_path) -> None:
    w = W(tmp_path / "case", tmp_path / "home", made)
    w.root.mkdir()
    w.home.mkdir()
    args = case.build(w)
    line = refused(args, w.root, w.home, case.names[:1])
    assert all(name in line for name in case.names), line


@pytest.mark.parametrize(("change", "words"), [c[1:] for c in CAMERA_FILES],
                         ids=[c[0] for c in CAMERA_FILES])
def test_camera_file_values_are_refused_naming_it(change, words, made, tmp_path) -> None:
    data = json.loads((made["data"] / "camera.json").read_text())
    change(data)
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(data))
    with pytest.raises(DatasetError) as caught:
        read_camera_file(path)
    assert str(caught.value).startswith(f"{path}: ") and words in str(caught.value)


@pytest.mark.parametrize(
    ("text", "words"),
    [("[" * 100_000 + "]" * 100_000, "nested"), ('{"a": ' + "9" * 5000 + "}", "not a JSON"),
     ("{", "not a JSON"), ("[]", "not a ps-lab camera file"), ("\xff", "not a JSON")],
    ids=["nested", "integer-of-5000-digits", "truncated", "array", "not-utf8"],
)
def test_camera_files_that_are_not_json_objects(text, words, tmp_path) -> None:
    path = tmp_path / "camera.json"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(DatasetError, match=words):
        read_camera_file(path)


@pytest.mark.parametrize(
    ("spec", "words"),
    [("chessboard:10x7:nan", "positive"), ("charuco:9x6:inf:15", "positive"),
     ("charuco:9x6:-20:15", "positive"), ("charuco:9x6:20:1e-300", "printed board"),
     ("charuco:9x6:20:1", "at least 0.1"), ("chessboard:100000x7:20", "at most 200"),
     ("charuco:30x30:20:15", "markers"), ("charuco:40x40:20:15:APRILTAG_36H11", "587 markers"),
     ("chessboard:10x7:20000", "printed board"), ("chessboard:10x7:0.001", "printed board"),
     ("chessboard:3x3:5", "at least 4x4"), ("chessboard:12x3:5", "at least 4x4")],
)
def test_board_specs_no_printed_board_has(spec, words) -> None:
    with pytest.raises(CalibrationError, match=words) as caught:
        parse_board(spec)
    assert str(caught.value).startswith(f"--board {spec}: ")


def test_read_only_out_names_the_users_folder(made, tmp_path) -> None:
    """A read-only disk: the line names --out, never the staging folder (issue 43)."""
    mount = tmp_path / "ro"
    prefix = tmpfs_prefix(mount, "ro")
    if prefix is None:
        pytest.skip("cannot mount a tmpfs here (unshare -rm not allowed): read-only not tested")
    w = W(tmp_path / "case", tmp_path / "home", made)
    w.root.mkdir()
    w.home.mkdir()
    line = refused(["calibrate-camera", *w.frames("boards"), "--board", BOARD, "--out",
                    str(mount / "cam")], w.root, w.home, (f"--out {mount / 'cam'}",), prefix=prefix)
    assert "partial" not in line, line


def test_good_views_record_their_uncertainty(made, tmp_path) -> None:
    """A varied set calibrates; camera.json and the summary carry the 1-sigma of f and c."""
    home = tmp_path / "home"
    home.mkdir()
    frames = sorted(str(p) for p in made["boards"].iterdir())
    result = run(["calibrate-camera", *frames, "--board", BOARD, "--out", str(tmp_path / "cam")],
                 tmp_path, home)
    assert result.code == 0, result.stderr
    assert_quiet(result)
    assert not result.lines, result.stderr  # no warning for a good set
    data = json.loads((tmp_path / "cam" / "camera.json").read_text())
    sigma = data["uncertainty_px"]
    fx = data["camera_matrix"][0][0]
    assert 0 < sigma["fx"] < 0.01 * fx and 0 < sigma["cx"] < 0.02 * SIZE[0]
    # the truth within 4 sigma (the corners' noise is what sigma describes)
    assert abs(fx - LENS.fx) < 4 * sigma["fx"] + 1e-3 * LENS.fx
    assert data["views"]["distinct"] == len(frames)
    assert data["views"]["tilt_spread_deg"] > WEAK_TILT_SPREAD_DEG
    assert f"+/- {sigma['fx']:.2f}" in result.stdout


# --- the degeneracy checks on projected corners ------------------------------------------------


def _detections(poses, seed: int = 0, noise: float = 0.1) -> list[Detection]:
    rng = np.random.default_rng(seed)
    corners = TARGET.board().getChessboardCorners().astype(np.float64)
    out = []
    for rvec, tvec in poses:
        points, _ = cv2.projectPoints(corners, rvec, tvec, LENS.matrix, LENS.coefficients)
        points = points.reshape(-1, 2) + rng.normal(0.0, noise, (len(corners), 2))
        inside = ((points >= 0) & (points <= np.array(SIZE) - 1)).all(axis=1)
        out.append(Detection(corners[inside].astype(np.float32),
                             points[inside].astype(np.float32)))
    return out


def _tilted_poses(count: int, tilt_deg: float, seed: int):
    """Poses tilted by up to ``tilt_deg`` about x and y (board_poses' placement)."""
    rng = np.random.default_rng(seed)
    frontal = _frontal_poses(count, seed)
    poses = []
    for rvec, tvec in frontal:
        tilt, _ = cv2.Rodrigues(np.radians([rng.uniform(-tilt_deg, tilt_deg),
                                            rng.uniform(-tilt_deg, tilt_deg), 0.0]))
        rotation = cv2.Rodrigues(rvec)[0]
        centre = tvec + rotation @ np.array([TARGET.size[0] / 2, TARGET.size[1] / 2, 0.0])
        turned = tilt @ rotation
        poses.append((cv2.Rodrigues(turned)[0].reshape(3),
                      centre - turned @ np.array([TARGET.size[0] / 2, TARGET.size[1] / 2, 0.0])))
    return poses


def test_varied_views_pass_and_sigma_covers_the_error() -> None:
    result = calibrate_from_corners(_detections(board_poses(TARGET, LENS, 8, seed=3)), SIZE)
    assert result.warning is None and result.views.distinct_views == 8
    for name, truth in (("fx", LENS.fx), ("fy", LENS.fy), ("cx", LENS.cx), ("cy", LENS.cy)):
        estimate = getattr(result.camera, name)
        assert abs(estimate - truth) < 4 * result.sigma[name], (name, estimate, truth)


def test_repeated_views_are_found_and_refused() -> None:
    pose = board_poses(TARGET, LENS, 2, seed=3)[1]
    detections = _detections([pose] * 6, seed=1)  # one pose, six noisy shots
    repeats = repeated_views([d.object_points for d in detections],
                             [d.image_points for d in detections], SIZE)
    assert repeats == {k: 0 for k in range(1, 6)}
    with pytest.raises(CalibrationError, match="1 distinct view"):
        calibrate_from_corners(detections, SIZE)


def test_a_repeat_among_varied_views_is_a_warning() -> None:
    poses = board_poses(TARGET, LENS, 8, seed=3)
    result = calibrate_from_corners(_detections([*poses, poses[2]], seed=2), SIZE)
    assert result.views.repeats == {8: 2}
    assert "frame 9 repeats frame 3" in result.warning


def test_varied_views_are_not_repeats() -> None:
    detections = _detections(board_poses(TARGET, LENS, 8, seed=3))
    assert repeated_views([d.object_points for d in detections],
                          [d.image_points for d in detections], SIZE) == {}


def test_fronto_parallel_views_are_refused() -> None:
    detections = _detections(_frontal_poses(8, seed=5))
    with pytest.raises(CalibrationError, match="parallel in every view"):
        calibrate_from_corners(detections, SIZE)


def test_weakly_tilted_views_warn_with_numbers() -> None:
    """Tilts up to 8 deg: usable, with a warning; the error within ~3 sigma of OpenCV's."""
    result = calibrate_from_corners(_detections(_tilted_poses(8, 8.0, seed=4), seed=4), SIZE)
    assert MIN_TILT_SPREAD_DEG <= result.views.tilt_spread_deg < WEAK_TILT_SPREAD_DEG
    assert result.warning is not None and "sigma f" in result.warning
    assert abs(result.camera.fx - LENS.fx) < 3 * result.sigma["fx"]


def test_corners_on_one_line_are_refused_not_an_opencv_assertion() -> None:
    """A board cut by the frame down to one row of corners: OpenCV's initialisation asserted."""
    detections = _detections(board_poses(TARGET, LENS, 4, seed=3))
    one_row = []
    for d in detections:
        row = d.object_points[:, 1] == d.object_points[0, 1]
        one_row.append(Detection(d.object_points[row], d.image_points[row]))
    with pytest.raises(CalibrationError, match="one line"):
        calibrate_from_corners(one_row, SIZE)


def test_an_implausible_rms_is_refused_naming_the_board() -> None:
    """Corners off by 4 px per axis everywhere (a wrong --board, a bent board): no frame is an
    outlier, and the overall RMS (about 4 x sqrt(2) = 5.7 px, MAX_RMS_PX is 2) is refused."""
    detections = _detections(board_poses(TARGET, LENS, 8, seed=3), noise=4.0)
    with pytest.raises(CalibrationError, match="--board") as caught:
        calibrate_from_corners(detections, SIZE)
    assert "implausible" in str(caught.value)


def test_tilt_spread_is_the_largest_angle_between_normals() -> None:
    a = np.radians([10.0, 0.0, 0.0])  # Rodrigues vectors: about x by 10 deg...
    b = np.radians([-20.0, 0.0, 0.0])
    c = np.radians([0.0, 0.0, 30.0])  # a turn about the view axis: the normal unchanged
    assert tilt_spread_deg([a, b, c]) == pytest.approx(30.0, abs=1e-9)
    assert tilt_spread_deg([c]) == 0.0


# --- camera_problem: the one rule for a camera.json --------------------------------------------


@pytest.mark.parametrize("coefficients", [(0, 0, 0, 0, 0), (-0.2, 0.05, 4e-4, -3e-4, 0.0),
                                          (-0.46, 0.05, 0.0, 0.035, 0.0), (0.3, 0.0, 0, 0, 0)])
def test_real_lenses_pass(coefficients) -> None:
    assert camera_problem(CameraModel(400.0, 401.0, 161.3, 118.2, coefficients, SIZE)) is None


@pytest.mark.parametrize(
    ("camera", "words"),
    [
        (CameraModel(1e-300, 400.0, 160.0, 120.0, image_size=SIZE), "implausible"),
        (CameraModel(400.0, 400.0, 160.0, 1e4, image_size=SIZE), "outside"),
        (CameraModel(400.0, 400.0, 160.0, 120.0, (-3.0, 0, 0, 0, 0), SIZE), "fold"),
        (CameraModel(400.0, 400.0, 160.0, 120.0, (1e6, 0, 0, 0, 0), SIZE), "outside the recorded"),
        (CameraModel(400.0, 400.0, 160.0, 120.0, (0, 0, 0, 0, float("nan")), SIZE), "finite"),
    ],
)
def test_impossible_lenses_are_named(camera, words) -> None:
    with np.errstate(all="raise"):  # and no numpy warning on the way
        problem = camera_problem(camera)
    assert problem is not None and words in problem


def test_calibrate_camera_output_passes_its_own_rule() -> None:
    result = calibrate_from_corners(_detections(board_poses(TARGET, LENS, 8, seed=3)), SIZE)
    assert camera_problem(result.camera) is None
    assert camera_json(result.camera)["image_size"] == list(SIZE)
