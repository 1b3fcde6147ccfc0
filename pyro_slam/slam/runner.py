"""SLAM with DVBF-LM: online (sweep t = 1..T) and offline (all steps), with checkpoints.

The estimator is the paper's: SVI (Adam) on the particle-chunk ELBO (eq. 3) for the map belief
``q(M)`` (and, without a pretrained one, the emission network), with the particle filter as the
pose guide and the asynchronous particle cache.

* **online**: at every step the particle filter advances under the current map belief, its
  particles enter the cache, and one SVI step (every ``training.every`` steps) runs on the newest
  chunk plus random older chunks (replay), with the ELBO scaled to the steps seen so far.
* **offline**: an online sweep, then ``offline.rounds`` rounds of SVI on random chunks from
  anywhere in the traversal; the pose posterior is a filter pass over the whole traversal
  (``offline.estimate="forward"``, also after each round) or, as in the paper's Appendix B-I
  (``"cache"``), filtered in consecutive chunks each started from the cache.

Every long loop shows a tqdm bar and writes atomic checkpoints from which :meth:`SLAM.resume`
continues with the same random stream.
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import numpy as np
import pyro
import torch
from pyro import poutine
from pyro.infer import SVI
from pyro.optim import Adam

from .. import pretrained
from ..data import Traversal
from ..geometry import wrap_angle
from ..inference import (
    PROPOSALS,
    HeadingProposal,
    ParticleCache,
    ParticleChunkELBO,
    ParticleFilter,
    ParticleHistory,
    Particles,
    PyroSMCFilter,
    sequence_guide,
)
from ..model import (
    Emission,
    EmissionMLP,
    GlobalGuide,
    MapBelief,
    Transition,
    map_marginals,
)
from ..model.guide import ParamScope, map_param_leaves
from ..runtime import torch_threads
from . import checkpoint, loop, presets
from .build import build_model, check_size, prepare_traversal, traversal_tensors
from .components import emission_kind
from .config import SLAMConfig
from .heading import ManhattanHeading
from .insertion import ScanInserter
from .loop import Phase, SLAMState

CACHE_PARTICLES = 50  # N, cached particles per step (paper III-D2)
LR_EMISSION = 1e-3  # Adam's learning rate of an emission learned from scratch


class SLAM:
    """A SLAM run over one traversal.

    Args:
        traversal: the data (:class:`~pyro_slam.data.Traversal`).
        config: a preset name (``"raycast"``, ``"real"``, ...), a
            :class:`~pyro_slam.slam.presets.Preset` or a
            :class:`~pyro_slam.slam.config.SLAMConfig` (default: the default preset for the
            traversal, :func:`pyro_slam.slam.presets.default_for`). A preset is adapted to the
            traversal as ``pyro-slam slam`` does (:func:`pyro_slam.slam.presets.resolve`).
        transition: a transition to use instead of the configured one (``transition.kind``
            ``"learned"``: the shipped network).
        emission: an emission instead of the configured kind's default (the shipped LiDAR MLP
            where the sensor matches it; otherwise a new one).
        learn_emission: whether SVI also learns the emission (default: only a new one; a given
            or shipped emission is pretrained and stays frozen).
        guide: a factory ``model -> guide`` of the map guide (default: the mean-field
            :class:`~pyro_slam.model.MapGuide`); the guide samples the site ``"map"`` and gives
            its marginal mean and std through ``params()`` or Pyro's ``quantiles``
            (:func:`~pyro_slam.model.map_marginals`); :func:`~pyro_slam.model.autoguide` makes
            one from a Pyro autoguide.
        prior, noise: the map prior and the emission noise of the model
            (:class:`~pyro_slam.model.DVBFLM`): they reach the filter's weights and trust, the
            training objective and everything else that reads the model.
        smc: filter with Pyro's :class:`pyro.infer.SMCFilter` on the same model and proposal
            (:class:`~pyro_slam.inference.PyroSMCFilter`; slower) instead of our batched filter;
            training keeps ours.
        threads: torch intra-op threads while running (default: torch's current count, at most
            one per idle core, :func:`pyro_slam.runtime.idle_cores`, so that a loaded machine is
            not oversubscribed).
        checkpoint: path of the checkpoint written every ``checkpoint_every`` steps.
        seed: seeds Pyro and the run's own ``torch.Generator``.

    Each run keeps its parameters in its own scope of Pyro's parameter store
    (:meth:`pyro.params.param_store.ParamStoreDict.scope`): two runs in one process never share
    or clear each other's parameters, nor the caller's.

    Example::

        tr = pyro_slam.data.load("traversal.npz")
        slam = SLAM(tr, "raycast", checkpoint="run/ckpt.pt")  # or "real" for a laser log
        result = slam.run("online")          # dict: mean [T, 3], std [T, 3], losses, map
    """

    def __init__(
        self,
        traversal: Traversal,
        config: SLAMConfig | presets.Preset | str | None = None,
        transition: Transition | None = None,
        emission: Emission | EmissionMLP | None = None,
        checkpoint: str | Path | None = None,
        checkpoint_every: int = 1000,
        seed: int = 0,
        learn_emission: bool | None = None,
        guide=None,
        prior=None,
        noise=None,
        smc: bool = False,
        threads: int | None = None,
    ):
        self.cfg = presets.resolve(config, traversal)
        if not (isinstance(checkpoint_every, int) and checkpoint_every > 0):
            raise ValueError(
                f"checkpoint_every must be a positive integer, got {checkpoint_every!r}"
            )
        self.checkpoint_every, self.seed, self.threads = checkpoint_every, seed, threads
        self.tr = prepare_traversal(traversal, self.cfg)
        check_size(self.tr, self.cfg)
        self.obs, self.ctl, self.mask, self.init_pose = traversal_tensors(self.tr)
        self.T = self.obs.shape[0]
        if transition is None and self.cfg.transition.kind == "learned":
            transition = pretrained.transition_for(self.tr)
        kind = emission_kind(self.cfg.emission.kind)
        if emission is None and kind.shipped is not None:
            emission = kind.shipped(self.tr)
        if learn_emission is None:
            learn_emission = emission is None and kind.learned
        self.scope = ParamScope()  # this run's parameters (``with slam.scope():``)
        with self.scope():
            self._build(transition, emission, bool(learn_emission), guide, prior, noise, smc)
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.particles: Particles | None = None
        self.state: SLAMState | None = None

    def _build(self, transition, emission, learn_emission, guide, prior, noise, smc) -> None:
        """The model, its guides, the filter, the ELBO and SVI (inside this run's scope)."""
        pyro.set_rng_seed(self.seed)  # (after loading: building a network draws its weights)
        self.gen = torch.Generator().manual_seed(self.seed)
        self.model, self.map_guide = build_model(
            self.tr, self.cfg, transition, emission, prior, noise
        )
        self.model.learn_emission = learn_emission
        if guide is not None:
            self.map_guide = guide(self.model)
        self.heading = None  # ManhattanHeading: the wall directions and the frame's guide
        if self.cfg.heading is not None:
            image = self.cfg.emission.observation == "image"
            drift = float(self.model.transition.sigma[2])
            self.heading = ManhattanHeading(
                self.tr,
                self.obs,
                self.mask,
                self.cfg.heading,
                image,
                drift,
                self.cfg.emission.outlier_prob,
            )
            self.model.heading = self.heading.factor()
        self.guide = GlobalGuide(
            self.map_guide, None if self.heading is None else self.heading.frame
        )
        name = self.cfg.filter.proposal
        self.proposal = (
            HeadingProposal() if self.heading and name == "transition" else PROPOSALS[name]()
        )
        self.pf = ParticleFilter(self.model, self.proposal, self.gen, shared=self.cfg.filter.shared)
        if smc:
            self.pf = PyroSMCFilter(self.model, self.proposal, shared=self.cfg.filter.shared)
        self.cache = ParticleCache(self.T, CACHE_PARTICLES)
        self.history = ParticleHistory(self.T, self.cfg.filter.particles)
        self.elbo = ParticleChunkELBO(
            ParticleFilter(self.model, self.proposal, self.gen),
            self.cache,
            self.obs,
            self.ctl,
            self.mask,
            num_particles=self.cfg.training.particles,
            headings=None if self.heading is None else self.heading.evidence(),
        )
        lr = self.cfg.training.lr
        self.optim = Adam(
            lambda name, _p: {"lr": LR_EMISSION if name.startswith("emission") else lr}
        )
        self.svi = SVI(self.model.global_model, self.guide, self.optim, loss=self.elbo)
        self._create_guide_params()
        self.inserter = None
        if self.cfg.emission.insert is not None:
            self.inserter = self._inserter()

    def _inserter(self) -> ScanInserter | None:
        """Scan insertion into the map guide's parameters, where the guide keeps a marginal
        mean and scale (:func:`~pyro_slam.model.guide.map_param_leaves`); otherwise insertion is
        switched off with a warning."""
        leaves = map_param_leaves(self.map_guide, self.model.grid.shape)
        if leaves is None:
            warnings.warn(
                f"scan insertion is off: the map guide {type(self.map_guide).__name__} keeps no "
                "marginal mean and scale to write scans into (map_param_leaves)",
                stacklevel=3,
            )
            return None
        return ScanInserter(self.cfg.emission.insert, self.model, leaves)

    def _create_guide_params(self) -> None:
        """Create the map guide's parameters now (checkpoints need them): a
        :class:`~pyro_slam.model.MapGuide` through ``params()``; another guide by one draw
        (outside any inference)."""
        if hasattr(self.map_guide, "params"):
            self.map_guide.params()
            return
        with torch.no_grad(), poutine.block():
            self.map_guide()

    # --------------------------------------------------------------------------- helpers
    def model_inputs(self) -> tuple:
        """The arguments of :meth:`DVBFLM.model <pyro_slam.model.DVBFLM.model>` for this run's
        data: ``(observations [T, N], controls [T-1, D_u], init_pose [3], mask [T, N] or None,
        headings)``, the wall directions as a :class:`~pyro_slam.model.HeadingEvidence` (None
        without a heading factor)."""
        headings = None if self.heading is None else self.heading.evidence()
        return self.obs, self.ctl, self.init_pose, self.mask, headings

    def sequence_guide(self):
        """This run's guide of the whole traversal as a Pyro guide of ``DVBFLM.model``: the map
        (and frame) guide, then each pose from the filter's proposal
        (:func:`~pyro_slam.inference.sequence_guide`). Pyro's ``Trace_ELBO`` on
        ``(self.model.model, self.sequence_guide(), *self.model_inputs())`` estimates the bound
        that SLAM's own objective (``self.elbo``) estimates with one particle."""
        return sequence_guide(self.model, self.proposal, self.guide)

    def map_belief(self) -> MapBelief:
        """The map belief the filter weighs with: mean and scale of ``q(M)`` (detached)."""
        with self.scope():
            loc, scale = map_marginals(self.map_guide)
        return MapBelief(loc.detach(), scale.detach())

    def valid(self, t: int) -> torch.Tensor:
        """``[B]`` bool: the valid readings of step ``t``."""
        if self.mask is None:
            return torch.ones_like(self.obs[t], dtype=torch.bool)
        return self.mask[t].bool()

    def run(self, mode: str = "online", progress: bool = True) -> dict:
        """Run (or, after :meth:`resume`, continue) SLAM. Returns :meth:`result`."""
        with torch_threads(self.threads), self.scope():
            return self._run(mode, progress)

    def _run(self, mode: str, progress: bool) -> dict:
        if mode not in ("online", "offline"):
            raise ValueError(f"mode must be 'online' or 'offline', got {mode!r}")
        if self.state is None:
            self.state = SLAMState(mode, Phase.ONLINE if mode == "online" else Phase.SWEEP)
        elif self.state.mode != mode:
            raise checkpoint.CheckpointError(
                f"the resumed run is an {self.state.mode} run, not {mode}: resume it with mode "
                f"{self.state.mode!r} or start a new run"
            )
        elif self.state.phase == Phase.DONE:  # resumed from the final checkpoint: nothing to redo
            return self.result()
        if mode == "online":
            loop.online_sweep(self, progress)
        else:
            loop.offline(self, progress)
        self.state.phase = Phase.DONE
        if self.checkpoint:
            self.save(self.checkpoint)
        return self.result()

    def result(self) -> dict:
        """``mean``, ``std`` ``[T, 3]``: the pose posterior smoothed over the particles'
        history (:class:`~pyro_slam.inference.ParticleHistory`: online with a lag of
        ``filter.lag`` steps, offline along the ancestral path of the final pass);
        ``filtered_mean``, ``filtered_std`` ``[T, 3]``: the filter's own; ``losses``,
        ``map_loc``, ``map_scale`` ``[w, h, D_m]`` (``q(M)``) and, offline, the initial sweep's
        ``sweep_mean [T, 3]``."""
        st = self.state
        belief = self.map_belief()
        loc, scale = belief.loc, belief.scale
        filtered = np.asarray(st.estimates, dtype=np.float64).reshape(-1, 3)
        filtered_std = np.asarray(st.stds, dtype=np.float64).reshape(-1, 3)
        mean, std = filtered, filtered_std
        if st.phase == Phase.DONE and self.history.filled.any():
            lag = self.T if st.mode == "offline" else self.cfg.filter.lag
            m, sd = self.history.smoothed(lag)
            mean, std = m.double().numpy(), sd.double().numpy()
            mean[:, 2] = wrap_angle(mean[:, 2])
        return {
            "mean": mean,
            "std": std,
            "filtered_mean": filtered,
            "filtered_std": filtered_std,
            "losses": np.asarray(st.losses),
            "map_loc": loc.detach().numpy(),
            "map_scale": scale.detach().numpy(),
            "sweep_mean": np.asarray(st.sweep_estimates, dtype=np.float64).reshape(-1, 3),
        }

    # --------------------------------------------------------------------------- checkpoints
    def fingerprint(self) -> dict:
        """What a checkpoint of this run belongs to: the data, the configuration, the seed."""
        data = checkpoint.data_fingerprint(
            self.obs, self.ctl, self.mask, self.init_pose, torch.as_tensor(self.tr.beam_angles)
        )
        return {"data": data, "config": self.cfg.to_dict(), "seed": self.seed}

    def state_dict(self) -> dict:
        """Everything :meth:`resume` needs: tensors and plain data only."""
        p = self.particles
        return {
            "format": checkpoint.FORMAT,
            "fingerprint": {**self.fingerprint(), "mode": self.state.mode},
            "state": {**copy.deepcopy(self.state.__dict__), "phase": self.state.phase.value},
            "params": self._param_state(),
            "optim": self.optim.get_state(),
            "model": self.model.state_dict(),
            "cache": self.cache.state_dict(),
            "particles": None if p is None else {"z": p.z, "logw": p.logw, "scan": p.scan},
            "filter": self.pf.state_dict(),
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "elbo_seen": self.elbo.num_steps_seen,
            "inserter": None if self.inserter is None else self.inserter.state_dict(),
            "history": self.history.state_dict(),
            "heading": None if self.heading is None else self.heading.state_dict(),
        }

    def _param_state(self) -> dict:
        with self.scope():
            return checkpoint.param_store_state()

    def save(self, path) -> None:
        """Atomic checkpoint (temp file + rename)."""
        checkpoint.write(path, self.state_dict())

    def resume(self, path) -> SLAM:
        """Load a checkpoint written by :meth:`save` for this data, configuration and seed
        (:class:`~pyro_slam.slam.checkpoint.CheckpointError` otherwise); :meth:`run` then
        continues from it."""
        d = checkpoint.read(path)
        checkpoint.check(path, d["fingerprint"], self.fingerprint())
        try:
            with self.scope():
                self._load(d)
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise checkpoint.CheckpointError(f"{path}: damaged checkpoint ({e})") from None
        return self

    def _load(self, d: dict) -> None:
        checkpoint.load_param_store(d["params"])
        self.model.load_state_dict(d["model"])
        if self.model.learn_emission:
            # the store now holds *loaded* tensors: make the emission network use (and SVI
            # update) those, as it did before the checkpoint, not its own parameter copies
            pyro.module("emission", self.model.emission, update_module_params=True)
        self.optim.set_state(d["optim"])
        self.cache.load_state_dict(d["cache"])
        self.particles = None if d["particles"] is None else Particles(**d["particles"])
        self.pf.load_state_dict(d["filter"])
        self.gen.set_state(d["gen"])
        torch.set_rng_state(d["torch_rng"])
        self.elbo.num_steps_seen = int(d["elbo_seen"])
        if self.inserter is not None:  # (the loaded parameters are new tensors)
            self.inserter = self._inserter()
            self.inserter.load_state_dict(d["inserter"])
        if self.heading is not None:
            self.heading.load_state_dict(d["heading"])
        self.history.load_state_dict(d["history"])
        self.state = SLAMState(**d["state"])
