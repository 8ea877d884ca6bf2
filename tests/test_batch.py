"""register_many: resumable JSON-lines output, error records, same records for 1 / 2 workers
and Ray (tests/test_batch.py; about a minute on 2 cores, most of it worker start-up)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from logdesc_rt import write_point_cloud
from logdesc_rt.batch import comparable, read_records, register_many
from logdesc_rt.demo import make_demo_pair


@pytest.fixture(scope="module")
def pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Three different pairs (two seeds of the demo object, one pair reversed)."""
    first, second = make_demo_pair(seed=1), make_demo_pair(seed=2)
    return [
        ("first", first.source, first.target),
        ("second", second.source, second.target),
        ("reversed", first.target, first.source),
    ]


def _lines(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_resume_skips_pairs_already_done(pairs, tmp_path):
    output = tmp_path / "results.jsonl"
    first = register_many(pairs[:2], workers=0, output=output, seed=0, progress=False)
    assert [record["id"] for record in first] == ["first", "second"]
    assert all(record["ok"] for record in first)
    assert [record["id"] for record in _lines(output)] == ["first", "second"]

    seen: list[str] = []
    second = register_many(pairs, workers=0, output=output, seed=0, progress=False,
                           on_record=lambda r: seen.append(r["id"]))
    assert seen == ["reversed"], "pairs already in the output must not run again"
    assert [record["id"] for record in second] == ["first", "second", "reversed"]
    assert second[:2] == first[:2], "skipped pairs come back as they were written"
    assert [record["id"] for record in _lines(output)] == ["first", "second", "reversed"]

    fresh: list[str] = []
    register_many(pairs[:1], workers=0, output=output, resume=False, seed=0, progress=False,
                  on_record=lambda r: fresh.append(r["id"]))
    assert fresh == ["first"] and [record["id"] for record in _lines(output)] == ["first"]


def test_a_truncated_last_line_is_ignored_and_rerun(pairs, tmp_path):
    output = tmp_path / "results.jsonl"
    register_many(pairs[:1], workers=0, output=output, seed=0, progress=False)
    with output.open("a") as handle:
        handle.write('{"id": "second", "ok": tr')  # a run killed in the middle of a write
    seen: list[str] = []
    register_many(pairs[:2], workers=0, output=output, seed=0, progress=False, on_record=lambda r: seen.append(r["id"]))
    assert seen == ["second"]
    assert set(read_records(output)) == {"first", "second"}
    assert all(record["ok"] for record in read_records(output).values())


def test_unreadable_file_becomes_an_error_record_and_the_run_goes_on(pairs, tmp_path):
    good_source, good_target = tmp_path / "source.ply", tmp_path / "target.xyz"
    write_point_cloud(good_source, pairs[0][1])
    write_point_cloud(good_target, pairs[0][2])
    corrupt = tmp_path / "corrupt.ply"
    corrupt.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nend_header\n\x00\x01"
    )
    missing = tmp_path / "missing.pcd"
    work = [(good_source, good_target), (corrupt, good_target), (good_source, missing)]
    output = tmp_path / "results.jsonl"
    records = register_many(work, workers=2, output=output, seed=0, progress=False)

    assert [record["id"] for record in records] == [f"{source} -> {target}" for source, target in work]
    assert records[0]["ok"] and records[0]["success"]
    for record in records[1:]:
        assert record["ok"] is False
        assert record["error"]["type"] == "PointCloudFileError"
    assert "corrupt.ply" in records[1]["error"]["message"]
    assert "missing.pcd" in records[2]["error"]["message"]
    assert set(read_records(output)) == {record["id"] for record in records}

    # Resume runs the error records again (the files may have been mended), not the good pair.
    write_point_cloud(missing, pairs[0][2])
    seen: list[str] = []
    again = register_many(work, workers=0, output=output, seed=0, progress=False,
                          on_record=lambda r: seen.append(r["id"]))
    assert seen == [records[1]["id"], records[2]["id"]]
    assert again[2]["ok"] and not again[1]["ok"]


def test_one_and_two_workers_give_the_same_records(pairs):
    one = register_many(pairs, workers=1, threads_per_worker=1, seed=0, progress=False)
    two = register_many(pairs, workers=2, threads_per_worker=1, seed=0, progress=False)
    assert [comparable(r) for r in one] == [comparable(r) for r in two]
    assert all(record["ok"] and record["success"] for record in one)
    # Default threads (2 for one worker, 1 each for two): the same decisions, floats within
    # round-off of the summation order.
    default_one = register_many(pairs, workers=1, seed=0, progress=False)
    for a, b in zip(default_one, two):
        assert (a["success"], a["pose_estimator"], a["correspondence_count"]) == (
            b["success"], b["pose_estimator"], b["correspondence_count"]
        )
        np.testing.assert_allclose(a["transformation"], b["transformation"], rtol=0, atol=1e-9)
        assert a["confidence"] == pytest.approx(b["confidence"], abs=1e-9)


