"""A checkpoint's provenance, derived from its training log instead of copied by hand.

Usage (from the repository root)::

    python -m training.provenance training/checkpoints/v3_cpu_log.jsonl \
        --notes training/checkpoints/v3_cpu_notes.json \
        --checkpoint training/checkpoints/v3.pt \
        --out training/checkpoints/v3_cpu_provenance.json

The log (``training.train``'s ``log.jsonl``) already holds every fact that drifts when a run
goes on: where it stands (step, pairs, wall time), each invocation (a ``start`` or ``resume``
record with its commit and arguments, up to its ``stop``) and every validation. This module
turns those into the provenance file; the notes file holds what the log cannot know (what
the data is, the hardware, the status) and is copied in front of the derived keys. The
resume command is rebuilt from the last invocation's arguments, so it is the one that ran.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as ``python training/provenance.py``: import from the repo root
    _here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _here]
    sys.path.insert(0, str(_here.parent))

__all__ = ["derived_provenance", "invocations", "read_log", "training_command", "validations"]

# Arguments that say where one invocation ran, not how the model was trained: a change in
# them is not a change of training.
_LOCAL_ARGUMENTS = ("out", "resume", "max_minutes", "no_progress")
# Validation metrics are kept to this many significant digits.
_DIGITS = 4


def read_log(path: Path) -> list[dict]:
    """The log's records, in order (one JSON object per line; blank lines skipped)."""
    records = []
    for number, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if line.strip():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError as error:
                raise ValueError(f"{path}:{number}: not a JSON record ({error})") from error
    if not records:
        raise ValueError(f"{path}: no records")
    return records


def training_command(arguments: dict, **overrides) -> str:
    """``python -m training.train ...`` that parses back to ``arguments`` (with ``overrides``).

    Only arguments that differ from the parser's defaults are written, so the command stays
    readable; :func:`training.train.build_parser` decides what a default is.
    """
    from training.train import build_parser

    values = {**arguments, **overrides}
    words = ["python", "-m", "training.train"]
    for action in build_parser()._actions:
        if not action.option_strings or action.dest not in values:
            continue
        value, flag = values[action.dest], action.option_strings[0]
        if value is None or value == action.default or str(value) == str(action.default):
            continue
        if action.nargs == 0:  # a switch: store_true
            words += [flag] if value else []
        elif isinstance(value, list):  # action="append": the flag once per value
            for item in value:
                words += [flag, str(item)]
        else:
            words += [flag, str(value)]
    return " ".join(words)


def _rounded(value):
    if isinstance(value, float) and math.isfinite(value) and value != 0.0:
        return round(value, max(0, _DIGITS - 1 - int(math.floor(math.log10(abs(value))))))
    return value


def invocations(records: list[dict]) -> list[dict]:
    """One entry per ``start`` / ``resume`` record: the steps, pairs and training wall time it
    added, its commit, why it ended, and the training arguments it changed (all of them for
    the first; run-local ones such as ``--out`` or ``--max-minutes`` never count)."""
    # Each invocation's records: its start / resume record, then the progress records up to
    # and including its stop (later ones, before the next resume, belong to no invocation).
    segments: list[list[dict]] = []
    for record in records:
        if record.get("type") in ("start", "resume"):
            segments.append([record])
        elif segments and "step" in record and segments[-1][-1].get("type") != "stop":
            segments[-1].append(record)

    entries: list[dict] = []
    previous_arguments: dict = {}
    for position, segment in enumerate(segments):
        first, last = segment[0], segment[-1]
        arguments = {k: v for k, v in first.get("args", {}).items() if k not in _LOCAL_ARGUMENTS}
        changed = {k: v for k, v in arguments.items() if previous_arguments.get(k, object()) != v}
        previous_arguments = arguments
        if last.get("type") == "stop":
            ended = last.get("reason", "stop")
        elif position == len(segments) - 1:
            ended = "still running when the log was read"
        else:
            ended = "no stop record (killed)"
        entries.append({
            "kind": first["type"],
            "from_step": first["step"],
            "to_step": last["step"],
            "pairs": last["pairs_seen"] - first["pairs_seen"],
            "wall_time_s": round(last["wall_time_s"] - first["wall_time_s"], 1),
            "git_commit": first.get("git_commit", "unknown"),
            "changed_arguments": changed,
            "ended": ended,
        })
    return entries


def validations(records: list[dict]) -> dict[str, dict]:
    """Step (as a string, for JSON) -> that validation's metrics, rounded."""
    skipped = {"type", "step", "epoch", "wall_time_s"}
    return {
        str(record["step"]): {k: _rounded(v) for k, v in record.items() if k not in skipped}
        for record in records
        if record.get("type") == "val"
    }


def derived_provenance(log_path: Path, checkpoint: Path | None = None) -> dict:
    """The log's facts: progress, invocations, validations and the command to continue."""
    records = read_log(log_path)
    last = records[-1]
    runs = invocations(records)
    arguments = next(
        (r.get("args", {}) for r in reversed(records) if r.get("type") in ("start", "resume")), {}
    )
    resume_from = str(checkpoint) if checkpoint is not None else arguments.get("resume") or "auto"
    return {
        "step": last["step"],
        "pairs_seen": last["pairs_seen"],
        "wall_time_s": round(last["wall_time_s"], 1),
        "log": str(log_path),
        "resume_command": training_command(arguments, resume=resume_from, max_minutes=None),
        "invocations": runs,
        "validation": {"logged_by": "training.train, every --val-every steps", "by_step": validations(records)},
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m training.provenance",
        description="Write a checkpoint's provenance JSON from its training log and hand-written notes.",
    )
    parser.add_argument("log", type=Path, help="the run's log.jsonl (training.train)")
    parser.add_argument("--notes", type=Path, default=None,
                        help="JSON object of facts the log cannot know (data, hardware, status); copied first")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="the checkpoint the resume command should start from (default: the last --resume)")
    parser.add_argument("--out", type=Path, required=True, help="provenance JSON to write")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    notes = json.loads(args.notes.read_text()) if args.notes else {}
    if not isinstance(notes, dict):
        raise SystemExit(f"{args.notes}: expected a JSON object")
    derived = derived_provenance(args.log, args.checkpoint)
    clashes = sorted(set(notes) & set(derived))
    if clashes:
        raise SystemExit(f"{args.notes}: keys {clashes} come from the log; remove them from the notes")
    args.out.write_text(json.dumps({**notes, **derived}, indent=2) + "\n")
    print(f"wrote {args.out}: step {derived['step']}, {derived['pairs_seen']} pairs, "
          f"{len(derived['invocations'])} invocations, {len(derived['validation']['by_step'])} validations")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
