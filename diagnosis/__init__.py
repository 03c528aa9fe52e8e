"""Sim-to-real gap diagnosis: where a simulation departs from experiments, which
unmodelled effect causes it, and how much of the gap that effect closes on held-out data."""

from diagnosis.drops import diagnose_drops, simulate_condition
from diagnosis.spec import Experiment, load_experiment, read_drop_observations
from diagnosis.synth import synthesize_drops

__all__ = [
    "Experiment",
    "diagnose_drops",
    "load_experiment",
    "read_drop_observations",
    "simulate_condition",
    "synthesize_drops",
]
