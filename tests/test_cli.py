"""The ``logdesc-rt`` command line, run as a user would (a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from logdesc_rt.demo import make_demo_pair
from logdesc_rt.io import read_point_cloud, write_point_cloud
from logdesc_rt.metrics import rotation_error_deg


def run_cli(*arguments: str, prelude: str = "") -> subprocess.CompletedProcess:
    """Run the CLI in a fresh interpreter; ``prelude`` runs first (e.g. to hide a module)."""
    code = f"{prelude}\nimport sys\nfrom logdesc_rt.cli import main\nsys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *arguments], capture_output=True, text=True, timeout=300)


# The registration's first progress line: seeing it means the work started.
STARTED = "matching: geometry"


@pytest.fixture(scope="module")
def cloud_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("clouds")
    pair = make_demo_pair()
    write_point_cloud(folder / "source.ply", pair.source)
    write_point_cloud(folder / "target.pcd", pair.target)
    return folder, pair


def test_register_prints_the_transform_as_json(cloud_files):
    folder, pair = cloud_files
    aligned = folder / "aligned.npy"
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--json",
                        "--write-aligned", str(aligned))
    assert completed.returncode == 0, completed.stderr
    result = json.loads(completed.stdout)
    transformation = np.array(result["transformation"])
    assert transformation.shape == (4, 4)
    assert rotation_error_deg(transformation[:3, :3], pair.true_transformation[:3, :3]) < 2.0
    moved = read_point_cloud(aligned)
    assert np.allclose(moved, pair.source @ transformation[:3, :3].T + transformation[:3, 3])


def test_register_plain_output_is_a_4x4_matrix(cloud_files):
    folder, _ = cloud_files
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"))
    assert completed.returncode == 0, completed.stderr
    assert np.loadtxt(completed.stdout.splitlines()).shape == (4, 4)


def test_demo_prints_its_errors():
    completed = run_cli("demo")
    assert completed.returncode == 0, completed.stderr
    line = next(line for line in completed.stdout.splitlines() if line.startswith("rotation error"))
    assert float(line.split()[2]) < 2.0


def test_describe_writes_descriptors(cloud_files, tmp_path):
    folder, pair = cloud_files
    out = tmp_path / "descriptors.npz"
    completed = run_cli("describe", str(folder / "source.ply"), "--out", str(out))
    assert completed.returncode == 0, completed.stderr
    with np.load(out) as saved:
        assert saved["descriptors"].shape[0] == len(pair.source)
        assert np.allclose(saved["points"], pair.source)


def test_errors_are_reported_without_a_traceback(tmp_path):
    (tmp_path / "empty.xyz").write_text("")
    # Both files are checked before either is read: the missing one is named first.
    completed = run_cli("register", str(tmp_path / "empty.xyz"), str(tmp_path / "missing.ply"))
    assert completed.returncode == 2
    assert "error:" in completed.stderr and "missing.ply" in completed.stderr
    assert "Traceback" not in completed.stderr
    (tmp_path / "other.xyz").write_text("1 2 3\n")
    completed = run_cli("register", str(tmp_path / "empty.xyz"), str(tmp_path / "other.xyz"))
    assert completed.returncode == 2
    assert "error:" in completed.stderr and "empty.xyz" in completed.stderr
    assert "Traceback" not in completed.stderr


def test_register_writes_a_before_after_picture(cloud_files, tmp_path):
    pytest.importorskip("matplotlib")
    folder, _ = cloud_files
    picture = tmp_path / "registration.png"
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--plot", str(picture))
    assert completed.returncode == 0, completed.stderr
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_version_and_help_say_what_a_user_needs():
    completed = run_cli("--version")
    assert completed.returncode == 0 and completed.stdout.strip().startswith("logdesc-rt 0.")
    help_text = run_cli("register", "--help").stdout
    for needed in (".ply", ".pcd", ".xyz", ".npy", ".off", "auto", "ransac", "1024", "success", "--allow-failure",
                   "exit codes", "--init", "--config", "matplotlib"):
        assert needed in help_text, needed


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("--write-aligned", "{tmp}/no/such/folder/out.ply"), "does not exist"),
        (("--write-aligned", "{tmp}/out.las"), "unsupported suffix"),
        (("--plot", "{tmp}/picture.jpg"), "unsupported suffix"),
        (("--config", "{tmp}/missing.json"), "cannot read"),
        (("--init", "{tmp}/missing.txt"), "no such file"),
    ],
)
def test_bad_outputs_and_options_fail_before_the_work(cloud_files, tmp_path, arguments, message):
    folder, _ = cloud_files
    arguments = [argument.format(tmp=tmp_path) for argument in arguments]
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), *arguments)
    assert completed.returncode == 2
    assert message in completed.stderr and "Traceback" not in completed.stderr
    assert STARTED not in completed.stderr  # refused before registering


def test_plot_without_matplotlib_fails_before_the_work(cloud_files, tmp_path):
    folder, _ = cloud_files
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"),
                        "--plot", str(tmp_path / "picture.png"), prelude="import sys; sys.modules['matplotlib'] = None")
    assert completed.returncode == 2 and "matplotlib" in completed.stderr
    assert STARTED not in completed.stderr and not (tmp_path / "picture.png").exists()


@pytest.fixture(scope="module")
def beyond_range_files(tmp_path_factory):
    """The demo pair with the target turned a further 150 deg: beyond the model's range."""
    from scipy.spatial.transform import Rotation

    folder = tmp_path_factory.mktemp("beyond")
    pair = make_demo_pair()
    turn = Rotation.from_euler("y", 150, degrees=True).as_matrix()
    write_point_cloud(folder / "source.ply", pair.source)
    write_point_cloud(folder / "target.ply", pair.target @ turn.T)
    return folder


