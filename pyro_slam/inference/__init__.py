"""Inference for DVBF-LM: weighted particles (:mod:`.particles`), resampling
(:mod:`.resampling`), pose proposals as SMC guides (:mod:`.proposals`), the particle filter
(:mod:`.filter`), the asynchronous particle cache (:mod:`.cache`), the particle-chunk ELBO
(:mod:`.elbo`) and Pyro's SMCFilter behind the same interface (:mod:`.smc`)."""

from . import resampling
from .cache import ParticleCache
from .elbo import ChunkBatch, ParticleChunkELBO
from .filter import ParticleFilter
from .particles import Particles, pose_moments, weighted_pose_mean
from .proposals import (
    PROPOSALS,
    HeadingProposal,
    Proposal,
    TransitionProposal,
    sequence_guide,
)
from .resampling import ParticleFilterFailed
from .smc import EvidenceSMCFilter, ProposalGuide, PyroSMCFilter
from .smoothing import ParticleHistory, transition_log_density

__all__ = [
    "PROPOSALS",
    "ChunkBatch",
    "EvidenceSMCFilter",
    "HeadingProposal",
    "ParticleCache",
    "ParticleChunkELBO",
    "ParticleFilter",
    "ParticleFilterFailed",
    "ParticleHistory",
    "transition_log_density",
    "Particles",
    "Proposal",
    "ProposalGuide",
    "PyroSMCFilter",
    "TransitionProposal",
    "pose_moments",
    "resampling",
    "sequence_guide",
    "weighted_pose_mean",
]
