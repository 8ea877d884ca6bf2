"""Reading training checkpoints (written by :mod:`training.train`) for evaluation and export.

A checkpoint is a dict with the model state (``model``), optimiser / scheduler / RNG states,
progress counters (``step``, ``pairs_seen``, ``wall_time_s``), the best validation metric, and
every config the run used (``model_config``, ``geometry_config``, ``normalization_config``,
``matching_config``, ``train_args``), so a model can always be rebuilt and its preprocessing
reproduced from the file alone.

A *weights-only* checkpoint (``python -m training.checkpoint weights-only IN OUT``) drops the
optimiser, scheduler and RNG states: a third of the size, for committing a shipped model.
Training resumes from it with fresh Adam moments (see :func:`training.train._restore`).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from logdesc_rt.config import DEFAULT_WORKING_SIZE, GeometryConfig, NormalizationConfig

# Keys of a checkpoint copied into an exported model's provenance.
_PROVENANCE_KEYS = (
    "step", "pairs_seen", "wall_time_s", "best_metric", "best_metric_name", "best_step",
    "git_commit", "torch_version",
)

# What only an exact resume needs: Adam's moments, the schedule's state, the RNG streams.
RESUME_STATE_KEYS = ("optimizer", "scheduler", "rng_states")


@dataclass(frozen=True)
class CheckpointInfo:
    """What a checkpoint says about preprocessing and origin.

    Attributes:
        geometry: geometry config used in training.
        normalization: pair normalisation used in training.
        points_per_cloud: training cloud size (the runtime's working size).
        provenance: progress counters, best validation metric, commit, training arguments.
    """

    geometry: GeometryConfig
    normalization: NormalizationConfig
    points_per_cloud: int
    provenance: dict[str, Any] = field(default_factory=dict)


def load_checkpoint(path, map_location="cpu") -> dict:
    """Read a checkpoint written by :mod:`training.train` (our own file: full unpickling)."""
    import torch

    return torch.load(Path(path), map_location=map_location, weights_only=False)


def model_from_checkpoint(checkpoint: dict, device="cpu"):
    """Rebuild the :class:`training.model.LoGDescMatcher` of a checkpoint, in eval mode."""
    from training.config import ModelConfig
    from training.model import LoGDescMatcher

    model = LoGDescMatcher(ModelConfig.from_dict(checkpoint["model_config"]))
    model.load_state_dict(checkpoint["model"])
    return model.to(device).eval()


def configs_from_checkpoint(checkpoint: dict) -> tuple[GeometryConfig, NormalizationConfig]:
    """The geometry and normalisation the checkpoint was trained with (a checkpoint from before the
    edge layouts holds the paper's geometry; the normalisation's defaults where absent)."""
    geometry = GeometryConfig.from_stored(checkpoint.get("geometry_config", {}))
    normalization = NormalizationConfig.from_dict(checkpoint.get("normalization_config", {}))
    return geometry, normalization


def load_model(path, device="cpu"):
    """(model in eval mode, :class:`CheckpointInfo`) of the checkpoint at ``path``."""
    checkpoint = load_checkpoint(path)
    geometry, normalization = configs_from_checkpoint(checkpoint)
    train_args = checkpoint.get("train_args", {})
    provenance = {key: checkpoint[key] for key in _PROVENANCE_KEYS if key in checkpoint}
    provenance["train_args"] = train_args
    info = CheckpointInfo(
        geometry=geometry,
        normalization=normalization,
        points_per_cloud=int(
            train_args.get("working_size") or train_args.get("points_per_cloud") or DEFAULT_WORKING_SIZE
        ),
        provenance=provenance,
    )
    return model_from_checkpoint(checkpoint, device), info


def weights_only(checkpoint: dict) -> dict:
    """The checkpoint without :data:`RESUME_STATE_KEYS`, marked ``weights_only: True``; the
    model, counters, configs and provenance are kept as they are."""
    slim = {key: value for key, value in checkpoint.items() if key not in RESUME_STATE_KEYS}
    slim["weights_only"] = True
    return slim


def is_weights_only(checkpoint: dict) -> bool:
    """True when the checkpoint lacks any of the states an exact resume needs."""
    return any(key not in checkpoint for key in RESUME_STATE_KEYS)


def main(argv=None) -> int:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    slim = commands.add_parser("weights-only", help="write the checkpoint without its resume states")
    slim.add_argument("checkpoint", type=Path)
    slim.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    if args.out.resolve() == args.checkpoint.resolve():
        parser.error("OUT must differ from the checkpoint: the resume states would be lost")
    torch.save(weights_only(load_checkpoint(args.checkpoint)), args.out)
    print(f"{args.out}: {args.out.stat().st_size / 1e6:.1f} MB (was {args.checkpoint.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
