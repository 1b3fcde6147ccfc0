"""The shipped pretrained networks (trained by ``pyro-slam pretrain`` on a held-out maze,
seed 100, never a test maze) and loaders for network files.

* ``emission_lidar20.pt`` -- the paper's LiDAR emission MLP ``mu_E`` for the simulator's
  20-beam, 0.53-range LiDAR;
* ``transition_moderate_medium.pt`` -- the learned transition ``mu_T`` (it reads the 20-beam
  predicted scan).

Files hold tensors and plain data only and are read with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

from pathlib import Path

from ..data import DatasetError, Traversal, load_tensors, one_line
from ..model import EmissionMLP, LearnedTransition
from ..model.networks import LIDAR_HIDDEN, LIDAR_LAYERS, LIDAR_MAP_DIM, MIN_WORLD_DIRECTIONS

PRETRAINED = Path(__file__).parent
EMISSION_FILE = "emission_lidar20.pt"
TRANSITION_FILE = "transition_moderate_medium.pt"
SHIPPED_BEAMS, SHIPPED_RANGE = 20, 0.53  # the sensor the shipped networks were trained on


def _load(path) -> dict:
    """A network file's contents (tensors and plain data only), or a one-line error."""
    blob = load_tensors(path, "a network file written by pyro-slam")
    if not isinstance(blob, dict):
        raise DatasetError(f"{path}: not a network file written by pyro-slam")
    return blob


def load_emission(path, traversal: Traversal) -> EmissionMLP:
    """A pretrained LiDAR emission MLP from ``path`` for ``traversal``'s LiDAR."""
    blob = _load(path)
    if "state_dict" not in blob:
        raise DatasetError(f"{path}: not an emission network file (no 'state_dict')")
    meta = blob.get("meta", {})
    n_world, map_dim = meta.get("n_world", MIN_WORLD_DIRECTIONS), meta.get("map_dim", LIDAR_MAP_DIM)
    wanted = max(traversal.num_beams, MIN_WORLD_DIRECTIONS)
    if n_world != wanted:
        raise DatasetError(
            f"{path}: emission pretrained for {n_world} world directions, but the traversal "
            f"has {traversal.num_beams} beams (needs {wanted})"
        )
    hidden, layers = meta.get("hidden", LIDAR_HIDDEN), meta.get("layers", LIDAR_LAYERS)
    em = EmissionMLP(map_dim, n_world, hidden, layers, scale=meta.get("scale", traversal.max_range))
    try:
        em.load_state_dict(blob["state_dict"])
    except (RuntimeError, KeyError, TypeError) as e:
        raise DatasetError(
            f"{path}: not an emission MLP for this sensor (its weights do not fit: {one_line(e)})"
        ) from None
    return em


def load_transition(path) -> LearnedTransition:
    """A :class:`~pyro_slam.model.LearnedTransition` from ``path``."""
    blob = _load(path)
    try:
        return LearnedTransition.from_state(blob)
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: not a learned transition file ({one_line(e)})") from None


def shipped_sensor(traversal: Traversal) -> bool:
    """Whether the traversal's LiDAR is the one the shipped networks were trained on."""
    return (
        traversal.num_beams == SHIPPED_BEAMS
        and abs(traversal.max_range - SHIPPED_RANGE) < 1e-9
        and "image_shape" not in traversal.metadata
    )


def shipped_emission(traversal: Traversal) -> EmissionMLP | None:
    """The shipped LiDAR emission MLP on the shipped sensor; None otherwise (an emission MLP is
    then learned from scratch)."""
    if shipped_sensor(traversal) and (PRETRAINED / EMISSION_FILE).is_file():
        return load_emission(PRETRAINED / EMISSION_FILE, traversal)
    return None


def transition_for(traversal: Traversal) -> LearnedTransition:
    """The shipped learned transition; it reads the 20-beam predicted scan, so the traversal's
    sensor must be the shipped one."""
    if not shipped_sensor(traversal):
        raise ValueError(
            "the learned transition reads the simulator's 20-beam, 0.53-range LiDAR scan; this "
            f"traversal has {traversal.num_beams} beams and range {traversal.max_range:g}: use "
            "transition.kind 'kinematic'"
        )
    return load_transition(PRETRAINED / TRANSITION_FILE)