def test_options_reach_the_workers(pairs):
    records = register_many(pairs[:1], workers=0, seed=0, refine="point_to_plane", estimator="fsr", progress=False)
    assert records[0]["refinement"] == "point_to_plane" and records[0]["pose_estimator"] == "fsr"
    assert records[0]["icp"] is not None


def test_bad_arguments_are_named(pairs):
    with pytest.raises(ValueError, match="duplicate pair id"):
        register_many([pairs[0], pairs[0]], workers=0)
    with pytest.raises(ValueError, match="backend"):
        register_many(pairs, backend="dask")
    with pytest.raises(ValueError, match="workers"):
        register_many(pairs, workers=-1)
    with pytest.raises(ValueError, match="pair 0"):
        register_many([("only one",)], workers=0)


def test_ray_backend_gives_the_local_records(pairs):
    ray = pytest.importorskip("ray")
    local = register_many(pairs, workers=2, threads_per_worker=1, seed=0, progress=False)
    bad = ("bad", "/nonexistent/cloud.ply", pairs[0][2])
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = register_many([*pairs, bad], workers=2, backend="ray", seed=0, progress=False)
    finally:
        ray.shutdown()
    assert [comparable(r) for r in remote[:3]] == [comparable(r) for r in local]
    assert remote[3]["ok"] is False and remote[3]["error"]["type"] == "PointCloudFileError"


def test_resume_keeps_a_failed_verdict_and_retries_other_errors(pairs, tmp_path):
    """A pair that cannot be registered is a result (success false, with its reason: too few
    matches, or a pose not verified), the pipeline's verdict on the pair: resuming would only
    repeat it (a network pass each); an error that may not recur (here a worker crash) is
    retried."""
    rng = np.random.default_rng(0)
    # A flat Gaussian blob against uniform noise in a cube: no surface in common.
    blob = rng.normal(size=(600, 3)) * [0.3, 0.05, 0.01]
    noise = rng.uniform(-1, 1, size=(600, 3))
    work = [("unmatched", blob, noise), ("first", pairs[0][1], pairs[0][2])]
    output = tmp_path / "results.jsonl"
    first = register_many(work[:1], workers=0, output=output, seed=0, progress=False)
    assert first[0]["ok"] and first[0]["success"] is False, first[0]
    assert first[0]["reason"].startswith(("too few matches", "not verified")), first[0]["reason"]
    with output.open("a") as handle:  # as a crashed worker leaves it
        handle.write(json.dumps({"id": "first", "source": None, "target": None, "ok": False,
                                 "error": {"type": "WorkerCrashed", "message": "a worker process died"}}) + "\n")
    seen: list[str] = []
    again = register_many(work, workers=0, output=output, seed=0, progress=False,
                          on_record=lambda r: seen.append(r["id"]))
    assert seen == ["first"], "the verdict is kept, the crash retried"
    assert again[0] == first[0] and again[1]["ok"]
    assert [record["id"] for record in _lines(output)] == ["unmatched", "first", "first"]


# The same two pairs registered by two local workers, written out by a script with no main guard.
_UNGUARDED_SCRIPT = """
import json, sys
from logdesc_rt.batch import comparable, register_many
from logdesc_rt.demo import make_demo_pair
first, second = make_demo_pair(seed=1), make_demo_pair(seed=2)
records = register_many([("first", first.source, first.target), ("second", second.source, second.target)],
                        workers=2, threads_per_worker=1, seed=0, progress=False)
print(json.dumps([comparable(record) for record in records]))
"""


@pytest.mark.parametrize("how", ["script without a main guard", "python - (stdin)"])
def test_register_many_with_workers_runs_from_an_unguarded_script_and_from_stdin(pairs, tmp_path, how):
    """multiprocessing's spawn re-imports the caller's main module in every worker: such a script
    killed its workers at start-up and left the parent waiting for ever. Each run here is a
    subprocess with a timeout, so a hang fails the test instead of the suite."""
    import subprocess
    import sys

    if how.startswith("script"):
        script = tmp_path / "unguarded.py"
        script.write_text(_UNGUARDED_SCRIPT)
        command, stdin = [sys.executable, str(script)], None
    else:
        command, stdin = [sys.executable, "-"], _UNGUARDED_SCRIPT
    finished = subprocess.run(command, input=stdin, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert finished.returncode == 0, finished.stderr[-2000:]
    records = json.loads(finished.stdout.strip().splitlines()[-1])
    # One worker, one thread each, from this (guarded) process: the same records.
    expected = register_many(pairs[:2], workers=1, threads_per_worker=1, seed=0, progress=False)
    assert records == [comparable(record) for record in expected]
