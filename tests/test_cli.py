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
    code = f"{prelude}\nimport sys\nfrom logdesc_rt.tools.cli import main\nsys.exit(main(sys.argv[1:]))"
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
    from logdesc_rt.config import DEFAULT_WORKING_SIZE

    with np.load(out) as saved:
        described = min(len(pair.source), DEFAULT_WORKING_SIZE)  # the working subset of a larger cloud
        assert saved["descriptors"].shape[0] == described == len(saved["points"])
        # The points described are points of the cloud, each once.
        source_rows = {tuple(np.round(row, 6)) for row in pair.source}
        assert all(tuple(np.round(row, 6)) in source_rows for row in saved["points"])


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
    from logdesc_rt.config import DEFAULT_WORKING_SIZE

    for needed in (".ply", ".pcd", ".xyz", ".npy", ".off", "auto", "ransac", f"{DEFAULT_WORKING_SIZE} points",
                   "success", "--allow-failure", "exit codes", "--init", "--config", "--second-draw", "matplotlib"):
        assert needed in help_text, needed


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("--write-aligned", "{tmp}/no/such/folder/out.ply"), "does not exist"),
        (("--write-aligned", "{tmp}/out.obj"), "unsupported suffix"),
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
def unregistrable_files(tmp_path_factory):
    """Two ends of the demo shape, cut across its longest axis, that share no surface: no pose
    is right, whatever the model (an invariant one registers any rotation of the demo pair)."""
    folder = tmp_path_factory.mktemp("unregistrable")
    points = make_demo_pair().source
    centred = points - points.mean(axis=0)
    along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
    gap = 0.05 * np.ptp(along)
    write_point_cloud(folder / "source.ply", points[along < -gap])
    write_point_cloud(folder / "target.ply", points[along > gap])
    return folder


def test_a_failed_registration_has_its_own_exit_code(unregistrable_files):
    folder = unregistrable_files
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


