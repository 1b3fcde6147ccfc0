"""Traversal validation at the API boundary: every malformed input raises :class:`DatasetError`
naming the source and the field, before any compute (property-based with hypothesis)."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pyro_slam.data import DatasetError, Traversal, load, validate

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FLOAT_FIELDS = ("observations", "controls", "walls", "beam_angles", "poses", "timestamps")


@st.composite
def traversal_fields(draw, min_steps=1):
    """Keyword arguments of a valid :class:`Traversal` (T <= 6 steps, B <= 5 beams)."""
    T = draw(st.integers(min_steps, 6))
    B = draw(st.integers(1, 5))
    W = draw(st.integers(0, 3))
    dtype = draw(st.sampled_from([np.float32, np.float64]))
    fin = dict(allow_nan=False, allow_infinity=False, width=32)

    def arr(shape, lo=-10.0, hi=10.0):
        return draw(hnp.arrays(dtype, shape, elements=st.floats(lo, hi, **fin)))

    fields = dict(
        observations=arr((T, B), 0.0, 5.0),
        controls=arr((T - 1, 2)),
        walls=arr((W, 4)),
        beam_angles=arr((B,), -3.0, 3.0),
        max_range=draw(st.floats(0.1, 10.0)),
        poses=arr((T, 3)),
        timestamps=np.sort(arr((T,), 0.0, 100.0)),
        metadata={"seed": draw(st.integers(0, 9))},
    )
    if draw(st.booleans()):
        fields["obs_mask"] = draw(hnp.arrays(np.bool_, (T, B)))
        fields["obs_mask"][0, 0] = True
    # a data set needs at least one valid reading below the sensor's range
    fields["observations"][0, 0] = min(fields["observations"][0, 0], fields["max_range"] / 2)
    return fields


def base(**changes):
    """A small valid traversal's fields, with ``changes``."""
    fields = dict(
        observations=np.full((3, 2), 0.5),
        controls=np.zeros((2, 2)),
        walls=np.zeros((1, 4)),
        beam_angles=np.zeros(2),
        max_range=1.0,
    )
    return {**fields, **changes}


def rejects(fields, field, pattern=""):
    """Building the traversal raises a DatasetError that names ``field`` (and ``pattern``)."""
    with pytest.raises(DatasetError) as info:
        Traversal(**fields)
    msg = str(info.value)
    assert msg.startswith("traversal: ") and f"'{field}'" in msg, msg
    assert re.search(pattern, msg), msg
    return msg


# ----------------------------------------------------------------------------- valid
@SETTINGS
@given(traversal_fields())
def test_valid_traversals_pass_and_roundtrip(fields):
    tr = Traversal(**fields)
    assert tr.num_steps == fields["observations"].shape[0]
    assert tr.observations.dtype in (np.float32, np.float64)
    with tempfile.TemporaryDirectory() as d:
        back = load(tr.save(Path(d) / "t.npz"))
    for name in FLOAT_FIELDS + ("obs_mask",):
        a, b = getattr(tr, name), getattr(back, name)
        assert (a is None and b is None) or np.array_equal(a, b), name
    assert back.max_range == tr.max_range and back.metadata == tr.metadata


# ------------------------------------------------------------------------ bad values
@SETTINGS
@given(
    traversal_fields(),
    st.sampled_from(FLOAT_FIELDS),
    st.sampled_from([np.nan, np.inf, -np.inf]),
    st.data(),
)
def test_non_finite_values_are_rejected(fields, field, bad, data):
    a = np.array(fields[field], dtype=np.float64)
    assume(a.size > 0)
    idx = data.draw(st.tuples(*(st.integers(0, n - 1) for n in a.shape)))
    a[idx] = bad
    fields[field] = a
    rejects(fields, field, rf"non-finite value at index \[{', '.join(map(str, idx))}\]")


