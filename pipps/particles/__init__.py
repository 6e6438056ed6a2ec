"""Particle predictions through a learned dynamics model (thesis Algorithm 3)."""

from pipps.particles.forward import (
    Noise,
    ParticleRecord,
    RolloutConfig,
    particle_rollout,
    reparameterized_objective,
    sample_noise,
)
from pipps.particles.models import ModelOutput, model_output

__all__ = [
    "ModelOutput", "Noise", "ParticleRecord", "RolloutConfig", "model_output",
    "particle_rollout", "reparameterized_objective", "sample_noise",
]
