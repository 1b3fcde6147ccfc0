"""SLAM checkpoints: tensors and plain data only (read with ``torch.load(weights_only=True)``,
so a file can never run code), written atomically, and stamped with what they belong to.

A checkpoint records a fingerprint of the data the run filters (a hash of the prepared
observations, controls, mask, beam angles, start pose and walls), the model it started from (its
networks and map grid), its map prior and emission noise, the configuration, the seed and the
mode. :func:`check` refuses a
checkpoint whose fingerprint differs and names what differs. Its contents are the run's
:class:`~pyro_slam.slam.state.SLAMState` and each of its components' own state
(:func:`snapshot`).
"""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import pyro
import torch
from pyro.distributions import constraints

from ..data import DatasetError, atomic_write, load_tensors
from .config import ConfigError, from_dict

FORMAT = 5
CHECKPOINT_EVERY = 1000  # steps between two checkpoints, by default


class CheckpointError(DatasetError):
    """A checkpoint cannot be read, or belongs to another run; the message says which."""


def data_fingerprint(*tensors) -> str:
    """A SHA-256 of the tensors' dtypes, shapes and bytes (None entries count as absent)."""
    h = hashlib.sha256()
    for t in tensors:
        if t is None:
            h.update(b"none")
            continue
        t = torch.as_tensor(t).detach().contiguous().cpu()
        h.update(f"{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()[:32]


def state_fingerprint(state: dict) -> str:
    """A SHA-256 of a ``state_dict``'s names and tensors."""
    h = hashlib.sha256(",".join(state).encode())
    h.update(data_fingerprint(*state.values()).encode())
    return h.hexdigest()[:32]


def param_store_state() -> dict:
    """The Pyro param store's unconstrained values (tensors only)."""
    return {
        k: v.detach().clone().requires_grad_() for k, v in pyro.get_param_store().named_parameters()
    }


def load_param_store(params: dict) -> None:
    """Put unconstrained ``params`` into the param store, keeping the registered constraints."""
    ps = pyro.get_param_store()
    current = ps.get_state()["constraints"]
    ps.set_state(
        {
            "params": dict(params),
            "constraints": {k: current.get(k, constraints.real) for k in params},
        }
    )


MAGIC = b"pyro-slam checkpoint\n"


def write(path, state: dict) -> None:
    """Atomic write (temp file + rename) of ``MAGIC``, the SHA-256 of the payload and the
    ``torch.save`` payload: a damaged file is detected on reading, not silently resumed."""
    buf = io.BytesIO()
    torch.save(state, buf)
    payload = buf.getvalue()
    digest = hashlib.sha256(payload).hexdigest().encode()
    atomic_write(Path(path), lambda f: f.write(MAGIC + digest + b"\n" + payload))


def read(path) -> dict:
    """A checkpoint's contents; :class:`CheckpointError` for anything that is not one, is
    damaged (its digest does not match) or holds more than tensors and plain data (code in a
    pickle is refused by ``weights_only=True`` and never runs)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from")
    data = path.read_bytes()
    head = len(MAGIC) + 65
    if not data.startswith(MAGIC) or len(data) < head or data[head - 1 : head] != b"\n":
        raise CheckpointError(f"{path}: not a pyro-slam checkpoint")
    digest, payload = data[len(MAGIC) : head - 1], data[head:]
    if hashlib.sha256(payload).hexdigest().encode() != digest:
        raise CheckpointError(f"{path}: damaged checkpoint (its contents do not match its digest)")
    try:
        d = load_tensors(path, "a pyro-slam checkpoint", data=payload)
    except DatasetError as e:
        raise CheckpointError(str(e)) from None
    if not isinstance(d, dict) or d.get("format") != FORMAT or "fingerprint" not in d:
        raise CheckpointError(f"{path}: not a pyro-slam checkpoint (format {FORMAT} expected)")
    return d


def _diff(a, b, where: str = "") -> list[str]:
    """Dotted names of the entries where the nested dicts ``a`` and ``b`` differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{where}{k}.")
        return out
    return [] if a == b else [f"{where[:-1]} ({a!r} in the checkpoint, {b!r} now)"]


def _completed(config):
    """A saved configuration dict with the fields it lacks at their defaults (a field added
    since it was written); as it is where it is not a valid configuration."""
    try:
        return from_dict(config).to_dict()
    except (ConfigError, TypeError):
        return config


def check(path, saved: dict, expected: dict) -> None:
    """Raise :class:`CheckpointError` naming every field of the fingerprint that differs."""
    problems = []
    if saved.get("data") != expected["data"]:
        problems.append("the data set (another traversal, length, walls or sensor preparation)")
    if saved.get("model") != expected["model"]:
        problems.append("the model it started from (another --emission or --transition network)")
    problems += [f"config {d}" for d in _diff(_completed(saved.get("config")), expected["config"])]
    for key in ("prior", "noise", "seed", "mode"):
        if key in saved and key in expected and saved[key] != expected[key]:
            problems.append(f"{key} ({saved[key]!r} in the checkpoint, {expected[key]!r} now)")
    if problems:
        raise CheckpointError(f"{path}: belongs to another run; differs in " + "; ".join(problems))


def snapshot(components, state, fingerprint: dict) -> dict:
    """Everything a SLAM run needs to continue from this point, byte for byte: its
    :class:`~pyro_slam.slam.state.SLAMState` and each of its
    :class:`~pyro_slam.slam.parts.Components`' own state (tensors and plain data only), stamped
    with the run's ``fingerprint`` and mode."""
    return {
        "format": FORMAT,
        "fingerprint": {**fingerprint, "mode": state.mode},
        "state": state.state_dict(),
        "components": components.state_dict(),
    }


def restore(components, state, d: dict) -> None:
    """Put a :func:`snapshot` ``d`` back into a run's components and state."""
    components.load_state_dict(d["components"])
    state.load_state_dict(d["state"])
