"""The training CLI end to end: a short run, resume, SIGTERM checkpointing, evaluate and plot.

Tiny preset, 96 points per cloud (72 after the partial crop), batches of 2, a few steps: the
whole module takes well under a minute on two cores.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("h5py")

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_ROOT = REPO_ROOT.parent / "shared" / "data"

COMMON = [
    "--preset", "tiny", "--batch-size", "2", "--points-per-cloud", "96", "--val-every", "2",
    "--val-pairs", "4", "--workers", "0", "--no-progress", "--warmup-steps", "2",
    "--data-root", str(DATA_ROOT),
]


def _run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    result = subprocess.run(
        args, cwd=REPO_ROOT, capture_output=True, text=True, timeout=timeout,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert result.returncode == 0, f"exit {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result


def _log(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


def _checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, shared_data) -> Path:
    out = tmp_path_factory.mktemp("run")
    _run([sys.executable, "-m", "training.train", "--out", str(out), "--max-steps", "3", *COMMON])
    return out


def test_short_run_writes_checkpoint_and_log(trained):
    checkpoint = _checkpoint(trained / "last.pt")
    assert checkpoint["step"] == 3 and checkpoint["pairs_seen"] == 6
    assert checkpoint["wall_time_s"] > 0
    for key in ("model", "optimizer", "scheduler", "rng_states", "model_config", "geometry_config",
                "normalization_config", "train_args", "git_commit", "best_metric"):
        assert key in checkpoint, key
    assert checkpoint["model_config"]["descriptor_dim"] == 24  # tiny
    assert (trained / "best.pt").is_file()

    records = _log(trained)
    train = [r for r in records if r["type"] == "train"]
    val = [r for r in records if r["type"] == "val"]
    assert [r["step"] for r in train] == [1, 2, 3]
    assert {"loss", "nll", "lr", "pairs_seen", "wall_time_s", "epoch"} <= set(train[0])
    assert [r["step"] for r in val] == [2, 3]  # every 2 steps, plus the final one
    assert {"val_loss", "val_precision", "val_accuracy", "val_recall", "val_rot_median_deg",
            "val_rot_mean_deg"} <= set(val[0])
    assert records[-1]["type"] == "stop" and records[-1]["reason"] == "max_steps"


def test_resume_auto_continues_step_and_wall_time(trained):
    before = _checkpoint(trained / "last.pt")
    # Script form this time: ``python training/train.py`` must find the package too.
    _run([sys.executable, "training/train.py", "--out", str(trained), "--resume", "auto",
          "--max-steps", "5", *COMMON])
    after = _checkpoint(trained / "last.pt")
    assert after["step"] == 5 and after["pairs_seen"] == 10
    assert after["wall_time_s"] > before["wall_time_s"]
    records = _log(trained)
    assert any(r["type"] == "resume" and r["step"] == 3 for r in records)
    steps = [r["step"] for r in records if r["type"] == "train"]
    assert steps == [1, 2, 3, 4, 5]
    times = [r["wall_time_s"] for r in records if r["type"] == "train"]
    assert times == sorted(times)  # the wall-time counter carries over
    # The optimiser really continued (Adam's step count).
    states = after["optimizer"]["state"]
    assert int(next(iter(states.values()))["step"]) == 5


def test_sigterm_writes_a_checkpoint(tmp_path, shared_data):
    out = tmp_path / "sig"
    process = subprocess.Popen(
        [sys.executable, "-m", "training.train", "--out", str(out), "--max-steps", "100000",
         *COMMON, "--val-every", "0"],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 60
        log = out / "log.jsonl"
        while time.monotonic() < deadline:  # wait for two training steps
            if log.is_file() and sum('"type": "train"' in line for line in log.read_text().splitlines()) >= 2:
                break
            assert process.poll() is None, process.communicate()
            time.sleep(0.2)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, stderr
    checkpoint = _checkpoint(out / "last.pt")
    assert checkpoint["step"] >= 2
    last = _log(out)[-1]
    assert last["type"] == "stop" and last["reason"] == "signal SIGTERM" and last["step"] == checkpoint["step"]


def test_evaluate_and_plot_cli(trained, tmp_path):
    report = tmp_path / "eval.md"
    result = _run([sys.executable, "-m", "training.evaluate", str(trained / "last.pt"), "--protocols",
                   "clean", "partial", "--pairs", "2", "--workers", "0", "--no-progress",
                   "--data-root", str(DATA_ROOT), "--out", str(report), "--any-orientation"])
    assert "| clean |" in result.stdout and "| partial |" in result.stdout
    assert json.loads((tmp_path / "eval.json").read_text())["meta"]["any_orientation"] is True
    metrics = json.loads((tmp_path / "eval.json").read_text())["metrics"]
    assert set(metrics) == {"clean", "partial"} and metrics["partial"]["pairs"] == 2
    for key in ("rmse_r", "mae_r", "rmse_t", "mae_t", "l_r", "l_t", "l_rmse", "precision", "accuracy", "recall"):
        assert key in metrics["clean"], key

    image = tmp_path / "curves.png"
    _run([sys.executable, "training/plot_curves.py", str(trained / "log.jsonl"), str(image)])
    assert image.stat().st_size > 10_000


def test_evaluate_on_the_checkpoints_validation_split(trained, tmp_path):
    from training.data import load_training_sources, split_training_shapes
    from training.evaluate import validation_dataset

    checkpoint = _checkpoint(trained / "last.pt")
    dataset = validation_dataset(checkpoint, DATA_ROOT)
    expected = split_training_shapes(load_training_sources(DATA_ROOT), 0.05, 0).val
    assert dataset.name == "val" and np.array_equal(dataset.shapes, expected)
    # another training seed carves another validation set: the split follows the checkpoint
    other = validation_dataset({**checkpoint, "train_args": {**checkpoint["train_args"], "seed": 7}}, DATA_ROOT)
    assert not np.array_equal(other.shapes, expected)

    report = tmp_path / "val.md"
    result = _run([sys.executable, "-m", "training.evaluate", str(trained / "last.pt"), "--split", "val",
                   "--protocols", "noisy", "--pairs", "2", "--workers", "0", "--no-progress",
                   "--data-root", str(DATA_ROOT), "--out", str(report)])
    assert "| noisy |" in result.stdout
    saved = json.loads((tmp_path / "val.json").read_text())
    assert saved["meta"]["split"] == "val" and saved["metrics"]["noisy"]["pairs"] == 2
    assert saved["meta"]["any_relative_rotation"] is False
    # The same validation pairs with the target turned alone: the CLI reaches make_pair's turn.
    turned = validation_dataset(checkpoint, DATA_ROOT, any_orientation=True, any_relative_rotation=True)
    plain = validation_dataset(checkpoint, DATA_ROOT, any_orientation=True)
    key = (0, 0, "noisy", 1024)
    np.testing.assert_array_equal(turned[key]["source_user"], plain[key]["source_user"])
    assert not np.allclose(turned[key]["T_gt_user"], plain[key]["T_gt_user"])
    _run([sys.executable, "-m", "training.evaluate", str(trained / "last.pt"), "--split", "val",
          "--protocols", "noisy", "--pairs", "1", "--workers", "0", "--no-progress", "--any-orientation",
          "--any-relative-rotation", "--data-root", str(DATA_ROOT), "--out", str(report)])
    assert json.loads((tmp_path / "val.json").read_text())["meta"]["any_relative_rotation"] is True


def test_plot_marks_where_a_resumed_run_changed_its_pairs(tmp_path):
    from training.plot_curves import plot_curves, read_log_segments

    records = [{"type": "start", "wall_time_s": 0.0, "args": {}}]
    records += [{"type": "train", "step": s, "wall_time_s": float(s), "loss": 2.0, "lr": 1e-3, "pairs_seen": s}
                for s in range(1, 5)]
    records += [{"type": "resume", "wall_time_s": 4.0, "args": {"any_orientation": False}},
                {"type": "resume", "wall_time_s": 6.0, "args": {"any_orientation": True}},
                {"type": "val", "step": 6, "wall_time_s": 6.5, "val_loss": 1.0, "val_rot_median_deg": 1.0},
                {"type": "resume", "wall_time_s": 8.0, "args": {"any_orientation": True}}]
    log = tmp_path / "log.jsonl"
    log.write_text("\n".join(json.dumps(r) for r in records) + "\n{cut by a cra")
    train, val, changes = read_log_segments(log)
    assert len(train) == 4 and len(val) == 1
    # a resume with unchanged pairs is no change; the switch to any orientation is one
    assert [t for t, _ in changes] == [0.0, 6.0] and "any orientation" in changes[1][1]
    assert plot_curves(log, tmp_path / "curves.png").stat().st_size > 10_000


def test_geometry_on_the_device_trains_like_geometry_in_the_workers(tmp_path, shared_data):
    """--geometry-on-device (the torch port) gives the v3 run the same losses, step for step."""
    options = [*COMMON, "--max-steps", "3", "--log-every", "1", "--threads", "1"]
    options[options.index("tiny")] = "tiny_v3"
    logs = []
    for name, extra in (("workers", []), ("device", ["--geometry-on-device"])):
        _run([sys.executable, "-m", "training.train", "--out", str(tmp_path / name), *options, *extra])
        logs.append([r for r in _log(tmp_path / name) if r["type"] in ("train", "val")])
    assert [r["type"] for r in logs[0]] == [r["type"] for r in logs[1]] and len(logs[0]) >= 4
    for worker_record, device_record in zip(*logs):
        key = "loss" if worker_record["type"] == "train" else "val_loss"
        assert device_record[key] == pytest.approx(worker_record[key], rel=1e-4, abs=1e-5)


def _cuboid_surface(sides, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points on the surface of an axis-aligned cuboid centred at the origin."""
    sides = np.asarray(sides, dtype=np.float64)
    points = rng.uniform(-0.5, 0.5, size=(count, 3)) * sides
    face_axis = rng.integers(0, 3, size=count)
    points[np.arange(count), face_axis] = np.sign(rng.normal(size=count)) * 0.5 * sides[face_axis]
    return points


