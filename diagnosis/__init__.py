"""Sim-to-real gap diagnosis: where a simulation departs from experiments, which
unmodelled effect causes it, and how much of the gap that effect closes on held-out data."""

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.diagnosis.drops import diagnose_drops, simulate_condition
    from chipstack.diagnosis.spec import Experiment, load_experiment, read_drop_observations
    from chipstack.diagnosis.synth import synthesize_drops

__all__ = [
    "Experiment",
    "diagnose_drops",
    "load_experiment",
    "read_drop_observations",
    "simulate_condition",
    "synthesize_drops",
]

# Imported on first use: `pipeline diagnose` and `synth` import this package before
# they check their input, and the diagnosis brings scipy and pybullet (~2 s).
lazy_package(
    __name__,
    {
        "diagnose_drops": "chipstack.diagnosis.drops",
        "simulate_condition": "chipstack.diagnosis.drops",
        "Experiment": "chipstack.diagnosis.spec",
        "load_experiment": "chipstack.diagnosis.spec",
        "read_drop_observations": "chipstack.diagnosis.spec",
        "synthesize_drops": "chipstack.diagnosis.synth",
    },
)
