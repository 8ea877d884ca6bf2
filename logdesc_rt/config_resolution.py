"""From what a caller passes to the configuration a registration runs with.

A :class:`~logdesc_rt.config.RuntimeConfig` leaves some values to the model (working size 0,
matching and verification None); :class:`ConfigResolver` fills them from the model's manifest,
reads a caller's ``config`` argument (None, a partial dict, or a RuntimeConfig) and applies
:meth:`~logdesc_rt.registration.Registrar.register`'s keyword overrides over it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .config import POSE_ESTIMATORS, REFINEMENT_METHODS, RuntimeConfig, VerificationConfig

UNSET = object()  # "not given": refine=None means no refinement, so None cannot mean "unset"


class ConfigResolver:
    """The model's defaults, and how a caller's configuration is completed with them.

    Args:
        manifest: the model's :class:`~logdesc_rt.network.ModelManifest` (its working size,
            geometry minimum, matching and runtime calibration).
    """

    def __init__(self, manifest):
        self.manifest = manifest
        model_defaults = manifest.runtime_config()
        # The model's calibration (code defaults for a model without one), parsed once: every
        # resolved config with verification None takes it.
        self.model_verification = model_defaults.verification or VerificationConfig()
        # The model's working size: its stored runtime setting, else the size it was exported at.
        self.model_working_size = model_defaults.subsampling.max_points or manifest.points_per_cloud
        self.model_defaults = self.resolved(model_defaults)

    def given(self, config: RuntimeConfig | dict | None, base: RuntimeConfig) -> RuntimeConfig:
        """A caller's ``config`` argument as a RuntimeConfig: None is ``base``, a dict applies
        over it, a RuntimeConfig is taken as it is."""
        if config is None:
            return base
        if isinstance(config, dict):
            return RuntimeConfig.from_dict(config, base=base)
        if not isinstance(config, RuntimeConfig):
            raise TypeError(f"config: expected a RuntimeConfig or a dict, got {type(config).__name__}")
        return config

    def resolved(self, config: RuntimeConfig) -> RuntimeConfig:
        """``config`` with the model's values filled in (working size, matching,
        verification), checked.

        Raises:
            ValueError: a working size below the geometry's minimum.
        """
        max_points = config.subsampling.max_points or self.model_working_size
        min_points = self.manifest.geometry.min_points
        if max_points < min_points:
            raise ValueError(f"max_points {max_points} < {min_points}, the geometry's minimum")
        return dataclasses.replace(
            config,
            subsampling=dataclasses.replace(config.subsampling, max_points=int(max_points)),
            matching=self.manifest.matching if config.matching is None else config.matching,
            verification=self.model_verification if config.verification is None else config.verification,
        )

    def for_call(
        self,
        config: RuntimeConfig | dict | None,
        base: RuntimeConfig,
        *,
        estimator: str | None = None,
        refine=UNSET,
        max_correspondence_distance: float | None = None,
        seed: int | None = None,
        thorough: bool | None = None,
    ) -> RuntimeConfig:
        """The configuration of one call: ``config`` over ``base`` (:meth:`given`), resolved,
        with the keyword overrides applied (:func:`with_overrides`)."""
        return with_overrides(
            self.resolved(self.given(config, base)),
            estimator=estimator,
            refine=refine,
            max_correspondence_distance=max_correspondence_distance,
            seed=seed,
            thorough=thorough,
        )


def with_overrides(
    config: RuntimeConfig,
    *,
    estimator: str | None = None,
    refine=UNSET,
    max_correspondence_distance: float | None = None,
    seed: int | None = None,
    thorough: bool | None = None,
) -> RuntimeConfig:
    """``config`` with :meth:`~logdesc_rt.registration.Registrar.register`'s keyword arguments
    applied (None / UNSET: unchanged; ``thorough=True`` removes the fast exit, so that every
    candidate is verified).

    Raises:
        ValueError: an unknown estimator or refinement, a distance <= 0, a bad seed.
    """
    if thorough and config.verification is not None and config.verification.fast_exit:
        config = dataclasses.replace(
            config,
            verification=dataclasses.replace(config.verification, exit_weights=(), exit_bias=0.0, exit_threshold=1.0),
        )
    if estimator is not None:
        if estimator not in POSE_ESTIMATORS:
            raise ValueError(f"estimator {estimator!r}: expected one of {POSE_ESTIMATORS}")
        config = dataclasses.replace(config, estimator=estimator)
    refinement = config.refinement
    if refine is not UNSET:
        if refine is not None and refine not in REFINEMENT_METHODS:
            raise ValueError(f"refine {refine!r}: expected None or one of {REFINEMENT_METHODS}")
        refinement = dataclasses.replace(refinement, method=refine)
    if max_correspondence_distance is not None:
        distance = float(max_correspondence_distance)
        if not 0.0 < distance < float("inf"):
            raise ValueError(f"max_correspondence_distance: {distance} must be > 0")
        refinement = dataclasses.replace(refinement, max_correspondence_distance=distance)
    return seeded(dataclasses.replace(config, refinement=refinement), seed)


def seeded(config: RuntimeConfig, seed: int | None) -> RuntimeConfig:
    """``config`` with every random choice seeded by ``seed`` (unchanged for None).

    Raises:
        ValueError: a seed that is not an integer >= 0.
    """
    if seed is None:
        return config
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: {seed!r} must be an integer >= 0")
    return config.with_seed(int(seed))
