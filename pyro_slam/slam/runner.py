"""SLAM with DVBF-LM, the public entry point: :class:`SLAM` holds a run's components
(:mod:`.assemble`, :mod:`.parts`), its state (:mod:`.state`) and its data, runs the algorithms
of :mod:`.loop` online or offline over them, and writes and reads the checkpoints of
:mod:`.checkpoint`, from which :meth:`SLAM.resume` continues with the same random stream."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from ..data import Traversal
from ..inference import sequence_guide
from ..model import (
    Emission,
    EmissionMLP,
    MapBelief,
    Transition,
)
from ..model.guide import ParamScope
from ..runtime import thread_count, torch_threads
from . import checkpoint, loop, presets
from .assemble import assemble
from .build import (
    check_size,
    describe_noise,
    describe_prior,
    prepare_traversal,
    traversal_tensors,
)
from .checkpoint import state_fingerprint
from .config import SLAMConfig
from .parts import Components, RunData
from .state import Phase, SLAMState


def _part(part: str, name: str, doc: str) -> property:
    """A read-only attribute of a run: ``run.<part>.<name>``."""
    return property(lambda run: getattr(getattr(run, part), name), doc=doc)


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
        guide: a factory ``model -> guide`` of the map guide over the site ``"map"`` (default:
            the mean-field :class:`~pyro_slam.model.MapGuide`; Pyro's autoguides through
            :func:`~pyro_slam.model.autoguide`).
        prior, noise: the map prior and the emission noise of the model
            (:class:`~pyro_slam.model.DVBFLM`), for everything that reads the model, instead
            of the configured ones (``emission.prior``, ``emission.noise``); a checkpoint
            records them by description, and a resume under another is refused.
        smc: filter with Pyro's :class:`pyro.infer.SMCFilter` on the same model and proposal
            (:class:`~pyro_slam.inference.PyroSMCFilter`; slower) instead of our batched filter;
            training keeps ours.
        threads: torch intra-op threads while running (default
            :data:`pyro_slam.runtime.DEFAULT_THREADS`, never read from the machine's load: the
            results depend on the count).
        checkpoint: path of the checkpoint written every ``checkpoint_every`` steps.
        seed: seeds Pyro and the run's own ``torch.Generator``.
        handler: Pyro handlers around the model (:class:`~pyro_slam.model.DVBFLM`'s
            ``handler``): a function ``fn -> handled fn`` such as ``lambda fn:
            poutine.condition(fn, data={"frame": torch.tensor(0.1)})``, or a messenger such as
            ``poutine.scale(scale=0.5)``. The filter's weights, scan insertion, SVI, and the
            planner and MI on this run all run the model under them (``slam.model.handler``
            may also be set later).

    Each run keeps its parameters in its own scope of Pyro's parameter store
    (:meth:`pyro.params.param_store.ParamStoreDict.scope`): two runs in one process never share
    or clear each other's parameters, nor the caller's.

    A run is its fixed :class:`~pyro_slam.slam.parts.Components` (``components``: model,
    guides, filter, objective, SVI, inserter, heading), its
    :class:`~pyro_slam.slam.state.SLAMState` (``state``: particles, cache, history, generator,
    counters and outputs so far) and its :class:`~pyro_slam.slam.parts.RunData` (``data``); the
    names of all three read as the run's own (``slam.model``, ``slam.particles``,
    ``slam.obs``, ...). A checkpoint is the state and each component's own state.

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
        checkpoint_every: int = checkpoint.CHECKPOINT_EVERY,
        seed: int = 0,
        learn_emission: bool | None = None,
        guide=None,
        prior=None,
        noise=None,
        smc: bool = False,
        threads: int | None = None,
        handler=None,
    ):
        cfg = presets.resolve(config, traversal)
        if not (isinstance(checkpoint_every, int) and checkpoint_every > 0):
            raise ValueError(
                f"checkpoint_every must be a positive integer, got {checkpoint_every!r}"
            )
        self.checkpoint_every = checkpoint_every
        self.threads = thread_count(threads)
        tr = prepare_traversal(traversal, cfg)
        check_size(tr, cfg)
        self.data = RunData(tr, cfg, *traversal_tensors(tr), seed)
        K, N = cfg.filter.particles, cfg.training.cache_particles
        self.state = SLAMState.new(seed, self.data.T, N, K)
        scope = ParamScope()  # this run's parameters (``with slam.scope():``)
        with scope():
            parts = (transition, emission, learn_emission, guide, prior, noise, smc, handler)
            self.components: Components = assemble(self.data, self.state, scope, *parts)
        self.state.history.keep_scans = self.model.transition.needs_scan
        # the networks and map grid the run starts from (given, shipped or drawn from the seed)
        self.model_fingerprint = state_fingerprint(self.model.state_dict())
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self._clock: float | None = None  # when the wall time was last added to the state

    # the components, the state and the data, read as the run's own
    scope = _part("components", "scope", "The run's own parameter store.")
    model = _part("components", "model", "The :class:`~pyro_slam.model.DVBFLM`.")
    map_guide = _part("components", "map_guide", "The guide of the site ``map``.")
    guide = _part("components", "guide", "The global guide (map and walls' frame).")
    heading = _part("components", "heading", "The heading factor's data (None: none).")
    proposal = _part("components", "proposal", "The filter's proposal.")
    pf = _part("components", "pf", "The pose filter.")
    elbo = _part("components", "elbo", "The training objective.")
    optim = _part("components", "optim", "The optimiser of SVI.")
    svi = _part("components", "svi", "SVI on the model's global part.")
    inserter = _part("components", "inserter", "Scan insertion (None: off).")
    particles = _part("state", "particles", "The last step's particles (None before).")
    cache = _part("state", "cache", "The particle cache ``[T, N, 3]``.")
    history = _part("state", "history", "The particles' history, for smoothing.")
    gen = _part("state", "gen", "The run's generator.")
    tr = _part("data", "tr", "The prepared traversal.")
    cfg = _part("data", "cfg", "The run's configuration.")
    seed = _part("data", "seed", "The run's seed.")
    obs = _part("data", "obs", "The observations ``[T, N]``.")
    ctl = _part("data", "ctl", "The controls ``[T-1, D_u]``.")
    mask = _part("data", "mask", "The valid readings ``[T, N]`` (None: all).")
    init_pose = _part("data", "init_pose", "The start pose ``[3]``.")
    T = _part("data", "T", "The number of steps.")

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
        """The map belief the filter weighs with: mean and scale of ``q(M)`` ``[w, h, D_m]``
        (detached)."""
        return self.components.map_belief()

    def valid(self, t: int) -> torch.Tensor:
        """``[N]`` bool: the valid readings of step ``t``."""
        return self.data.valid(t)

    def run(self, mode: str = "online", progress: bool = True) -> dict:
        """Run (or, after :meth:`resume`, continue) SLAM. Returns :meth:`result`. The wall time
        spent in runs, summed over resumes, accumulates in ``state.wall_time_s`` (checkpoints
        keep it)."""
        self._clock = time.perf_counter()
        try:
            with torch_threads(self.threads), self.scope():
                return self._run(mode, progress)
        finally:
            self._tick()
            self._clock = None

    def _tick(self) -> None:
        """Add the wall time since the last tick of this :meth:`run` to ``state.wall_time_s``."""
        now = time.perf_counter()
        if self._clock is not None:
            self.state.wall_time_s += now - self._clock
            self._clock = now

    def _run(self, mode: str, progress: bool) -> dict:
        if mode not in ("online", "offline"):
            raise ValueError(f"mode must be 'online' or 'offline', got {mode!r}")
        if self.state.mode is None:
            self.state.begin(mode)
        elif self.state.mode != mode:
            raise checkpoint.CheckpointError(
                f"the resumed run is an {self.state.mode} run, not {mode}: resume it with mode "
                f"{self.state.mode!r} or start a new run"
            )
        elif self.state.phase == Phase.DONE:  # resumed from the final checkpoint: nothing to redo
            return self.result()
        algorithm = loop.online_sweep if mode == "online" else loop.offline
        algorithm(self.components, self.state, self.data, progress, self._checkpoint)
        self.state.phase = Phase.DONE
        result = self.result()
        if self.checkpoint:  # (last: its wall time is the run's)
            self.save(self.checkpoint)
        return result

    def result(self) -> dict:
        """``mean``, ``std`` ``[T, 3]``: the pose posterior smoothed over the particles'
        history by forward filtering, backward smoothing (online with a lag of ``filter.lag``
        steps, offline over the whole final pass); ``filtered_mean``, ``filtered_std``
        ``[T, 3]``: the filter's own; ``losses``, ``map_loc``, ``map_scale`` ``[w, h, D_m]``
        (``q(M)``) and, offline, the initial sweep's ``sweep_mean [T, 3]``
        (:func:`~pyro_slam.slam.loop.estimates`)."""
        belief = self.map_belief()
        out = loop.estimates(self.state, self.data, self.model)
        return {**out, "map_loc": belief.loc.numpy(), "map_scale": belief.scale.numpy()}

    # --------------------------------------------------------------------------- checkpoints
    def fingerprint(self) -> dict:
        """What a checkpoint of this run belongs to: the data (with the walls, which shape the
        map grid), the configuration, the seed, the model it started from and its map prior
        and emission noise (named ones or objects passed in, described by
        :func:`~pyro_slam.slam.build.describe_prior` and
        :func:`~pyro_slam.slam.build.describe_noise`)."""
        data = checkpoint.data_fingerprint(
            self.obs,
            self.ctl,
            self.mask,
            self.init_pose,
            torch.as_tensor(self.tr.beam_angles),
            torch.as_tensor(self.tr.walls),
        )
        return {
            "data": data,
            "config": self.cfg.to_dict(),
            "seed": self.seed,
            "model": self.model_fingerprint,
            "prior": describe_prior(self.model.prior),
            "noise": describe_noise(self.model.noise),
        }

    def state_dict(self) -> dict:
        """Everything :meth:`resume` needs: tensors and plain data only
        (:func:`~pyro_slam.slam.checkpoint.snapshot`)."""
        return checkpoint.snapshot(self.components, self.state, self.fingerprint())

    def _checkpoint(self, every: bool = True) -> None:
        """Write the checkpoint (if the run has one): ``every``, on the checkpoint interval
        (``state.t``, a multiple of ``checkpoint_every``); otherwise now."""
        if self.checkpoint and (not every or self.state.t % self.checkpoint_every == 0):
            self.save(self.checkpoint)

    def save(self, path) -> None:
        """Atomic checkpoint (temp file + rename)."""
        self._tick()
        checkpoint.write(path, self.state_dict())

    def resume(self, path) -> SLAM:
        """Load a checkpoint written by :meth:`save` for this data, configuration and seed
        (:class:`~pyro_slam.slam.checkpoint.CheckpointError` otherwise); :meth:`run` then
        continues from it."""
        d = checkpoint.read(path)
        checkpoint.check(path, d["fingerprint"], self.fingerprint())
        try:
            checkpoint.restore(self.components, self.state, d)
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise checkpoint.CheckpointError(f"{path}: damaged checkpoint ({e})") from None
        return self
