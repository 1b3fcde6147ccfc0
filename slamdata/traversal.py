"""The traversal dataset: one long agent trajectory with its sensor readings.

A :class:`Traversal` is what simulators and log readers produce and what every inference
routine consumes. On disk it is a single ``.npz`` (``numpy.savez_compressed``) with these fields
(``T`` time steps, ``B`` range beams, ``W`` wall segments):

==================  ===============  =======================================================
field               shape / dtype    meaning
==================  ===============  =======================================================
``observations``    [T, B] float     range readings (same units as poses), beam ``i`` at angle
                                     ``heading + beam_angles[i]``; ``max_range`` = no return
``controls``        [T-1, D_u] float control ``u_t`` applied after observing ``x_t``; moves
                                     ``z_t`` to ``z_{t+1}``. ``metadata["control_model"]``
                                     says which: ``"rotate_forward"`` (default, D_u = 2:
                                     rotate by ``u_t[0]`` rad, then move ``u_t[1]`` along the
                                     new heading) or ``"odometry_delta"`` (D_u = 3: ``(dx,
                                     dy, dtheta)`` in the robot frame of ``z_t``)
``poses``           [T, 3] float     true (or reference) poses ``(x, y, heading)``, heading in
                                     ``[-pi, pi)``; optional (real logs may lack it)
``walls``           [W, 4] float     wall segments ``(x1, y1, x2, y2)``; ``W`` may be 0
``beam_angles``     [B] float        beam directions relative to the heading, rad
``max_range``       scalar float     sensor range; readings >= it mean "no return"
``obs_mask``        [T, B] bool      optional; ``False`` marks invalid / masked readings
``images``          [T, H, W] float  optional first-person images, values in [0, 1]
``timestamps``      [T] float        optional, seconds, non-decreasing
``metadata``        JSON string      seed, maze spec, sensor and noise config, provenance
==================  ===============  =======================================================

Loading validates every field and raises :class:`DatasetError` naming the file and the field.
Saving is atomic (temporary file + rename), so an interrupted save never leaves a half-written
file in place of a good one.
"""

from __future__ import annotations

import io
import json
import os
import struct
import tempfile
import warnings
import zipfile
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

FORMAT_VERSION = 1


class DatasetError(ValueError):
    """A traversal (in memory or on disk) is malformed; the message names source and field."""


@dataclass
class Traversal:
    """One trajectory. See the module docstring for the field table."""

    observations: np.ndarray  # [T, B]
    controls: np.ndarray  # [T-1, D_u]
    walls: np.ndarray  # [W, 4]
    beam_angles: np.ndarray  # [B]
    max_range: float
    poses: np.ndarray | None = None  # [T, 3]
    obs_mask: np.ndarray | None = None  # [T, B] bool
    images: np.ndarray | None = None  # [T, H, W]
    timestamps: np.ndarray | None = None  # [T]
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        validate(self)

    @property
    def num_steps(self) -> int:
        return int(self.observations.shape[0])

    @property
    def num_beams(self) -> int:
        return int(self.observations.shape[1])

    @property
    def start_pose(self) -> np.ndarray:
        """``[3]`` the pose SLAM and path integration start from: ``poses[0]`` when the poses
        are known, else the origin."""
        return np.zeros(3) if self.poses is None else np.asarray(self.poses[0], dtype=np.float64)

    def __len__(self) -> int:
        return self.num_steps

    def slice(self, start: int, stop: int) -> Traversal:
        """Steps ``start:stop`` as a new traversal (controls trimmed to match)."""
        if not 0 <= start < stop <= self.num_steps:
            raise IndexError(
                f"slice [{start}:{stop}] outside a traversal of {self.num_steps} steps"
            )

        def cut(a):
            return None if a is None else a[start:stop]

        return replace(
            self,
            observations=self.observations[start:stop],
            controls=self.controls[start : stop - 1],
            poses=cut(self.poses),
            obs_mask=cut(self.obs_mask),
            images=cut(self.images),
            timestamps=cut(self.timestamps),
            metadata={**self.metadata, "sliced_from": [start, stop]},
        )

    def subsample_beams(self, k: int) -> Traversal:
        """Every ``k``-th beam (observations, mask and beam angles; ``k = 1``: ``self``)."""
        k = int(k)
        if k < 1:
            raise ValueError(f"beam stride must be >= 1, got {k}")
        if k == 1:
            return self
        sensor = dict(self.metadata.get("sensor", {}))
        sensor["beam_stride"] = sensor.get("beam_stride", 1) * k
        sensor["num_beams"] = len(self.beam_angles[::k])
        return replace(
            self,
            observations=self.observations[:, ::k],
            obs_mask=None if self.obs_mask is None else self.obs_mask[:, ::k],
            beam_angles=self.beam_angles[::k],
            metadata={**self.metadata, "sensor": sensor},
        )

    def clip_ranges(self, r: float) -> Traversal:
        """Valid readings beyond ``r`` clipped to ``r`` (they still say "at least r"); masked
        readings stay masked. ``max_range`` is kept (the sensor's no-return value)."""
        r = float(r)
        if not r > 0:
            raise ValueError(f"range clip must be positive, got {r}")
        obs = np.minimum(self.observations, np.asarray(r, self.observations.dtype))
        if self.obs_mask is not None:  # masked entries keep their placeholder value
            obs = np.where(self.obs_mask, obs, self.observations)
        return replace(self, observations=obs, metadata={**self.metadata, "range_clip": r})

    def valid_ranges(self) -> np.ndarray:
        """The unmasked readings below ``max_range``, flattened."""
        obs = self.observations if self.obs_mask is None else self.observations[self.obs_mask]
        return obs[obs < self.max_range]

    def save(self, path: str | os.PathLike) -> Path:
        """Write atomically to ``path`` (``.npz``)."""
        path = Path(path)
        arrays = {
            "format_version": np.asarray(FORMAT_VERSION),
            "observations": self.observations,
            "controls": self.controls,
            "walls": self.walls,
            "beam_angles": self.beam_angles,
            "max_range": np.asarray(self.max_range, dtype=np.float64),
            "metadata": np.asarray(json.dumps(self.metadata, sort_keys=True)),
        }
        for name in OPTIONAL_FIELDS:
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        atomic_write(path, lambda f: np.savez_compressed(f, **arrays))
        return path