def test_second_draw_flag_sets_the_config_over_the_file(cloud_files, tmp_path):
    """--second-draw turns SubsamplingConfig.second_draw on, beside a --config file's settings."""
    folder, _ = cloud_files
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"subsampling": {"method": "voxel"}}))
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--json",
                        "--config", str(config), "--second-draw")
    assert completed.returncode == 0, completed.stderr
    result = json.loads(completed.stdout)
    assert result["config"]["subsampling"]["second_draw"] is True
    assert result["draws"] == (1 if result["success"] else 2)
    plain = json.loads(run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"), "--json").stdout)
    assert plain["config"]["subsampling"]["second_draw"] is False and plain["draws"] == 1


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


# ----------------------------------------------------------------------------- register-many, align
@pytest.fixture(scope="module")
def many_files(tmp_path_factory):
    """Two demo pairs (different seeds) and a cloud far from everything, in one folder."""
    folder = tmp_path_factory.mktemp("many")
    first, second = make_demo_pair(), make_demo_pair(seed=2)
    write_point_cloud(folder / "a.ply", first.source)
    write_point_cloud(folder / "b.xyz", first.target)
    write_point_cloud(folder / "c.ply", second.source)
    write_point_cloud(folder / "d.npy", second.target)
    stray = np.random.default_rng(1).normal(size=(800, 3)) * [0.3, 0.1, 0.05] + [3.0, 0.0, 0.0]
    write_point_cloud(folder / "stray.npy", stray)
    return folder, first


def _jsonl(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_register_many_reads_a_csv_and_resumes(many_files, tmp_path):
    folder, _ = many_files
    # Relative paths are read from the CSV's folder, wherever the command runs.
    (folder / "good.csv").write_text("id,source,target\nfirst,a.ply,b.xyz\nsecond,c.ply,d.npy\n")
    out = tmp_path / "results.jsonl"
    completed = run_cli("register-many", str(folder / "good.csv"), "--out", str(out), "--workers", "0")
    assert completed.returncode == 0, completed.stderr
    records = _jsonl(out)
    assert [record["id"] for record in records] == ["first", "second"]
    assert all(record["ok"] and record["success"] for record in records)
    assert records[0]["source"] == str(folder / "a.ply")
    assert "2 success, 0 not a success, 0 errors" in completed.stdout
    assert "first: success" in completed.stderr  # progress per pair on stderr

    # A missing cloud is an error record, not a lost run: exit 3, and the good pairs are
    # skipped on resume (only the new one runs).
    (folder / "bad.csv").write_text("a.ply,b.xyz,first\nc.ply,d.npy,second\nc.ply,missing.ply\n")
    completed = run_cli("register-many", str(folder / "bad.csv"), "--out", str(out), "--workers", "0")
    assert completed.returncode == 3, completed.stderr
    first_run, records = records, _jsonl(out)
    assert len(records) == 3 and records[:2] == first_run, "the done pairs were not run again"
    assert records[2]["id"] == "c.ply -> missing.ply" and records[2]["ok"] is False
    assert records[2]["error"]["type"] == "PointCloudFileError" and "missing.ply" in records[2]["error"]["message"]
    assert "2 already in" in completed.stdout and "first: success" not in completed.stderr
    allowed = run_cli("register-many", str(folder / "bad.csv"), "--out", str(out), "--workers", "0",
                      "--allow-failure", "--quiet")
    assert allowed.returncode == 0 and "done:" not in allowed.stderr  # --quiet: no progress lines
    # --no-resume starts the file afresh.
    completed = run_cli("register-many", str(folder / "good.csv"), "--out", str(out), "--workers", "0",
                        "--no-resume", "--estimator", "svd", "--quiet")
    assert completed.returncode == 0, completed.stderr
    assert [(r["id"], r["pose_estimator"]) for r in _jsonl(out)] == [("first", "svd"), ("second", "svd")]


@pytest.mark.parametrize(
    ("csv_text", "arguments", "message"),
    [
        (None, (), "no such file"),
        ("source,target\n", (), "a header but no pairs"),
        ("a.ply\n", (), "row 1: 1 cells"),
        ("a.ply,b.xyz,x\nc.ply,d.npy,x\n", (), "repeats row 1"),
        ("source,target,colour\na.ply,b.xyz,red\n", (), "must name source, target"),
        ("a.ply,b.xyz\n", ("--out", "{tmp}/no/such/folder/out.jsonl"), "does not exist"),
        ("a.ply,b.xyz\n", ("--out", "{tmp}/out.csv"), "unsupported suffix"),
        ("a.ply,b.xyz\n", ("--config", "{tmp}/missing.json"), "cannot read"),
        ("a.ply,b.xyz\n", ("--address", "auto"), "--backend ray only"),
    ],
)
def test_register_many_refuses_bad_input_before_the_work(many_files, tmp_path, csv_text, arguments, message):
    folder, _ = many_files
    pairs = tmp_path / "pairs.csv"
    if csv_text is not None:
        pairs.write_text(csv_text.replace("a.ply", str(folder / "a.ply")).replace("b.xyz", str(folder / "b.xyz")))
    arguments = [argument.format(tmp=tmp_path) for argument in arguments]
    if "--out" not in arguments:
        arguments += ["--out", str(tmp_path / "results.jsonl")]
    completed = run_cli("register-many", str(pairs), *arguments, "--workers", "0")
    assert completed.returncode == 2, completed.stderr
    assert message in completed.stderr and "Traceback" not in completed.stderr
    assert not (tmp_path / "results.jsonl").exists(), "refused before any record was written"


def test_register_many_ray_backend_needs_ray_checked_up_front(many_files, tmp_path):
    folder, _ = many_files
    (tmp_path / "pairs.csv").write_text(f"{folder / 'a.ply'},{folder / 'b.xyz'}\n")
    completed = run_cli("register-many", str(tmp_path / "pairs.csv"), "--out", str(tmp_path / "r.jsonl"),
                        "--backend", "ray", prelude="import sys; sys.modules['ray'] = None")
    assert completed.returncode == 2 and "logdesc-rt[ray]" in completed.stderr
    assert not (tmp_path / "r.jsonl").exists()


def test_align_writes_poses_merged_cloud_and_overview(many_files, tmp_path):
    from logdesc_rt.io import read_point_attributes

    folder, pair = many_files
    scans = [str(folder / "a.ply"), str(folder / "b.xyz"), str(folder / "stray.npy")]
    out, merged, pairs = tmp_path / "poses.json", tmp_path / "merged.ply", tmp_path / "pairs.jsonl"
    extra = ["--merged", str(merged), "--voxel", "0.02", "--pairs", str(pairs), "--workers", "0"]
    has_matplotlib = subprocess.run([sys.executable, "-c", "import matplotlib"]).returncode == 0
    if has_matplotlib:
        extra += ["--plot", str(tmp_path / "overview.png")]
    completed = run_cli("align", *scans, "--out", str(out), *extra)
    # The stray cloud overlaps nothing: reported disconnected, exit 3, poses written anyway.
    assert completed.returncode == 3, completed.stderr
    assert "stray.npy: DISCONNECTED" in completed.stdout and "disconnected" in completed.stderr
    result = json.loads(out.read_text())
    assert set(result["poses"]) == set(scans[:2]) and result["disconnected"] == [scans[2]]
    assert result["reference"] == scans[0] and f"{scans[0]}: placed (reference)" in completed.stdout
    np.testing.assert_array_equal(result["poses"][scans[0]], np.eye(4))
    # b's points into a's frame: the inverse of the pair's source -> target pose.
    truth = np.linalg.inv(pair.true_transformation)
    assert rotation_error_deg(np.array(result["poses"][scans[1]])[:3, :3], truth[:3, :3]) < 2.0
    assert [(p["source"], p["target"]) for p in result["pairs"]] == [(scans[1], scans[0])]
    assert len(_jsonl(pairs)) == 3
    scan_index = read_point_attributes(merged)["scan"]
    assert set(np.unique(scan_index)) == {0, 1}
    assert len(scan_index) < 2 * 768, "the merged cloud is voxel-thinned"
    if has_matplotlib:
        assert (tmp_path / "overview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Rerun from the pairs file into b's frame: nothing registered again (the records are
    # kept: still 3), the same relative pose, --allow-failure exits 0.
    again = run_cli("align", *scans, "--out", str(out), "--pairs", str(pairs), "--workers", "0",
                    "--reference", scans[1], "--allow-failure")
    assert again.returncode == 0, again.stderr
    assert len(_jsonl(pairs)) == 3
    in_b = json.loads(out.read_text())
    assert in_b["reference"] == scans[1]
    np.testing.assert_array_equal(in_b["poses"][scans[1]], np.eye(4))
    np.testing.assert_allclose(in_b["poses"][scans[0]], np.linalg.inv(result["poses"][scans[1]]), atol=1e-9)


@pytest.mark.parametrize(
    ("arguments", "message", "prelude"),
    [
        (("{a}",), "at least 2 scans", ""),
        (("{a}", "{a}"), "more than once", ""),
        (("{a}", "{tmp}/missing.ply"), "no such file", ""),
        (("{a}", "{b}", "--out", "{tmp}/poses.txt"), "unsupported suffix", ""),
        (("{a}", "{b}", "--merged", "{tmp}/merged.off"), "unsupported suffix", ""),
        (("{a}", "{b}", "--voxel", "-1"), "--voxel", ""),
        (("{a}", "{b}", "--reference", "{tmp}/c.ply"), "not one of the scans", ""),
        (("{a}", "{b}", "--pairs", "{tmp}/no/folder/p.jsonl"), "does not exist", ""),
        (("{a}", "{b}", "--plot", "{tmp}/o.png"), "matplotlib", "import sys; sys.modules['matplotlib'] = None"),
    ],
)
def test_align_refuses_bad_input_before_the_work(many_files, tmp_path, arguments, message, prelude):
    folder, _ = many_files
    arguments = [a.format(a=folder / "a.ply", b=folder / "b.xyz", tmp=tmp_path) for a in arguments]
    if "--out" not in arguments:
        arguments += ["--out", str(tmp_path / "poses.json")]
    completed = run_cli("align", *arguments, "--workers", "0", prelude=prelude)
    assert completed.returncode == 2, completed.stderr
    assert message in completed.stderr and "Traceback" not in completed.stderr
    assert "aligning" not in completed.stderr and not (tmp_path / "poses.json").exists()


def test_register_reads_and_writes_las_and_e57(cloud_files, tmp_path):
    pytest.importorskip("laspy")
    pytest.importorskip("pye57")
    folder, pair = cloud_files
    write_point_cloud(tmp_path / "source.laz", pair.source)
    write_point_cloud(tmp_path / "target.e57", pair.target)
    aligned = tmp_path / "aligned.las"
    completed = run_cli("register", str(tmp_path / "source.laz"), str(tmp_path / "target.e57"), "--json",
                        "--write-aligned", str(aligned))
    assert completed.returncode == 0, completed.stderr
    transformation = np.array(json.loads(completed.stdout)["transformation"])
    assert rotation_error_deg(transformation[:3, :3], pair.true_transformation[:3, :3]) < 2.0
    np.testing.assert_allclose(read_point_cloud(aligned),
                               pair.source @ transformation[:3, :3].T + transformation[:3, 3],
                               atol=1e-8)


@pytest.mark.parametrize(("module", "suffix", "extra"), [("laspy", ".las", "logdesc-rt[las]"),
                                                         ("pye57", ".e57", "logdesc-rt[e57]")])
def test_scanner_format_without_its_library_fails_before_the_work(cloud_files, tmp_path, module, suffix, extra):
    folder, _ = cloud_files
    hide = f"import sys; sys.modules[{module!r}] = None"
    completed = run_cli("register", str(folder / "source.ply"), str(folder / "target.pcd"),
                        "--write-aligned", str(tmp_path / f"aligned{suffix}"), prelude=hide)
    assert completed.returncode == 2 and extra in completed.stderr, completed.stderr
    assert STARTED not in completed.stderr and "Traceback" not in completed.stderr
    (tmp_path / f"scan{suffix}").write_bytes(b"\0" * 64)
    completed = run_cli("align", str(folder / "source.ply"), str(tmp_path / f"scan{suffix}"), "--out",
                        str(tmp_path / "poses.json"), prelude=hide)
    assert completed.returncode == 2 and extra in completed.stderr, completed.stderr
    assert "aligning" not in completed.stderr


def test_the_package_version_has_one_value():
    """pyproject.toml and logdesc_rt.__version__ (what --version prints) say the same."""
    from pathlib import Path

    from logdesc_rt import __version__

    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert pyproject["project"]["version"] == __version__