@SETTINGS
@given(traversal_fields(), st.data(), st.floats(-1e6, -1e-6))
def test_negative_ranges_are_rejected_unless_masked(fields, data, neg):
    T, B = fields["observations"].shape
    t, b = data.draw(st.integers(0, T - 1)), data.draw(st.integers(0, B - 1))
    fields["observations"] = fields["observations"].astype(np.float64)
    fields["observations"][t, b] = neg
    mask = fields.get("obs_mask")
    if mask is not None and not mask[t, b]:
        Traversal(**fields)  # a masked (invalid) reading may hold anything finite
        return
    rejects(fields, "observations", f"negative range .* at step {t}, beam {b}$")


@SETTINGS
@given(traversal_fields(), st.sampled_from([0.0, -1.0, np.nan, np.inf]))
def test_non_positive_max_range(fields, bad):
    fields["max_range"] = bad
    rejects(fields, "max_range", "must be positive")


# ---------------------------------------------------------------------- bad shapes
@SETTINGS
@given(traversal_fields(), st.integers(-2, 2).filter(bool))
def test_wrong_beam_count(fields, delta):
    B = fields["observations"].shape[1]
    assume(B + delta >= 0)
    fields["beam_angles"] = np.linspace(0, 6, B + delta)
    rejects(fields, "beam_angles", rf"\({B},\) to match {B} observation beams")


@SETTINGS
@given(traversal_fields(), st.integers(-2, 2).filter(bool))
def test_wrong_mask_shape(fields, delta):
    T, B = fields["observations"].shape
    assume(B + delta >= 0)
    fields["obs_mask"] = np.ones((T, B + delta), dtype=bool)
    rejects(fields, "obs_mask", rf"shape \({T}, {B}\)")


@SETTINGS
@given(
    traversal_fields(),
    st.sampled_from(["controls", "poses", "timestamps"]),
    st.integers(-2, 2).filter(bool),
)
def test_mismatched_lengths(fields, field, delta):
    T = fields["observations"].shape[0]
    a = fields[field]
    n = a.shape[0] + delta
    assume(n >= 0)
    fields[field] = (
        np.zeros((n,) + a.shape[1:]) if n <= a.shape[0] else np.resize(a, (n,) + a.shape[1:])
    )
    msg = rejects(fields, field)
    assert str(T - 1 if field == "controls" else T) in msg


@SETTINGS
@given(traversal_fields(), st.sampled_from(FLOAT_FIELDS))
def test_wrong_number_of_dimensions(fields, field):
    fields[field] = np.asarray(fields[field])[..., None]
    rejects(fields, field, "must have . dims")


def test_wrong_trailing_sizes():
    fields = base()
    Traversal(**fields)
    rejects({**fields, "walls": np.zeros((1, 3))}, "walls", r"\(W, 4\)")
    rejects({**fields, "poses": np.zeros((3, 2))}, "poses", r"\(3, 3\)")
    rejects({**fields, "controls": np.zeros((2, 0))}, "controls", r"\(T-1, D_u\)")
    rejects(
        {**fields, "timestamps": np.array([0.0, 2.0, 1.0])}, "timestamps", "decreases at step 2"
    )
    rejects({**fields, "images": np.full((3, 4, 4), 2.0)}, "images", r"\[0, 1\]")
    rejects({**fields, "metadata": ["not", "a", "dict"]}, "metadata", "must be a dict")


# ----------------------------------------------------------------- dtypes and empties
BAD_ARRAYS = [
    np.array([["a", "b"], ["c", "d"]]),
    np.array([[True, False], [True, True]]),
    np.array([[1 + 2j, 0j], [0j, 1j]]),
    np.array([[object(), None], [1, 2]], dtype=object),
]


@pytest.mark.parametrize("bad", BAD_ARRAYS, ids=["str", "bool", "complex", "object"])
@pytest.mark.parametrize("field", ["observations", "controls", "poses"])
def test_wrong_dtypes(field, bad):
    fields = base(poses=np.zeros((3, 3)))
    fields[field] = bad
    rejects(fields, field, "must be numeric, got dtype")