OPTIONAL_FIELDS = ("poses", "obs_mask", "images", "timestamps")
REQUIRED_FIELDS = ("observations", "controls", "walls", "beam_angles", "max_range")


def _file_mode() -> int:
    """The permissions of a new file under the process's umask (usually 0644)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


MAX_MAGNITUDE = 1e6  # |coordinate| or range beyond this is corrupt data, not a world
MAX_TIMESTAMP = 1e13  # s: |timestamp| beyond this (over 300,000 years) is corrupt data
MAX_LOAD_BYTES = 1 << 30  # a data set's arrays, uncompressed, at most (1 GiB)


def atomic_write(path: Path, write) -> None:
    """Call ``write(fileobj)`` on a temporary file next to ``path``, then rename it into place:
    a failure leaves any previous ``path`` as it was. The file gets the usual permissions."""
    atomic_write_all({Path(path): write})


def atomic_write_all(writes: dict) -> None:
    """:func:`atomic_write` for several files together (``{path: write}``): every file is
    written to a temporary file first, and only when all of them are written are they renamed
    into place; a failure leaves every previous file as it was."""
    done: list[tuple[str, Path]] = []
    try:
        for path, write in writes.items():
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            done.append((tmp, path))
            os.fchmod(fd, _file_mode())
            with os.fdopen(fd, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
        for tmp, path in done:
            os.replace(tmp, path)
    except BaseException:
        for tmp, _ in done:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise


def _float_array(src: str, name: str, value, ndim: int, limit: float = MAX_MAGNITUDE):
    """``value`` as a numeric array of ``ndim`` dims with finite entries of magnitude at most
    ``limit``; :class:`DatasetError` naming the field otherwise."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise DatasetError(f"{src}: field '{name}' must be numeric, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise DatasetError(f"{src}: field '{name}' must have {ndim} dims, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise DatasetError(f"{src}: field '{name}' has a non-finite value at index {bad}")
    if arr.size and np.abs(arr).max() > limit:
        bad = np.argwhere(np.abs(arr) > limit)[0].tolist()
        raise DatasetError(
            f"{src}: field '{name}' has the implausible value {arr[tuple(bad)]:g} at index {bad} "
            f"(|value| > {limit:g})"
        )
    return arr


def _observations(tr: Traversal, src: str):
    """The checked ``observations [T, B]``, ``max_range`` and ``obs_mask [T, B]`` (or None):
    plausible, non-negative, and at least one valid reading below the sensor's range."""
    obs = _float_array(src, "observations", tr.observations, 2)
    T, B = obs.shape
    if T == 0:
        raise DatasetError(f"{src}: field 'observations' is empty (0 time steps)")
    if B == 0:
        raise DatasetError(f"{src}: field 'observations' has 0 beams")
    max_range = np.asarray(tr.max_range)
    if max_range.shape != () or max_range.dtype.kind not in "fiu":
        raise DatasetError(f"{src}: field 'max_range' must be a number, got {tr.max_range!r}")
    if not np.isfinite(max_range) or not 0 < max_range <= MAX_MAGNITUDE:
        raise DatasetError(
            f"{src}: field 'max_range' must be positive and at most {MAX_MAGNITUDE:g}, "
            f"got {tr.max_range}"
        )
    mask = tr.obs_mask
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype != np.bool_ or mask.shape != (T, B):
            raise DatasetError(
                f"{src}: field 'obs_mask' must be bool of shape {(T, B)}, "
                f"got {mask.dtype} {mask.shape}"
            )
    valid = obs if mask is None else obs[mask]
    if not np.any(valid < max_range * (1 - 1e-6)):  # (float32 readings of the range itself)
        raise DatasetError(
            f"{src}: field 'observations' has no valid reading: every reading is masked or at "
            f"the sensor's range {float(max_range):g}"
        )
    if valid.size and valid.min() < 0:
        t, b = np.argwhere((obs < 0) & (True if mask is None else mask))[0].tolist()
        raise DatasetError(
            f"{src}: field 'observations' has a negative range {obs[t, b]} at step {t}, beam {b}"
        )
    return obs, max_range, mask


CONTROL_MODELS = {"rotate_forward": 2, "odometry_delta": 3}  # name -> D_u
FAR = 1000.0  # a position this many data spreads plus sensor ranges from the rest is corrupt


def _control_model(src: str, metadata: dict, d_u: int) -> None:
    """``metadata["control_model"]`` (default ``"rotate_forward"``) is one the transitions
    apply, with at least its number of control components."""
    model = metadata.get("control_model", "rotate_forward")
    if not isinstance(model, str) or model not in CONTROL_MODELS:
        raise DatasetError(
            f"{src}: field 'metadata.control_model' is {model!r}; known control models: "
            f"{', '.join(CONTROL_MODELS)}"
        )
    if d_u < CONTROL_MODELS[model]:
        raise DatasetError(
            f"{src}: field 'controls' has {d_u} components per step; control_model {model!r} "
            f"needs {CONTROL_MODELS[model]}"
        )


def _step_lengths(controls: np.ndarray, model: str) -> np.ndarray:
    """``[T-1]``: how far each control moves the agent (``rotate_forward``: the forward
    offset; ``odometry_delta``: the length of the robot-frame translation)."""
    c = np.asarray(controls, dtype=np.float64)
    if model == "odometry_delta":
        return np.hypot(c[:, 0], c[:, 1])
    return np.abs(c[:, 1]) if c.shape[1] > 1 else np.zeros(len(c))


def _far_from_the_rest(src, walls, poses, controls, metadata, max_range) -> None:
    """Refuse a wall end point or pose ``[2]`` (or a control's step) farther from the median of
    all wall end points and poses than :data:`FAR` times (their median distance from it plus
    the sensor's range): corrupt data, which would otherwise size the map grid. Names the field
    and the index."""
    named = [("walls", np.asarray(walls, dtype=np.float64).reshape(-1, 2), 2)]
    if poses is not None:
        named.append(("poses", np.asarray(poses, dtype=np.float64)[:, :2], 1))
    points = np.concatenate([p for _, p, _ in named])  # [N, 2]
    center = np.median(points, 0) if len(points) else np.zeros(2)
    spread = float(np.median(np.linalg.norm(points - center, axis=1))) if len(points) else 0.0
    limit = FAR * (spread + max_range)
    where = f"(median position ({center[0]:.4g}, {center[1]:.4g}), at most {limit:.4g} away)"
    for name, pts, per_row in named:
        d = np.linalg.norm(pts - center, axis=1)
        if len(d) and d.max() > limit:
            i = int(np.argmax(d > limit))
            raise DatasetError(
                f"{src}: field '{name}' has the point ({pts[i, 0]:.6g}, {pts[i, 1]:.6g}) at index "
                f"{i // per_row}, {d[i]:.4g} from the rest of the data {where}: corrupt?"
            )
    steps = _step_lengths(controls, metadata.get("control_model", "rotate_forward"))
    if len(steps) and steps.max() > limit:
        i = int(np.argmax(steps > limit))
        raise DatasetError(
            f"{src}: field 'controls' moves {steps[i]:.4g} at index {i}, far beyond the rest of "
            f"the data {where}: corrupt?"
        )


def _optional_fields(tr: Traversal, src: str, T: int) -> None:
    """Check (and convert in place) the optional ``poses``, ``images`` and ``timestamps`` of a
    traversal of ``T`` steps."""
    if tr.poses is not None:
        poses = _float_array(src, "poses", tr.poses, 2)
        if poses.shape != (T, 3):
            raise DatasetError(f"{src}: field 'poses' must have shape {(T, 3)}, got {poses.shape}")
        tr.poses = poses.astype(np.float32) if poses.dtype != np.float64 else poses
    if tr.images is not None:
        img = _float_array(src, "images", tr.images, 3)
        if img.shape[0] != T:
            raise DatasetError(f"{src}: field 'images' must have {T} frames, got {img.shape[0]}")
        if img.size and (img.min() < 0 or img.max() > 1):
            raise DatasetError(f"{src}: field 'images' must lie in [0, 1]")
        tr.images = img.astype(np.float32)
    if tr.timestamps is not None:
        ts = _float_array(src, "timestamps", tr.timestamps, 1, limit=MAX_TIMESTAMP)
        if ts.shape != (T,):
            raise DatasetError(f"{src}: field 'timestamps' must have shape ({T},), got {ts.shape}")
        if T > 1 and np.any(np.diff(ts) < 0):
            i = int(np.argmax(np.diff(ts) < 0))
            raise DatasetError(f"{src}: field 'timestamps' decreases at step {i + 1}")
        tr.timestamps = ts.astype(np.float64)


def validate(tr: Traversal, src: str = "traversal") -> Traversal:
    """Check shapes, dtypes, lengths and values; raise :class:`DatasetError` on the first problem.

    Converts float fields to ``float32`` (``float64`` is kept) in place.
    """
    obs, max_range, mask = _observations(tr, src)
    T, B = obs.shape
    ctl = _float_array(src, "controls", tr.controls, 2)
    if ctl.shape[0] != T - 1 or ctl.shape[1] < 1:
        raise DatasetError(
            f"{src}: field 'controls' must have shape (T-1, D_u) = ({T - 1}, D_u) for T={T} "
            f"observations, got {ctl.shape}"
        )
    walls = _float_array(src, "walls", tr.walls, 2)
    if walls.shape[1:] != (4,):
        raise DatasetError(f"{src}: field 'walls' must have shape (W, 4), got {walls.shape}")
    angles = _float_array(src, "beam_angles", tr.beam_angles, 1, limit=4 * np.pi)
    if angles.shape != (B,):
        raise DatasetError(
            f"{src}: field 'beam_angles' must have shape ({B},) to match {B} observation beams, "
            f"got {angles.shape}"
        )
    _optional_fields(tr, src, T)
    if not isinstance(tr.metadata, dict):
        raise DatasetError(f"{src}: field 'metadata' must be a dict, got {type(tr.metadata)}")
    _control_model(src, tr.metadata, ctl.shape[1])
    _far_from_the_rest(src, walls, tr.poses, ctl, tr.metadata, float(max_range))
    tr.observations = obs.astype(np.float32) if obs.dtype != np.float64 else obs
    tr.controls = ctl.astype(obs.dtype if obs.dtype == np.float64 else np.float32)
    tr.walls = walls.astype(np.float64)
    tr.beam_angles = angles.astype(np.float64)
    tr.max_range = float(tr.max_range)
    tr.obs_mask = mask
    return tr


def load_tensors(path, what: str, data: bytes | None = None):
    """The contents of a file written by ``torch.save`` (or of its bytes ``data``), read with
    ``weights_only=True``: only tensors and plain data, so nothing in the file can run. Any
    failure is a one-line :class:`DatasetError` naming the file and saying it is not ``what``."""
    path = Path(path)
    if data is None and not path.is_file():
        raise DatasetError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (pickle-protocol notes on foreign files)
            source = path if data is None else io.BytesIO(data)
            return torch.load(source, weights_only=True, map_location="cpu")
    except Exception as e:  # torch raises many types for truncated, corrupt or unsafe files
        if "Weights only load failed" in str(e):
            why = "it holds objects other than tensors and plain data; nothing in it was run"
        else:
            why = one_line(e)
        raise DatasetError(f"{path}: not {what} ({why})") from None


def one_line(e: BaseException, limit: int = 160) -> str:
    """The first line of an exception's message (its type if empty), at most ``limit`` chars."""
    text = str(e).strip()
    return (text.splitlines()[0] if text else type(e).__name__)[:limit]


def _check_member_count(path: Path, n: int) -> None:
    """``zipfile`` stops reading the central directory at an entry whose (corrupted) length
    fields overrun it, silently dropping the members after it: compare the ``n`` members it
    found with the count in the end-of-central-directory record (raises ``zipfile.BadZipFile``)."""
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        fh.seek(max(0, fh.tell() - (1 << 16) - 22))
        tail = fh.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or len(tail) < at + 12:
        raise zipfile.BadZipFile("no end-of-central-directory record")
    declared = struct.unpack("<H", tail[at + 10 : at + 12])[0]
    if declared != 0xFFFF and declared != n:  # 0xFFFF: zip64, counted elsewhere
        raise zipfile.BadZipFile(f"central directory lists {n} of {declared} members")


def _check_sizes(src: str, archive: zipfile.ZipFile) -> None:
    """Refuse, before anything is decompressed or allocated, a data set whose members would
    unpack to more than :data:`MAX_LOAD_BYTES` or whose array headers declare more data than
    the member holds (a zip bomb, a forged ``.npy`` header)."""
    total = 0
    for info in archive.infolist():
        total += info.file_size
        if total > MAX_LOAD_BYTES:
            raise DatasetError(
                f"{src}: unpacks to more than {MAX_LOAD_BYTES / 2**30:g} GiB "
                f"(member {info.filename!r} declares {info.file_size} bytes); refused"
            )
        if not info.filename.endswith(".npy"):
            continue
        with archive.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            read = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read(fh, max_header_size=10000)
        declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if declared > info.file_size:
            raise DatasetError(
                f"{src}: field {info.filename[:-4]!r} declares shape {shape} of {dtype} "
                f"({declared} bytes) but holds {info.file_size} bytes; refused"
            )


def _scalar(src: str, name: str, value, kinds: str):
    """A data set's scalar field as a Python number, its dtype kind one of ``kinds`` (numpy's
    ``"f"``, ``"i"``, ``"u"``); :class:`DatasetError` naming the field otherwise."""
    arr = np.asarray(value)
    what = "an integer" if "f" not in kinds else "a number"
    if arr.shape != ():
        raise DatasetError(f"{src}: field '{name}' must be a scalar ({what}), got {arr.shape}")
    if arr.dtype.kind not in kinds:
        raise DatasetError(f"{src}: field '{name}' must be {what}, got {arr.item()!r}")
    return arr.item()


def load(path: str | os.PathLike) -> Traversal:
    """Read and validate a traversal written by :meth:`Traversal.save`."""
    path = Path(path)
    src = str(path)
    if not path.exists():
        raise FileNotFoundError(f"{src}: no such dataset file")
    # corrupt members surface as zlib.error (bad deflate stream), NotImplementedError (bit
    # flips in a zip header's compression method / flags) or RuntimeError (a flipped
    # "encrypted" flag: zipfile asks for a password), not only as BadZipFile
    unreadable = (
        zipfile.BadZipFile,
        zlib.error,
        NotImplementedError,
        OSError,
        EOFError,
        RuntimeError,
    )
    data = None
    try:
        f = np.load(path, allow_pickle=False)
        if isinstance(f, np.lib.npyio.NpzFile):  # not a bare .npy array
            with f:
                _check_member_count(path, len(f.files))
                _check_sizes(src, f.zip)
                data = {k: f[k] for k in f.files}
    except DatasetError:
        raise
    except (*unreadable, ValueError, KeyError) as e:
        raise DatasetError(f"{src}: not a readable .npz dataset ({type(e).__name__}: {e})") from e
    if data is None:
        raise DatasetError(f"{src}: not a .npz dataset (a single .npy array)")
    missing = [k for k in REQUIRED_FIELDS if k not in data]
    if missing:
        raise DatasetError(f"{src}: missing field(s) {', '.join(repr(m) for m in missing)}")
    version = _scalar(src, "format_version", data.get("format_version", FORMAT_VERSION), "iu")
    if version > FORMAT_VERSION:
        raise DatasetError(f"{src}: format_version {version} is newer than supported")
    try:
        metadata = json.loads(str(data["metadata"])) if "metadata" in data else {}
    except json.JSONDecodeError as e:
        raise DatasetError(f"{src}: field 'metadata' is not valid JSON ({e})") from e
    tr = Traversal.__new__(Traversal)
    tr.observations = data["observations"]
    tr.controls = data["controls"]
    tr.walls = data["walls"]
    tr.beam_angles = data["beam_angles"]
    tr.max_range = _scalar(src, "max_range", data["max_range"], "fiu")
    for name in OPTIONAL_FIELDS:
        setattr(tr, name, data.get(name))
    tr.metadata = metadata
    return validate(tr, src)
