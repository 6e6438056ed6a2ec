"""Episodic learning experiments: configuration, the learning loop, HDF5 results and sweeps
(thesis §4.5; docs/experiments.md). Tables, figures and verdicts are :mod:`pipps.reporting`."""

from pipps.experiments.config import PRESET_NAMES, ConfigError, ExperimentConfig, resolve_config
from pipps.experiments.loop import ExperimentResult, TrialResult, run_experiment
from pipps.experiments.methods import METHODS, Method
from pipps.experiments.state import restore

__all__ = [
    "ConfigError", "ExperimentConfig", "ExperimentResult", "METHODS", "Method", "PRESET_NAMES", "TrialResult",
    "resolve_config", "restore", "run_experiment",
]
