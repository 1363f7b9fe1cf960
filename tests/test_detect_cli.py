"""``ctpipe detect``: one detector on one image, keypoints to .npz and an overlay picture."""

import io
import json
import struct
import subprocess
import sys

import numpy as np
import pytest
import tifffile
from skimage.io import imread, imsave

from ctpipe.cli import _key_value, main
from ctpipe.data import Features
from ctpipe.errors import InputError
from ctpipe.evaluate.report import keypoints_png
from ctpipe.io.outputs import write_keypoints
from ctpipe.plugins import get_registry

ROWS, COLS = 112, 144  # not square, so a swapped axis shows

NPZ_KEYS = {"pt", "size", "angle", "response", "octave", "class_id", "descriptors", "norm", "detector", "params"}


def run_cli(*args):
    """Run the real console entry point in a subprocess (exit code, stdout, stderr)."""
    proc = subprocess.run([sys.executable, "-m", "ctpipe.cli", *args], capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def blobs():
    """float32 (ROWS, COLS) image of 40 Gaussian blobs of random width and height."""
    rng = np.random.default_rng(1)
    rows, cols = np.mgrid[:ROWS, :COLS]
    image = np.zeros((ROWS, COLS))
    for _ in range(40):
        y, x, sigma = rng.uniform(4, ROWS - 4), rng.uniform(4, COLS - 4), rng.uniform(1.2, 3.0)
        image += rng.uniform(0.5, 1.0) * np.exp(-((rows - y) ** 2 + (cols - x) ** 2) / (2 * sigma**2))
    return image.astype(np.float32)


@pytest.fixture(scope="module")
def images(tmp_path_factory, blobs):
    """The blobs as float32 .npy and .tif and as uint8 .npy and .png; name -> (path, array)."""
    folder = tmp_path_factory.mktemp("images")
    grey = np.rint(blobs / blobs.max() * 255).astype(np.uint8)
    files = {"float.npy": blobs, "float.tif": blobs, "uint8.npy": grey, "uint8.png": grey}
    for name, array in files.items():
        path = folder / name
        if name.endswith(".npy"):
            np.save(path, array)
        elif name.endswith(".tif"):
            tifffile.imwrite(path, array)
        else:
            imsave(path, array, check_contrast=False)
    return {name: (folder / name, array) for name, array in files.items()}


@pytest.fixture(scope="module")
def registry():
    return get_registry()


def png_size(data: bytes) -> tuple[int, int]:
    """(rows, cols) from a PNG's IHDR chunk, after checking the signature."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    cols, rows = struct.unpack(">II", data[16:24])
    return rows, cols


def leftovers(folder):
    """Files in ``folder`` that a run may have written, finished or not (temporaries included)."""
    return sorted(p.name for p in folder.iterdir() if p.suffix in (".npz", ".png", ".tmp"))


@pytest.mark.parametrize("detector, image_name", [
    ("sift", "float.npy"), ("sift", "float.tif"), ("sift", "uint8.png"), ("orb", "uint8.npy"),
])
def test_npz_has_opencv_keys_and_what_the_detector_returns(tmp_path, capsys, images, registry, detector, image_name):
    path, array = images[image_name]
    out = tmp_path / "kp.npz"
    assert main(["detect", str(path), "--detector", detector, "--out", str(out)]) == 0
    line = capsys.readouterr().out
    assert line.startswith(f"{detector}: ") and f"on {ROWS} x {COLS} ({array.dtype})" in line and line.count("\n") == 1
    expected = registry.get("detector", detector).cls().detect(array)
    with np.load(out, allow_pickle=False) as kp:
        assert set(kp.files) == NPZ_KEYS
        n = len(expected)
        assert n > 10 and f" {n} keypoints " in line
        assert kp["pt"].shape == (n, 2) and kp["pt"].dtype == np.float32
        for key in ("size", "angle", "response"):
            assert kp[key].shape == (n,) and kp[key].dtype == np.float32
        for key in ("octave", "class_id"):
            assert kp[key].shape == (n,) and kp[key].dtype == np.int32
        np.testing.assert_array_equal(kp["pt"], expected.xy)
        np.testing.assert_array_equal(kp["size"], expected.size)
        np.testing.assert_array_equal(kp["angle"], expected.angle_deg)  # both detectors orient every keypoint
        np.testing.assert_array_equal(kp["descriptors"], expected.descriptors)
        # Float norms are written as float32 (OpenCV's type) even where Features holds SIFT's bytes.
        assert kp["descriptors"].dtype == (np.uint8 if expected.norm.startswith("HAMMING") else np.float32)
        assert str(kp["detector"]) == detector and str(kp["norm"]) == expected.norm
        assert json.loads(str(kp["params"])) == registry.get("detector", detector).cls().params()


def test_set_changes_a_parameter_and_is_recorded(tmp_path, capsys, images):
    path, _ = images["uint8.npy"]
    counts = {}
    for label, extra in (("default", []), ("ten", ["--set", "n_features=10", "--set", "score_type=fast"])):
        out = tmp_path / f"{label}.npz"
        assert main(["detect", str(path), "--detector", "orb", *extra, "--out", str(out), "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        with np.load(out) as kp:
            counts[label] = len(kp["pt"])
            assert json.loads(str(kp["params"])) == report["params"]
        assert report["n_keypoints"] == counts[label]
    assert report["params"]["n_features"] == 10 and report["params"]["score_type"] == "fast"
    assert counts["ten"] <= 10 < counts["default"]


def test_json_and_overlay_through_the_console_entry_point(tmp_path, images):
    path, _ = images["float.tif"]
    out, overlay = tmp_path / "kp.npz", tmp_path / "kp.png"
    code, stdout, stderr = run_cli("detect", str(path), "--detector", "sift", "--set", "contrast_threshold=1e-3",
                                   "--out", str(out), "--overlay", str(overlay), "--json")
    assert code == 0, stderr
    report = json.loads(stdout)
    assert report["detector"] == "sift" and report["params"]["contrast_threshold"] == 0.001
    assert report["image"] == {"path": str(path), "shape": [ROWS, COLS], "dtype": "float32"}
    assert report["outputs"] == {"out": str(out), "overlay": str(overlay)}
    assert report["seconds"] >= 0 and report["n_keypoints"] == len(np.load(out)["pt"])
    data = overlay.read_bytes()
    rows, cols = png_size(data)
    assert rows % ROWS == 0 and rows // ROWS == cols // COLS and cols % COLS == 0  # one integer scale
    assert imread(io.BytesIO(data)).shape[:2] == (rows, cols)
    assert leftovers(tmp_path) == ["kp.npz", "kp.png"]


def test_overlay_draws_circles_of_the_keypoint_size_and_ticks_in_opencv_convention():
    # One keypoint pointing down the image (90 deg: from +x towards +y, y down), one without
    # an orientation; on a black image only the drawing is bright.
    features = Features.build(xy=[[20.0, 20.0], [60.0, 40.0]], size=[16.0, 8.0], angle_deg=[90.0, np.nan],
                              response=[2.0, 1.0], descriptors=np.zeros((2, 4), np.float32), norm="L2")
    scale = 4
    picture = imread(io.BytesIO(keypoints_png(np.zeros((64, 80), np.float32), features, scale=scale)))
    assert picture.shape[:2] == (64 * scale, 80 * scale)
    bright = picture[..., :3].max(axis=2) > 100

    def lit(x, y):  # any bright output pixel within 1 px of image point (x, y)
        cx, cy = int(round((x + 0.5) * scale)), int(round((y + 0.5) * scale))
        return bright[cy - 1:cy + 2, cx - 1:cx + 2].any()

    assert lit(20, 20 + 4) and not lit(20, 20 - 4)          # tick runs down (+y), not up
    assert lit(20, 20 + 8) and lit(20 - 8, 20) and lit(20 + 8, 20) and lit(20, 20 - 8)  # radius = size / 2
    assert not lit(20 + 4, 20) and not lit(20 - 4, 20)
    assert lit(60 + 4, 40) and lit(60, 40 - 4) and not lit(60 + 2, 40) and not lit(60, 40 + 2)  # no tick


def test_angle_nan_is_written_as_opencv_minus_one(tmp_path):
    features = Features.build(xy=[[1.0, 2.0], [3.0, 4.0]], size=[5.0, 6.0], angle_deg=[np.nan, 45.0],
                              response=[2.0, 1.0], descriptors=np.zeros((2, 4), np.uint8), norm="HAMMING")
    with np.load(write_keypoints(tmp_path / "kp.npz", features, detector="x", params={"k": (1, 2)})) as kp:
        np.testing.assert_array_equal(kp["angle"], np.float32([-1.0, 45.0]))
        assert json.loads(str(kp["params"])) == {"k": [1, 2]} and str(kp["norm"]) == "HAMMING"
        assert not {"clipped_side", "centre_edge_px", "centre_se_px"} & set(kp.files)


def test_the_side_a_clip_cuts_a_disc_on_is_written_with_its_keypoint(tmp_path):
    """The ``beads`` detector's ``clipped_side``, ``centre_edge_px`` and ``centre_se_px``, in the keypoints' order
    (strongest first)."""
    features = Features.build(xy=[[1.0, 2.0], [3.0, 4.0]], size=[5.0, 6.0], angle_deg=[np.nan, np.nan],
                              response=[1.0, 2.0], descriptors=np.zeros((2, 2), np.float32), norm="L2",
                              clipped_side=[[0.0, 0.0], [-0.3, 0.1]], centre_edge_px=[2.5, 2.4],
                              centre_se_px=[0.01, np.nan])
    with np.load(write_keypoints(tmp_path / "kp.npz", features, detector="beads", params={})) as kp:
        np.testing.assert_array_equal(kp["pt"][0], np.float32([3.0, 4.0]))
        np.testing.assert_array_equal(kp["clipped_side"], np.float32([[-0.3, 0.1], [0.0, 0.0]]))
        np.testing.assert_array_equal(kp["centre_edge_px"], np.float32([2.4, 2.5]))
        np.testing.assert_array_equal(kp["centre_se_px"], np.float32([np.nan, 0.01]))
    for name in ("centre_edge_px", "centre_se_px"):
        with pytest.raises(InputError, match=rf"Features.{name} must have shape \(2,\)"):
            Features(xy=features.xy, size=features.size, angle_deg=features.angle_deg, response=features.response,
                     octave=features.octave, class_id=features.class_id, descriptors=features.descriptors, norm="L2",
                     **{name: np.zeros(3, np.float32)})


@pytest.mark.parametrize("text, expected", [
    ("n_features=500", ("n_features", 500)),
    ("upright=true", ("upright", True)),
    ("score_type=fast", ("score_type", "fast")),
    ("contrast_threshold=1e-3", ("contrast_threshold", 0.001)),  # YAML 1.1 alone would give a string
    ("sigma=1.6", ("sigma", 1.6)),
    ("baselines=[1, 2]", ("baselines", [1, 2])),
])
def test_set_values_are_read_as_yaml(text, expected):
    assert _key_value(text) == expected


@pytest.fixture()
def bad_images(tmp_path, blobs):
    folder = tmp_path / "bad"
    folder.mkdir()
    np.save(folder / "stack.npy", np.stack([blobs, blobs]))
    with_nan = blobs.copy()
    with_nan[5, 7] = np.nan
    np.save(folder / "nan.npy", with_nan)
    np.save(folder / "empty.npy", np.zeros((0, 8), np.float32))
    imsave(folder / "colour.png", np.zeros((16, 16, 3), np.uint8), check_contrast=False)
    np.save(folder / "good.npy", blobs)
    return folder


@pytest.mark.parametrize("image, extra, message", [
    ("stack.npy", [], "stack.npy: image must be a 2-dimensional array (rows, cols), got shape (2, 112, 144)"),
    ("nan.npy", [], "nan.npy: image has 1 NaN or infinite pixels"),
    ("empty.npy", [], "empty.npy: image is empty (shape (0, 8))"),
    ("colour.png", [], "colour.png: image must be a 2-dimensional grey-level array (rows, cols), got a colour"),
    ("missing.npy", [], "missing.npy: no such file"),
    ("good.npy", ["--detector", "nope"], "detector.name: unknown detector 'nope'; registered detectors: akaze"),
    ("good.npy", ["--set", "n_featurs=5"], "detector.n_featurs: unknown parameter of detector 'sift'; allowed: "
                                           "n_features, "),
    ("good.npy", ["--set", "n_features=many"], "detector.n_features: must be an integer >= 0 and <= 1000000, got 'many'"),
    ("good.npy", ["--set", "sigma=1", "--set", "sigma=2"], "detector.sigma: given twice"),
])
def test_bad_input_exits_2_with_one_line_and_writes_nothing(capsys, bad_images, image, extra, message):
    out, overlay = bad_images / "kp.npz", bad_images / "kp.png"
    args = ["detect", str(bad_images / image), "--detector", "sift", *extra, "--out", str(out),
            "--overlay", str(overlay)]
    assert main(args) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("ctpipe: error: ") and captured.err.count("\n") == 1
    assert message in captured.err
    assert leftovers(bad_images) == ["colour.png"]


def test_usage_errors_exit_2_with_one_line_through_the_entry_point(bad_images):
    good, npz, png = (str(bad_images / name) for name in ("good.npy", "kp.npz", "kp.png"))
    for argv, message in (
        (["--detector", "sift", "--set", "n_features", "--out", npz],
         "argument --set: must be key=value (e.g. n_features=500), got 'n_features'"),
        (["--detector", "sift", "--out", png], f"--out {png}: must be a .npz file name"),
        (["--out", npz], "the following arguments are required: --detector"),
    ):
        code, stdout, stderr = run_cli("detect", good, *argv)
        assert code == 2 and stdout == ""
        assert stderr.startswith("ctpipe: error: ") and stderr.count("\n") == 1 and message in stderr
    assert leftovers(bad_images) == ["colour.png"]


def test_a_failure_while_writing_leaves_no_file(tmp_path, monkeypatch, images):
    path, _ = images["uint8.npy"]
    out, overlay = tmp_path / "kp.npz", tmp_path / "kp.png"

    def broken_savez(handle, **arrays):
        handle.write(b"PK\x03\x04 half an archive")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        main(["detect", str(path), "--detector", "orb", "--out", str(out), "--overlay", str(overlay)])
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("detector, size", [("orb", 1), ("brisk", 2)])
def test_images_too_small_for_an_opencv_pyramid_exit_2_with_one_line(tmp_path, capsys, detector, size):
    np.save(tmp_path / "tiny.npy", np.zeros((size, size), np.uint8))
    code = main(["detect", str(tmp_path / "tiny.npy"), "--detector", detector, "--out", str(tmp_path / "kp.npz")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert f"{detector} cannot run on a {size} x {size} image" in err
    assert not (tmp_path / "kp.npz").exists()
