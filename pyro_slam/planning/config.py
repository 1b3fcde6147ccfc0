"""Navigation's defaults, written once: the library's planner and learned map, the
``pyro-slam navigate`` command and the navigation benchmark read them from here."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NavigationConfig:
    """The defaults of navigating in a learned map.

    ``max_expansions``: hybrid A*'s node expansions (:func:`~pyro_slam.planning.plan`);
    ``traversal_steps``: the mapping traversal's length; ``fit_steps``: SVI steps fitting
    ``q(M)``; ``emission_steps``: steps fitting the emission on the mapping traversal (0: the
    shipped one, frozen), with ``n_world`` world directions; ``max_std``: a chart counts as
    explored below this std of ``q(M)``; ``hit_margin``: the learned planner keeps this far
    from the mapping scans' returns (0: off) (:func:`~pyro_slam.planning.learned_env`);
    an observation target's goals are up to ``hypotheses`` modes of the inverse model at
    least ``mode_separation`` apart, visited best first until the agent's own view matches
    the target scan within ``accept_tol`` (mean absolute range difference;
    :func:`~pyro_slam.planning.seek_observation`); a goal without a plan is explored towards
    (the agent scans at the reached place nearest to it and plans again) up to
    ``observe_rounds`` times. ``rollout_samples``: draws of the model per start pose and
    primitive in the planner's rollouts (their scans' mean safety cost is its cost; the
    successor follows the transition's mean; :class:`~pyro_slam.planning.LearnedEnv`);
    ``fit_noise``: the mapping fits the emission's noise after the map
    (:func:`~pyro_slam.slam.fit_noise`), which the rollouts then sample; ``clip_margin``: the
    mapping model's kinematics stop this far short of the wall its predicted scan shows ahead,
    so that its rollouts do not pass through walls
    (:class:`~pyro_slam.model.KinematicTransition`).
    """

    max_expansions: int = 2000
    traversal_steps: int = 3000
    fit_steps: int = 1500
    emission_steps: int = 0
    n_world: int = 20
    max_std: float = 0.6
    hit_margin: float = 0.02
    hypotheses: int = 3
    mode_separation: float = 0.1
    accept_tol: float = 0.01
    observe_rounds: int = 3
    rollout_samples: int = 8
    fit_noise: bool = True
    clip_margin: float = 0.01


# the library's and the command line's defaults
NAVIGATION = NavigationConfig()
# the navigation benchmark's (docs/navigation.md): a smaller A* budget, a longer mapping
# traversal and an emission fitted per maze with 60 world directions
NAVIGATION_BENCHMARK = NavigationConfig(
    max_expansions=1200, traversal_steps=6000, emission_steps=3000, n_world=60
)
