"""Planning and exploration in the learned model: hybrid A* (:mod:`.planner`), planning
environments (:mod:`.envs`), the inverse model ``q(z | x)`` for observation targets
(:mod:`.inverse`) and the agent that visits its modes (:mod:`.seek`), the measures that judge
a navigation run (:mod:`.evaluation`), mutual-information exploration (:mod:`.exploration`)
and PEMA (:mod:`.pema`)."""

from .config import NAVIGATION, NAVIGATION_BENCHMARK, NavigationConfig
from .envs import (
    GroundTruthEnv,
    LearnedEnv,
    ScanHits,
    execute,
    free_grid,
    learned_env,
    lookalikes,
    maze_bounds,
    run_env,
)
from .planner import (
    PlanResult,
    Primitives,
    check_endpoints,
    inside_scan,
    plan,
    safety,
    safety_cost,
    segments_cross,
)
from .seek import Look, Mover, SeekResult, seek_observation, seek_pose, sensor

__all__ = [
    "NAVIGATION",
    "NAVIGATION_BENCHMARK",
    "GroundTruthEnv",
    "LearnedEnv",
    "Look",
    "Mover",
    "NavigationConfig",
    "PlanResult",
    "Primitives",
    "ScanHits",
    "SeekResult",
    "check_endpoints",
    "execute",
    "free_grid",
    "inside_scan",
    "learned_env",
    "lookalikes",
    "maze_bounds",
    "plan",
    "run_env",
    "safety",
    "safety_cost",
    "seek_observation",
    "seek_pose",
    "sensor",
    "segments_cross",
]