def test_a_failed_registration_has_its_own_exit_code(beyond_range_files):
    folder = beyond_range_files
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.ply"), "--json")
    assert completed.returncode == 3, completed.stderr
    result = json.loads(completed.stdout)  # the pose is still printed
    assert result["success"] is False and np.array(result["transformation"]).shape == (4, 4)
    assert "NOT A SUCCESS" in completed.stderr
    allowed = run_cli("register", str(folder / "source.ply"), str(folder / "target.ply"), "--allow-failure")
    assert allowed.returncode == 0


def test_json_reports_success_confidence_and_config(cloud_files, tmp_path):
    folder, _ = cloud_files
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"estimator": "svd", "fsr": {"iterations": 9}}))
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--json",
                        "--config", str(config), "--seed", "3")
    assert completed.returncode == 0, completed.stderr
    result = json.loads(completed.stdout)
    assert result["success"] is True and 0 <= result["confidence"] <= 1
    assert result["pose_estimator"] == "svd" and result["config"]["estimator"] == "svd"
    assert result["config"]["fsr"] == {**result["config"]["fsr"], "iterations": 9, "seed": 3}
    assert STARTED in completed.stderr  # progress on stderr, JSON alone on stdout
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"fsr": {"tau": 1}}))
    refused = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--config", str(bad))
    assert refused.returncode == 2 and "tau" in refused.stderr and STARTED not in refused.stderr


def test_init_file_joins_the_candidates(cloud_files, tmp_path):
    folder, pair = cloud_files
    init = tmp_path / "init.json"
    init.write_text(json.dumps({"transformation": pair.true_transformation.tolist()}))
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--json",
                        "--init", str(init))
    assert completed.returncode == 0, completed.stderr
    hypotheses = json.loads(completed.stdout)["hypotheses"]
    assert any("init" in hypothesis["estimators"] for hypothesis in hypotheses)


def test_write_aligned_keeps_normals_and_colours(cloud_files, tmp_path):
    from logdesc_rt.io import read_point_attributes

    folder, pair = cloud_files
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(len(pair.source), 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    attributes = {"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2],
                  "red": rng.integers(0, 256, len(pair.source)).astype(np.uint8)}
    write_point_cloud(tmp_path / "coloured.ply", pair.source, attributes)
    aligned = tmp_path / "aligned.ply"
    completed = run_cli("register", str(tmp_path / "coloured.ply"), str(folder / "target.pcd"), "--json",
                        "--write-aligned", str(aligned))
    assert completed.returncode == 0, completed.stderr
    rotation = np.array(json.loads(completed.stdout)["transformation"])[:3, :3]
    kept = read_point_attributes(aligned)
    assert np.array_equal(kept["red"], attributes["red"])
    turned = np.stack([kept["nx"], kept["ny"], kept["nz"]], axis=1)
    assert np.allclose(turned, normals @ rotation.T, atol=1e-9)
