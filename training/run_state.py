"""Bookkeeping of a training run that survives sessions: atomic checkpoint writes, the JSON-lines
log (and its truncation on resume), the RNG states a resume restores, the stop flag that
SIGTERM / SIGINT set, the counters that travel in the checkpoint, the git commit.

:mod:`training.train` runs the loop with these; nothing here knows the model.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]


def git_commit() -> str:
    """``git rev-parse HEAD`` of the repository, or "unknown"."""
    try:
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() if result.returncode == 0 and result.stdout.strip() else "unknown"


def atomic_torch_save(obj, path: Path) -> None:
    """Write ``obj`` to ``path`` so that a crash never leaves a truncated file behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(temporary, "wb") as handle:
        torch.save(obj, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def rng_states() -> dict:
    states = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def restore_rng_states(states: dict) -> None:
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])
    if "cuda" in states and torch.cuda.is_available():
        try:
            torch.cuda.set_rng_state_all(states["cuda"])
        except (RuntimeError, IndexError):  # different GPU count: keep fresh CUDA states
            pass


class StopFlag:
    """SIGTERM / SIGINT set a flag; the loop checkpoints and exits at the next safe point.

    A second SIGINT falls back to the default handler (immediate KeyboardInterrupt).
    """

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self._previous = {}

    def install(self) -> None:
        for signum in (signal.SIGTERM, signal.SIGINT):
            self._previous[signum] = signal.signal(signum, self._handle)

    def uninstall(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)

    def _handle(self, signum, _frame) -> None:
        self.signal_name = signal.Signals(signum).name
        if signum == signal.SIGINT:
            signal.signal(signal.SIGINT, signal.default_int_handler)

    def __bool__(self) -> bool:
        return self.signal_name is not None


@dataclass
class Progress:
    """Counters that travel in the checkpoint."""

    step: int = 0
    pairs_seen: int = 0
    wall_time_s: float = 0.0  # accumulated over all sessions up to the last save
    best_metric: float | None = None
    best_step: int | None = None


class JsonlLog:
    """Append-only JSON-lines log (one flush per line, so a crash loses at most a line)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.handle = open(path, "a", buffering=1)

    def write(self, record: dict) -> None:
        # NaN / inf are not JSON: write null (e.g. precision of a pair without any match).
        self.handle.write(json.dumps(_finite(record), default=_json_default, allow_nan=False) + "\n")

    def close(self) -> None:
        self.handle.close()


def _finite(value):
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return None
    return value


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")


def truncate_log(path: Path, step: int) -> None:
    """Drop log lines from steps after ``step`` (written after the checkpoint we resume from),
    so the log of a resumed run reads as one consistent history."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a crash
        if record.get("step", 0) <= step or record.get("type") in ("start",):
            kept.append(line)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text("".join(line + "\n" for line in kept))
    os.replace(temporary, path)