@pytest.mark.parametrize("bad", ["far", None, np.array([1.0, 2.0]), np.array("1.0"), 1 + 1j])
def test_max_range_must_be_a_number(bad):
    fields = base(max_range=bad)
    rejects(fields, "max_range", "must be a number")


def test_mask_must_be_boolean():
    fields = base(obs_mask=np.ones((3, 2), dtype=int))
    rejects(fields, "obs_mask", "must be bool")


@pytest.mark.parametrize(
    "obs, pattern", [(np.zeros((0, 4)), "empty"), (np.zeros((3, 0)), "0 beams"), ([], "2 dims")]
)
def test_empty_sequences(obs, pattern):
    fields = base(observations=obs, beam_angles=np.zeros(4))
    rejects(fields, "observations", pattern)


def test_validate_names_the_source():
    tr = Traversal(np.full((2, 1), 0.5), np.zeros((1, 2)), np.zeros((0, 4)), np.zeros(1), 1.0)
    tr.controls = np.zeros((5, 2))
    with pytest.raises(DatasetError, match=r"^my-log: field 'controls'"):
        validate(tr, "my-log")


# ------------------------------------------------------------------------------- files
@pytest.fixture(scope="module")
def good_file(tmp_path_factory):
    rng = np.random.default_rng(0)
    tr = Traversal(
        observations=rng.uniform(0, 1, (20, 6)).astype(np.float32),
        controls=rng.normal(size=(19, 2)),
        walls=rng.uniform(0, 1, (3, 4)),
        beam_angles=np.linspace(0, 6, 6),
        max_range=1.0,
        poses=rng.normal(size=(20, 3)),
        metadata={"name": "good"},
    )
    path = tr.save(tmp_path_factory.mktemp("data") / "good.npz")
    return tr, path.read_bytes()


def load_bytes(raw: bytes):
    """``load`` on a file holding ``raw``; returns the traversal or the DatasetError's text."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "broken.npz"
        path.write_bytes(raw)
        try:
            return load(path)
        except DatasetError as e:
            msg = str(e)
            assert msg.startswith(str(path) + ": "), msg  # names the file
            return msg


def same(a: Traversal, b: Traversal) -> bool:
    return all(
        np.array_equal(getattr(a, k), getattr(b, k))
        for k in ("observations", "controls", "walls", "beam_angles", "poses")
    )


@SETTINGS
@given(st.data())
def test_truncated_files(good_file, data):
    tr, raw = good_file
    n = data.draw(st.integers(0, len(raw) - 1))
    assert isinstance(load_bytes(raw[:n]), str)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_corrupted_files_fail_cleanly_or_load_unchanged(good_file, data):
    """A flipped bit either raises DatasetError or hits a byte that does not matter (zip
    timestamps, ...): never another exception, never silently different data."""
    tr, raw = good_file
    i = data.draw(st.integers(0, len(raw) - 1))
    bit = data.draw(st.integers(0, 7))
    b = bytearray(raw)
    b[i] ^= 1 << bit
    out = load_bytes(bytes(b))
    assert isinstance(out, str) or same(out, tr)


def test_every_encrypted_flag_bit_fails_cleanly(good_file):
    """Each zip member flagged "encrypted" (bit 0 of the central directory's flags, the case
    hypothesis found: zipfile raises RuntimeError asking for a password) -> DatasetError."""
    _, raw = good_file
    offsets = [i for i in range(len(raw) - 4) if raw[i : i + 4] == b"PK\x01\x02"]
    assert offsets
    for off in offsets:
        b = bytearray(raw)
        b[off + 8] |= 1  # general purpose bit flag, bit 0: encrypted
        out = load_bytes(bytes(b))
        assert isinstance(out, str) and "RuntimeError" in out, out


def test_dropped_directory_entries_fail_cleanly(good_file):
    """A corrupted comment length in a central-directory entry makes zipfile stop reading
    the directory there without an error, dropping the members after it (hypothesis found
    it: ``poses`` vanished silently); the end record's member count catches it."""
    _, raw = good_file
    last = raw.rfind(b"PK\x01\x02")
    second_last = raw.rfind(b"PK\x01\x02", 0, last)
    b = bytearray(raw)
    b[second_last + 32 : second_last + 34] = (0xFFF0).to_bytes(2, "little")  # comment length
    out = load_bytes(bytes(b))
    assert isinstance(out, str) and "members" in out, out