def test_failure_kinds_tell_a_symmetric_flip_from_a_wrong_pose():
    from scipy.spatial.transform import Rotation

    from training.evaluate import PairResult, summarize

    rng = np.random.default_rng(3)
    box = _cuboid_surface((2.0, 1.0, 0.5), 3000, rng)
    # Three arms of different lengths from one corner: no half-turn maps it onto itself.
    tripod = np.concatenate([_cuboid_surface(sides, 1000, rng) + np.asarray(sides) / 2
                             for sides in ((2.0, 0.1, 0.1), (0.1, 1.0, 0.1), (0.1, 0.1, 0.5))])
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [30, 20, 10], degrees=True).as_matrix()
    truth[:3, 3] = [0.3, -0.2, 0.1]
    flipped = truth @ np.diag([1.0, -1.0, -1.0, 1.0])  # half-turn about the source's x axis first
    near = np.eye(4)
    near[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    near = near @ truth

    def result(shape, predicted, pose_failed=False):
        source = shape - shape.mean(axis=0)  # the half-turn's axis runs through the centroid
        return PairResult(
            protocol="partial", index=0, T_pred=predicted, T_gt=truth, source=source,
            target=source @ truth[:3, :3].T + truth[:3, 3], scale=float(np.linalg.norm(source, axis=1).max()),
            pred_match=np.full(len(source), -1), gt_match=np.full(len(source), -1),
            match_count=0, pose_failed=pose_failed, seconds=0.0,
        )

    assert result(box, truth).failure is None
    assert result(box, near).failure == "near miss"
    assert result(box, flipped).failure == "symmetric"
    assert result(tripod, flipped).failure == "wrong"
    assert result(tripod, np.eye(4), pose_failed=True).failure == "no pose"

    summary = summarize([result(box, flipped), result(tripod, flipped), result(box, truth)])
    assert summary["partial"]["failed_symmetric"] == 1 and summary["partial"]["failed_wrong"] == 1
    assert summary["partial"]["rotation_under_5deg"] == 1 / 3


def test_provenance_is_derived_from_the_log_and_its_command_parses_back(trained, tmp_path):
    from training.provenance import derived_provenance
    from training.train import build_parser

    provenance = derived_provenance(trained / "log.jsonl", trained / "last.pt")
    records = _log(trained)
    assert provenance["step"] == records[-1]["step"] and provenance["pairs_seen"] == records[-1]["pairs_seen"]
    assert sum(run["pairs"] for run in provenance["invocations"]) == provenance["pairs_seen"]
    assert set(provenance["validation"]["by_step"]) == {str(r["step"]) for r in records if r["type"] == "val"}

    command = provenance["resume_command"].split()
    assert command[:3] == ["python", "-m", "training.train"]
    parsed = vars(build_parser().parse_args(command[3:]))
    last_arguments = [r for r in records if r["type"] in ("start", "resume")][-1]["args"]
    for name, value in last_arguments.items():
        if name not in ("resume", "max_minutes"):
            assert str(parsed[name]) == str(value), name
    assert parsed["resume"] == str(trained / "last.pt")


def test_training_command_repeats_an_appended_flag_once_per_value():
    """--init-skip is action="append": the rebuilt command gives each prefix its own flag and
    parses back to the same list."""
    from training.provenance import training_command
    from training.train import build_parser

    command = training_command({"out": "runs/x", "init_skip": ["transformer.", "dustbin_score"]})
    assert "--init-skip transformer. --init-skip dustbin_score" in command
    parsed = build_parser().parse_args(command.split()[3:])
    assert parsed.init_skip == ["transformer.", "dustbin_score"]


def test_provenance_lists_each_invocation_with_what_it_changed():
    from training.provenance import invocations

    def progress(kind, step, **extra):
        return {"type": kind, "step": step, "pairs_seen": 8 * step, "wall_time_s": 10.0 * step, **extra}

    records = [
        progress("start", 0, git_commit="a", args={"lr": 1e-3, "out": "runs/x", "max_minutes": 60}),
        progress("train", 5), progress("stop", 5, reason="signal SIGINT"),
        progress("resume", 5, git_commit="b", args={"lr": 1e-3, "out": "elsewhere", "max_minutes": 30}),
        progress("train", 9),  # killed: no stop record
        progress("resume", 9, git_commit="c", args={"lr": 5e-4, "out": "elsewhere"}),
        progress("train", 12),
    ]
    runs = invocations(records)
    assert [(r["from_step"], r["to_step"], r["pairs"]) for r in runs] == [(0, 5, 40), (5, 9, 32), (9, 12, 24)]
    assert [r["git_commit"] for r in runs] == ["a", "b", "c"]
    assert runs[0]["changed_arguments"] == {"lr": 1e-3}  # --out / --max-minutes are not training
    assert runs[1]["changed_arguments"] == {} and runs[2]["changed_arguments"] == {"lr": 5e-4}
    assert runs[0]["ended"] == "signal SIGINT" and "killed" in runs[1]["ended"]
    assert "still running" in runs[2]["ended"]


def test_learning_by_pairs_counts_pairs_from_where_each_run_began(tmp_path):
    """Bins start at the pairs seen at ``since_step``; earlier steps are left out."""
    from training.learning_by_pairs import main, nll_by_pairs

    def train(step, pairs, protocol, nll):
        return {"type": "train", "step": step, "pairs_seen": pairs, "protocol": protocol, "nll": nll}

    records = [{"type": "start"}, train(10, 320, "partial", 9.0), train(20, 640, "partial", 5.0),
               train(30, 960, "partial", 3.0), train(40, 1280, "noisy", 1.0), train(50, 1600, "partial", 2.0)]
    bins = nll_by_pairs(records, since_step=20, bin_pairs=500)
    # Pairs since step 20 (640 seen): 320 and 960 -> bins 0 and 500; step 10 and 20 left out.
    assert bins == {"partial": {0: (3.0, 1), 500: (2.0, 1)}, "noisy": {500: (1.0, 1)}}
    with pytest.raises(ValueError, match="after step 50"):
        nll_by_pairs(records, since_step=50, bin_pairs=500)
    log = tmp_path / "log.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "table.md"
    assert main([str(log), str(log), "--labels", "a", "b", "--since-step", "0", "20", "--bin", "500",
                 "--out", str(out)]) == 0
    table = out.read_text()
    # Run a from step 0: 320 -> bin 0; 640 and 960 -> bin 500 (mean of 5 and 3); 1600 -> 1500.
    assert "| 0-500 | 9.00 (1) | 3.00 (1) |" in table and "| 500-1,000 | 4.00 (2) | 2.00 (1) |" in table
    assert "| 1,500-2,000 | 2.00 (1) | - |" in table


def test_a_weights_only_checkpoint_keeps_the_model_and_resumes_its_schedule(trained, tmp_path):
    full = trained / "last.pt"
    slim = tmp_path / "slim.pt"
    _run([sys.executable, "-m", "training.checkpoint", "weights-only", str(full), str(slim)])
    before, after = _checkpoint(full), _checkpoint(slim)
    assert after["weights_only"] is True
    assert not {"optimizer", "scheduler", "rng_states"} & set(after)
    assert slim.stat().st_size < full.stat().st_size
    assert after["step"] == before["step"] and after["model_config"] == before["model_config"]
    for name, tensor in before["model"].items():
        assert torch.equal(after["model"][name], tensor), name

    out = tmp_path / "resumed"
    result = _run([sys.executable, "-m", "training.train", "--out", str(out), "--resume", str(slim),
                   "--max-steps", str(before["step"] + 2), *COMMON])
    assert "weights-only checkpoint" in result.stderr
    resumed = _checkpoint(out / "last.pt")
    assert resumed["step"] == before["step"] + 2
    # Adam starts afresh (its step count is the steps since the resume) while the schedule
    # continues: the lr of each resumed step is the one an exact resume uses.
    assert int(next(iter(resumed["optimizer"]["state"].values()))["step"]) == 2
    exact = tmp_path / "exact"
    _run([sys.executable, "-m", "training.train", "--out", str(exact), "--resume", str(full),
          "--max-steps", str(before["step"] + 2), *COMMON])

    def learning_rates(run: Path) -> dict[int, float]:
        return {r["step"]: r["lr"] for r in _log(run) if r["type"] == "train"}

    assert sorted(learning_rates(out)) == [before["step"] + 1, before["step"] + 2]
    assert learning_rates(out) == pytest.approx(learning_rates(exact))


def test_weights_only_refuses_to_overwrite_its_input(trained):
    result = subprocess.run(
        [sys.executable, "-m", "training.checkpoint", "weights-only", str(trained / "last.pt"),
         str(trained / "last.pt")],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode != 0 and "must differ" in result.stderr


def test_a_new_cycle_warms_up_and_decays_again_from_its_start():
    """--cycle-start restarts the schedule of a finished run: warm-up from 1 % of lr at the cycle's
    first step, the full lr after its warm-up, the floor at its end; steps before it unchanged."""
    from argparse import Namespace

    from training.train import lr_factor

    first = Namespace(warmup_steps=100, schedule="cosine", decay_steps=7500, max_steps=7500, min_lr_ratio=0.05)
    second = Namespace(**vars(first), cycle_start=7500)
    second.decay_steps, second.max_steps, second.warmup_steps = 2000, 9500, 50
    assert lr_factor(7500, first) == pytest.approx(0.05)  # the first cycle ended at its floor
    assert lr_factor(7500, second) == pytest.approx(0.01)
    assert lr_factor(7550, second) == pytest.approx(1.0)
    assert lr_factor(8525, second) == pytest.approx(0.525, abs=1e-3)  # half-way down the cosine
    assert lr_factor(9500, second) == pytest.approx(0.05)
    assert lr_factor(3000, first) == lr_factor(3000, Namespace(**vars(first), cycle_start=0))
    # Without --decay-steps the cycle runs to --max-steps.
    second.decay_steps = None
    assert lr_factor(9500, second) == pytest.approx(0.05) and lr_factor(8525, second) > 0.5


def test_warm_start_into_a_wider_edge_layout_keeps_the_function():
    """--init-from a v3-layout state into a chiral-layout network: the two new input channels get
    zero weights, so at step 0 the network ignores them and computes what the old one did."""
    from training.config import EDGE_CHANNELS, ModelConfig
    from training.model import LoGDescMatcher
    from training.train import warm_start

    torch.manual_seed(0)
    old_config = ModelConfig.preset("tiny_v3")
    old = LoGDescMatcher(old_config).eval()
    new = LoGDescMatcher(old_config.replace(edge_channels=EDGE_CHANNELS["chiral"])).eval()
    warm_start(new, old.state_dict())
    rng = np.random.default_rng(0)
    edges = torch.from_numpy(rng.normal(size=(1, 64, 30, EDGE_CHANNELS["chiral"])).astype(np.float32))
    points = torch.from_numpy(rng.normal(size=(1, 64, 3)).astype(np.float32))
    normals = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(1, 64, 3)).astype(np.float32)), dim=2)
    with torch.no_grad():
        expected = old.describe(edges[..., : EDGE_CHANNELS["invariant"]], points, normals)
        got = new.describe(edges, points, normals)
    assert torch.allclose(got, expected, atol=1e-6)
    # A state that differs in another way is refused, naming the tensor.
    wrong = {**old.state_dict(), "dustbin_score": torch.zeros(3)}
    with pytest.raises(ValueError, match="dustbin_score"):
        warm_start(new, wrong)


