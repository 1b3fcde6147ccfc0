"""Inference for DVBF-LM: weighted particles (:mod:`.particles`), resampling
(:mod:`.resampling`), pose proposals as SMC guides (:mod:`.proposals`), the particle filter
(:mod:`.filter`), the asynchronous particle cache (:mod:`.cache`), the particle-chunk ELBO
(:mod:`.elbo`), Pyro's SMCFilter behind the same interface (:mod:`.smc`) and the model's
predictive of scans (:mod:`.predictive`)."""

from . import resampling
from .cache import ParticleCache
from .elbo import ChunkBatch, ParticleChunkELBO
from .filter import ParticleFilter
from .particles import Particles, pose_moments, weighted_pose_mean
from .predictive import band_coverage, scan_error
from .proposals import (
    PROPOSALS,
    HeadingProposal,
    Proposal,
    ScanMatchProposal,
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
    "ScanMatchProposal",
    "PyroSMCFilter",
    "TransitionProposal",
    "band_coverage",
    "pose_moments",
    "resampling",
    "scan_error",
    "sequence_guide",
    "weighted_pose_mean",
]
