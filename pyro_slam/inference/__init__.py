"""Inference for DVBF-LM: weighted particles (:mod:`.particles`), resampling
(:mod:`.resampling`), particle weights under a map belief (:mod:`.weighting`), proposals
(:mod:`.proposals`), the particle filter (:mod:`.filter`), the asynchronous particle cache
(:mod:`.cache`), the particle-chunk ELBO (:mod:`.elbo`) and Pyro's SMCFilter behind the same
interface (:mod:`.smc`)."""

from . import resampling
from .cache import ParticleCache
from .elbo import ChunkBatch, ParticleChunkELBO
from .filter import ParticleFilter
from .particles import Particles, pose_moments, weighted_pose_mean
from .proposals import HeadingObservation
from .resampling import ParticleFilterFailed
from .smc import PyroSMCFilter
from .weighting import WEIGHTINGS, MapBelief, Weighting

__all__ = [
    "WEIGHTINGS",
    "ChunkBatch",
    "HeadingObservation",
    "MapBelief",
    "ParticleCache",
    "ParticleChunkELBO",
    "ParticleFilter",
    "ParticleFilterFailed",
    "Particles",
    "PyroSMCFilter",
    "Weighting",
    "pose_moments",
    "resampling",
    "weighted_pose_mean",
]