def test_warm_start_into_a_descriptor_only_network_skips_the_transformer():
    """--init-from a full network into one without transformer layers, --init-skip 'transformer.':
    the descriptor is copied, the final map keeps its own start (s I), and the saved transformer
    layers the new network lacks are not asked for."""
    from training.config import ModelConfig
    from training.model import LoGDescMatcher
    from training.train import warm_start

    torch.manual_seed(0)
    config = ModelConfig.preset("tiny_v3")
    full = LoGDescMatcher(config)
    alone = LoGDescMatcher(config.replace(transformer_layers=0))
    own_projection = alone.transformer.projection.weight.detach().clone()
    warm_start(alone, full.state_dict(), skip=("transformer.",))
    for name, tensor in alone.descriptor.state_dict().items():
        assert torch.equal(tensor, full.descriptor.state_dict()[name]), name
    assert torch.equal(alone.transformer.projection.weight, own_projection)
    assert torch.equal(alone.dustbin_score, full.dustbin_score)
    # Without the skip the saved projection (trained after the layers) is copied.
    warm_start(alone, full.state_dict())
    assert torch.equal(alone.transformer.projection.weight, full.transformer.projection.weight)



def test_distilling_from_the_model_itself_starts_at_zero_and_from_another_does_not(trained, tmp_path):
    """--distill-from adds the KL term to every step: a student warm-started from its teacher
    logs ~0 at its first step, a fresh student a clearly positive term, and a teacher reading
    other geometry is refused."""
    teacher = str(trained / "last.pt")
    options = [*COMMON, "--max-steps", "1", "--log-every", "1", "--val-every", "0", "--distill-from", teacher]
    _run([sys.executable, "-m", "training.train", "--out", str(tmp_path / "same"), *options, "--init-from", teacher])
    _run([sys.executable, "-m", "training.train", "--out", str(tmp_path / "fresh"), *options, "--seed", "5"])
    same, fresh = ([r for r in _log(tmp_path / name) if r["type"] == "train"][0] for name in ("same", "fresh"))
    assert abs(same["distill"]) < 1e-3
    assert fresh["distill"] > 0.01  # two barely trained tiny networks: near-uniform plans, a small KL
    assert fresh["loss"] == pytest.approx(fresh["nll"] + 0.1 * fresh["infonce"] + fresh["distill"], rel=1e-4)

    other = [*options]
    other[other.index("tiny")] = "tiny_v3"
    refused = subprocess.run(
        [sys.executable, "-m", "training.train", "--out", str(tmp_path / "other"), *other],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120,
    )
    assert refused.returncode != 0 and "same geometry" in refused.stderr