@SETTINGS
@given(st.binary(max_size=300))
def test_garbage_files(raw):
    assert isinstance(load_bytes(raw), str)


def test_structurally_wrong_files(tmp_path, good_file):
    tr, raw = good_file
    with pytest.raises(FileNotFoundError, match="no such dataset file"):
        load(tmp_path / "missing.npz")
    np.save(tmp_path / "array.npy", np.zeros(3))
    (tmp_path / "array.npz").write_bytes((tmp_path / "array.npy").read_bytes())
    with pytest.raises(DatasetError, match=r"array\.npz: not a \.npz dataset"):
        load(tmp_path / "array.npz")

    def rewrite(name, **changes):
        (tmp_path / "src.npz").write_bytes(raw)
        with np.load(tmp_path / "src.npz") as f:
            arrays = {k: f[k] for k in f.files}
        arrays.update(changes)
        for k in [k for k, v in arrays.items() if v is None]:
            del arrays[k]
        np.savez(tmp_path / name, **arrays)
        return tmp_path / name

    cases = [
        (rewrite("a.npz", controls=None), "missing field\\(s\\) 'controls'"),
        (rewrite("b.npz", metadata=np.asarray("{not json")), "'metadata' is not valid JSON"),
        (rewrite("c.npz", metadata=np.asarray("[1, 2]")), "'metadata' must be a dict"),
        (rewrite("d.npz", format_version=np.asarray(99)), "format_version 99 is newer"),
        (rewrite("e.npz", max_range=np.ones(2)), "'max_range' must be a scalar"),
        (rewrite("f.npz", observations=-np.ones((20, 6))), "'observations' has a negative"),
        (rewrite("g.npz", poses=np.zeros((19, 3))), "'poses' must have shape \\(20, 3\\)"),
        (
            rewrite("h.npz", observations=np.array([["x"] * 6] * 20)),
            "'observations' must be numeric",
        ),
        (rewrite("i.npz", beam_angles=np.zeros(5)), "'beam_angles' must have shape \\(6,\\)"),
    ]
    for path, pattern in cases:
        with pytest.raises(DatasetError, match=f"^{re.escape(str(path))}: .*{pattern}"):
            load(path)


@pytest.mark.parametrize("field, index", [("walls", 1), ("poses", 2), ("controls", 1)])
def test_a_point_far_from_the_rest_is_named_with_its_index(field, index):
    """A wall end, pose or control step far outside the rest of the data (corrupt, and it
    would size the map) is refused, naming the field and the index; the same values near the
    rest are fine."""
    walls = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 1.0, 1.0]])
    fields = base(walls=walls, poses=np.full((3, 3), 0.5), controls=np.zeros((2, 2)))
    far = {"walls": (1, 3), "poses": (2, 0), "controls": (1, 1)}[field]
    fields[field] = fields[field].copy()
    fields[field][far] = 5.0
    Traversal(**fields)
    fields[field][far] = 1e6
    rejects(fields, field, f"at index {index}")


def test_unknown_control_model_is_named():
    rejects(base(metadata={"control_model": "teleport"}), "metadata.control_model", "teleport")
    rejects(base(metadata={"control_model": "odometry_delta"}), "controls", "needs 3")
